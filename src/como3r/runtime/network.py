"""A run across machines: ``como3r coordinator`` and ``como3r agent`` (manual:
docs/networked.md, "Across machines").

The coordinator (:func:`serve`) is the loop of :mod:`como3r.runtime.processes` over a
:class:`~como3r.transport.zenoh_hub.ZenohHub`; each agent (:func:`run_remote_agent`)
is the frame loop of :mod:`como3r.runtime.agent_worker` over a
:class:`~como3r.transport.zenoh_agent.ZenohAgentLink`. The coordinator owns the run's
configuration and sends it with every agent's task; an agent brings its input and its prior
files (its own paths, its own device).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from como3r.config import Config
from como3r.errors import InputError
from como3r.progress import ProgressCallback
from como3r.runtime.agent_worker import prior_fields, run_agent
from como3r.runtime.pipeline import PriorSpec, RunSummary, open_agents
from como3r.transport.spool import DEFAULT_MEMORY_BYTES, Spool
from como3r.transport.zenoh_agent import SendStatus, ZenohAgentLink
from como3r.transport.zenoh_protocol import Keys, ZenohOptions, open_session

if TYPE_CHECKING:  # an agent's process (``como3r agent``) needs no coordinator (~0.5 s CPU)
    from como3r.runtime.agent_events import RuntimeOptions
    from como3r.transport.zenoh_hub import ZenohHub

logger = logging.getLogger(__name__)


def serve(
    network: ZenohOptions,
    agents: int,
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    options: RuntimeOptions,
    ground_truth: Sequence[Path] = (),
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
    resume: bool = False,
) -> RunSummary:
    """Coordinate agents ``0 .. agents-1`` joining over Zenoh until each has finished or
    failed; write the output folder.

    Args:
        network: where to listen (and connect).
        agents: how many agents take part.
        out: output folder (created atomically).
        config: the run's configuration, sent to every agent.
        prior_spec: the prior of the coordinator (its name goes to the agents).
        options: runtime knobs (``agent_timeout_s`` also bounds the wait for an agent that
            never joins; ``away_timeout_s`` is how long an agent whose link is lost may take
            to reconnect or be restarted with its id).
        ground_truth: per agent, an input with ground truth to evaluate against (as
            ``como3r eval --gt``); empty: no evaluation.
        overwrite: replace an existing non-empty output folder.
        progress: as for :func:`~como3r.runtime.multiprocess.run_multiprocess`.
        resume: continue the coordinator that was killed (``out.partial``) from its session
            store; the agents still running re-send what it had not stored
            (:mod:`como3r.runtime.runtime_state`).

    Raises:
        InputError: bad ground truth, a network error, or every agent failed.
        StoreError: (``resume``) a store that cannot be resumed.
    """
    from como3r.runtime.multiprocess import coordinate
    from como3r.transport.zenoh_hub import ZenohHub

    if ground_truth and len(ground_truth) != agents:
        raise InputError(f"--gt: {len(ground_truth)} given for {agents} agents")
    inputs = open_agents(list(ground_truth), config) if ground_truth else []
    keys = Keys(network.session)
    session = open_session(network)
    hub: ZenohHub | None = None
    try:
        hub = ZenohHub(
            session,
            keys,
            agents,
            options.max_message_bytes,
            options.shutdown_grace_s,
            certified=network.member is not None,
            max_mbps=network.max_mbps,
        )
        logger.info("coordinator of %s: %s", keys.root, network.where())
        summary = coordinate(
            hub,
            [None] * agents,
            [0] * agents,
            out,
            config,
            prior_spec,
            options,
            inputs=inputs,
            overwrite=overwrite,
            progress=progress,
            resume=resume,
            continuing=resume,
        )
        _linger(hub, options.away_timeout_s)
        return summary
    finally:
        if hub is not None:
            hub.close()
        session.close()


def _linger(hub: ZenohHub, timeout_s: float) -> None:
    """The outputs written: wait (up to ``timeout_s``, or until Ctrl-C) for the agents
    that may not have their last acknowledgement (:meth:`ZenohHub.linger`)."""
    try:
        waiting = hub.linger(timeout_s)
    except KeyboardInterrupt:
        waiting = hub.unconfirmed()
    if waiting:
        logger.warning(
            "agent(s) %s did not confirm their last acknowledgement: their processes may "
            "still wait for it (the coordinator stored all their messages; stop them with "
            "Ctrl-C)",
            ", ".join(map(str, waiting)),
        )


def run_remote_agent(
    network: ZenohOptions,
    agent: int,
    path: Path,
    prior_spec: PriorSpec,
    threads: int | None = None,
    queue_memory_bytes: int = DEFAULT_MEMORY_BYTES,
    spill_dir: Path | None = None,
    on_status: Callable[[SendStatus], None] | None = None,
) -> bool:
    """Run agent ``agent`` on ``path`` for the coordinator reached through ``network``:
    wait for it, take its task, track every frame (on while the coordinator is away), and
    leave once the coordinator has stored the last message.

    A process started with the id of an agent whose earlier process left (crashed, killed)
    takes over: the coordinator's task makes it start after the last frame it heard of.

    Args:
        threads: torch threads of this agent (None: torch's default here).
        queue_memory_bytes: messages not yet stored by the coordinator kept in memory; more
            are spilled to disk.
        spill_dir: where the spill folder is made (None: the system's temporary folder).
        on_status: called with what was sent and what waits, every 10 s while messages
            wait to be put (``network.max_mbps`` caps the rate).

    Returns:
        Whether the agent ran to the end of its input without an error.

    Raises:
        InputError: a missing input, a network error, an id the coordinator does not
            have, or a prior other than the coordinator's.
    """
    if not path.exists():
        raise InputError(f"{path}: agent input does not exist")
    session = open_session(network)
    try:
        spool = Spool(queue_memory_bytes, spill_dir, label=f"agent-{agent}")
        link = ZenohAgentLink(
            session,
            Keys(network.session, network.member),
            agent,
            spool,
            where=network.where(),
            max_mbps=network.max_mbps,
            on_status=on_status,
        )
        task = link.fetch_task()
        if task.prior["name"] != prior_spec.name:
            link.close()
            raise InputError(
                f"--prior {prior_spec.name}: the coordinator runs --prior {task.prior['name']}"
            )
        task = dataclasses.replace(
            task,
            input_path=str(path),
            prior=prior_fields(prior_spec),
            torch_threads=threads if threads is not None else torch.get_num_threads(),
            log_level=logging.getLogger().getEffectiveLevel(),
        )
        logger.info(
            "agent %d: task received, running %s%s",
            agent,
            path,
            f" after frame {task.resume_after}" if task.resume_after >= 0 else "",
        )
        finished = run_agent(task, link)
        if on_status is not None:
            on_status(link.status())
        return finished
    finally:
        session.close()
