"""Running a team: the agents in processes, the coordinator in this one
(:func:`run_multiprocess`, ``como3r run``), or over any transport (:func:`coordinate`,
``como3r coordinator``); the coordinator's loop is :mod:`.processes`. The output folder is
written atomically, the session store kept in it as the run goes, and a run is resumed
(``--resume``), continued by a restarted coordinator, or started on a saved map (``--map``)
here. A first Ctrl-C or SIGTERM stops the coordinator between two messages while agents
still run (:mod:`.interrupts`): the agents are stopped, the store is closed and
``OUT.partial`` is kept for ``--resume``; once every agent has ended and the keyframes are
handled, the outputs are written.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from como3r.config import Config
from como3r.data.agent_input import AgentInput
from como3r.errors import InputError
from como3r.heap import one_heap_arena
from como3r.io.output import atomic_output_dir
from como3r.live import LiveCallback
from como3r.progress import ProgressCallback
from como3r.runtime import outputs
from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.agent_worker import agent_process_main
from como3r.runtime.disk_guard import DiskGuard, store_metrics
from como3r.runtime.interrupts import interrupts_are_checkpoints
from como3r.runtime.map_session import SavedMap, hold_map, seed_map
from como3r.runtime.pipeline import (
    PriorSpec,
    RunSummary,
    open_agents,
    run_frames,
    warn_skipped_frames,
)
from como3r.runtime.processes import _Runtime
from como3r.runtime.results import SegmentedCoordinator, agent_results, left_out
from como3r.runtime.runtime_metrics import runtime_metrics
from como3r.runtime.runtime_state import restore_runtime
from como3r.store.reader import read_session, resumable
from como3r.store.resume import open_store
from como3r.store.schema import STORE_NAME
from como3r.transport.links import Hub
from como3r.transport.pipes import PipeHub


def run_multiprocess(
    agent_paths: Sequence[Path],
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
    options: RuntimeOptions | None = None,
    live: LiveCallback | None = None,
    resume: bool = False,
    saved_map: SavedMap | None = None,
) -> RunSummary:
    """Run every agent in its own process and the coordinator here; write the output folder.

    Same contract as :func:`como3r.runtime.pipeline.run`; ``metrics.json`` gains a
    ``runtime`` section (per-agent status, bytes per message type and direction).

    Args:
        agent_paths: one agent input per agent, in agent order.
        out: output folder (created atomically).
        config: effective configuration.
        prior_spec: which prior every process builds.
        overwrite: replace an existing non-empty output folder.
        progress: called with an agent's :class:`~como3r.progress.AgentProgress` after its
            every frame (as its ``FrameDone`` arrives) and when it fails, and with a
            :class:`~como3r.progress.PhaseEvent` as each step of the terminal work starts.
        options: runtime knobs (default :class:`RuntimeOptions`).
        live: called with the live events of :mod:`como3r.live` (a viewer): the agents'
            frame events as their messages arrive, the keyframe and map events from the
            coordinator here. Only this process calls it; agents send frame events only
            when it is given.
        resume: continue the killed run in ``out.partial`` from its session store
            (:mod:`como3r.store.resume`; the agents start again from the beginning).
        saved_map: a finished run's map to start from (``--map``, :mod:`.map_session`).

    Raises:
        InputError: bad agent input (checked here before any process starts), or every
            agent failed.
    """
    options = options or RuntimeOptions()
    inputs = open_agents(agent_paths, config)
    warn_skipped_frames(inputs, prior_spec.name)
    frames = [len(run_frames(a, config.input.subsample, prior_spec.name)) for a in inputs]
    hub = PipeHub(agent_process_main, options.max_message_bytes, options.shutdown_grace_s)
    return coordinate(
        hub,
        list(agent_paths),
        frames,
        out,
        config,
        prior_spec,
        options,
        inputs=inputs,
        overwrite=overwrite,
        progress=progress,
        live=live,
        resume=resume,
        saved_map=saved_map,
    )


def coordinate(
    hub: Hub,
    agent_paths: Sequence[Path | None],
    frames: Sequence[int],
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    options: RuntimeOptions,
    inputs: Sequence[AgentInput] = (),
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
    live: LiveCallback | None = None,
    resume: bool = False,
    continuing: bool = False,
    saved_map: SavedMap | None = None,
) -> RunSummary:
    """Run the coordinator here over the agents behind ``hub``; write the output folder.

    Args:
        hub: the transport to agents ``0 .. N-1``.
        agent_paths: each agent's input as its task names it; None where the agent brings
            its own (``como3r agent PATH``).
        frames: frames each agent will process where known (0: its ``AgentStarted`` says).
        out: output folder (created atomically).
        config: effective configuration (every agent receives it with its task).
        prior_spec: the prior of this process and of the agents' tasks.
        options: runtime knobs.
        inputs: the agent inputs where this process has them, for the evaluation against
            their ground truth and the lockstep schedule; empty: no evaluation.
        overwrite, progress, live, resume: as for :func:`run_multiprocess`.
        continuing: (with ``resume``) the agents ran on while this coordinator was down:
            take up the runtime's state from the store too (:mod:`.runtime_state`; ``como3r
            coordinator --resume``) instead of starting the agents again.
        saved_map: a finished run's map the agents start on; their ids follow its agents'.

    Raises:
        InputError: every agent failed.
        StoreError: (``resume``) a store that cannot be resumed.
    """
    one_heap_arena()  # before the verification pool's and the store's threads (.heap)
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, options.torch_threads))
    runtime: _Runtime | None = None
    interrupted = False
    try:
        # a finished store resumes with agents across machines only (como3r coordinator)
        finished = not isinstance(hub, PipeHub)
        with (
            interrupts_are_checkpoints(),
            atomic_output_dir(
                out,
                overwrite=overwrite,
                resume=resume,
                kept=lambda folder: resumable(folder, finished),
            ) as staging,
        ):
            guard = DiskGuard(config.session.disk_reserve_mb, progress)
            runtime = _Runtime(
                hub, frames, config, prior_spec, options, guard.progress, live, inputs, saved_map
            )
            if saved_map is not None and not resume:
                seed_map(runtime.coordinator, saved_map)
            session = read_session(staging / STORE_NAME, paged=True) if continuing else None
            for _ in range(
                runtime.coordinator.num_agents, len(session.agents) if session else 0
            ):  # map segments of restarted agents
                runtime.coordinator.add_agent()
            with open_store(staging, config, runtime.coordinator, resume, session) as store:
                runtime.store = store
                guard.watch(store)  # from here a disk filling up stops the run, resumably
                if saved_map is not None:
                    hold_map(runtime.coordinator, saved_map)
                if session is not None:
                    restore_runtime(runtime, session)
                runtime.start(agent_paths, prior_spec)
                runtime.run(finish_threads=threads)
                runtime.stop()
                if all(s.status == "failed" for s in runtime.slots):
                    raise InputError(
                        "every agent failed: "
                        + "; ".join(f"agent {s.agent}: {s.error}" for s in runtime.slots)
                    )
                summary = _write(staging, runtime, inputs)  # reads paged-out keyframes
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        if runtime is not None:
            runtime.stop(interrupted)
        torch.set_num_threads(threads)
    summary.out = out
    return summary


def _write(staging: Path, runtime: _Runtime, inputs: Sequence[AgentInput]) -> RunSummary:
    """The output folder of :func:`como3r.runtime.pipeline.run`, from the agents' results."""
    config = runtime.config
    results, runtime.places = agent_results(
        runtime.slots, runtime.segments, runtime.coordinator.components()
    )
    coordinator = SegmentedCoordinator(runtime.coordinator, runtime.places)
    seconds = [s.seconds for s in runtime.slots]
    metrics, components = outputs.write_run_files(
        staging, results, coordinator, config, runtime.prior.describe(), seconds, runtime.progress
    )
    metrics["runtime"] = runtime_metrics(runtime)
    metrics["store"] = None if runtime.store is None else store_metrics(runtime.store)
    summary = RunSummary(out=staging)
    for slot, s in zip(runtime.slots, seconds):
        summary.agents.append(
            {
                "agent": slot.agent,
                "status": slot.status,
                **outputs.agent_row(results[slot.agent], s),
            }
        )
        if slot.status == "failed":
            summary.notes.append(
                f"agent {slot.agent} failed: {slot.error}; its outputs hold the "
                f"{len(results[slot.agent].keyframes)} keyframes the coordinator received"
            )
    summary.notes.extend(left_out(runtime.segments, runtime.places))
    advice = None if runtime.verifiers is not None else runtime.backlog.advice(len(runtime.slots))
    if advice is not None:
        summary.notes.append(advice)
    outputs.evaluate_and_finish(
        staging,
        summary,
        metrics,
        [] if runtime.first else inputs,
        components,
        results,
        coordinator,
        config,
        runtime.progress,
    )
    return summary
