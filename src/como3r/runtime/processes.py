"""The coordinator's loop over agent processes (C-Sec. B.1, A.8), on any transport.

Each agent runs :class:`~como3r.runtime.agent_worker.AgentWorker` in its own process; the
coordinator runs here. They exchange only the messages of :mod:`como3r.runtime.messages`,
carried by a :class:`~como3r.runtime.transport.Hub`: :func:`run_multiprocess` (``como3r
run``) starts one process per agent on this machine and talks to it over two one-way pipes
(:class:`~como3r.runtime.transport.PipeHub`); ``como3r coordinator`` serves agents started
on other machines over Zenoh (:mod:`como3r.runtime.network`). Both go through
:func:`coordinate`, so the loop below is the same. (``spawn`` re-imports the caller's main
module, so a script calling :func:`run_multiprocess` needs an ``if __name__ ==
"__main__":`` guard; the ``como3r`` command has one.)

The coordinator runs in the main process: that process would otherwise only wait on the
agents, it already needs the prior (to decode candidate pairs) and owns the output folder,
and a separate coordinator process would add a core's worth of contention on small
machines and one more serialization hop for every keyframe. While it solves, agents keep
tracking; their messages wait in the transport.

Ordering. The coordinator hands keyframes to :class:`Coordinator` in the order the
single-process runner does, by ``(timestamp, agent)``: a keyframe waits until every other
running agent has reported a frame at or after it (each agent's ``FrameDone`` is its
clock), so retrieval and verification see the same database in any run. Agents run free
and apply updates asynchronously, so a keyframe may be exported before its agent saw the
latest update; the coordinator then re-anchors it on its predecessor's current pose (the
relative pose is the agent's). Results therefore match the single-process run up to the
global solver's convergence. ``RuntimeOptions.lockstep`` additionally makes every agent wait
for a ``Step`` before each frame, in the single-process schedule, which reproduces
:func:`como3r.runtime.pipeline.run` (serially: for testing and debugging).

Failures. An agent that raises sends ``AgentFailed``; one that leaves (killed, crashed, its
link lost) is seen by the transport (process sentinel, liveliness token); one that stays
silent longer than ``agent_timeout_s`` (nothing from it waiting to be read) is stopped.
Either way the failure is logged, the coordinator keeps the keyframes it received, the
other agents run to the end, and the failed agent's outputs hold its keyframes only;
``metrics.json`` (``runtime``) and ``RunSummary.notes`` say so. Bytes that are not a valid
message are logged and dropped.
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from como3r.config import Config, config_to_dict
from como3r.coordination.coordinator import Coordinator
from como3r.data.agent import AgentInput
from como3r.errors import InputError
from como3r.frontend.agent import FrontendStats
from como3r.frontend.keyframes import apply_pointmap_update, apply_pose_update
from como3r.frontend.packets import PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.geometry.camera import to_focal
from como3r.geometry.lie import sim3_compose, sim3_inverse
from como3r.io.output import atomic_output_dir
from como3r.live import FrameEvent, LiveCallback
from como3r.progress import (
    AgentProgress,
    PhaseCallback,
    ProgressCallback,
    report_phase,
    tracking_state,
)
from como3r.runtime import codec, outputs
from como3r.runtime.agent_worker import agent_process_main, prior_fields
from como3r.runtime.live import CoordinatorLive
from como3r.runtime.messages import (
    AgentFailed,
    AgentFinished,
    AgentStarted,
    AgentTask,
    FrameDone,
    KeyframeMessage,
    PoseUpdateMessage,
    Step,
)
from como3r.runtime.pipeline import (
    PriorSpec,
    RunSummary,
    _frame_schedule,
    build_prior,
    open_agents,
)
from como3r.runtime.transport import Hub, Joined, PipeHub, Received, Rejected

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RuntimeOptions:
    """Knobs of the multi-process runtime.

    Attributes:
        lockstep: agents take turns in the single-process schedule (reproducible, serial).
        torch_threads: intra-op torch threads of every process (the main one while agents
            run; when free-running, its terminal work after the last agent stopped gets the
            caller's threads, the cores the agents no longer use: on 2 cores the demo's
            terminal refinement ran on one).
        max_message_bytes: size cap of one message.
        agent_timeout_s: a running agent silent for longer is terminated as hung.
        shutdown_grace_s: how long a stopping agent may take before it is terminated.
    """

    lockstep: bool = False
    torch_threads: int = 1
    max_message_bytes: int = codec.DEFAULT_MAX_BYTES
    agent_timeout_s: float = 900.0
    shutdown_grace_s: float = 10.0


# ------------------------------------------------------------------------------ results


@dataclass
class _KeyframeView:
    """What the outputs need of a keyframe, as received from its agent."""

    kf_id: int
    frame_index: int
    timestamp: float
    T_WC: Tensor
    X_hat: Tensor
    C_hat: Tensor
    colors: np.ndarray
    fused_frames: int = 1
    K: Tensor | None = None

    def rescale_focal(self, focal: float) -> None:
        """Move the pointmap to the focal length ``focal`` (as ``Keyframe.rescale_focal``)."""
        if self.K is not None:
            self.X_hat, self.K = to_focal(self.X_hat, self.K, focal)

    def mean_confidence(self) -> Tensor:
        """``(H, W)`` confidence per contributing frame (as ``Keyframe.mean_confidence``)."""
        return self.C_hat / self.fused_frames


@dataclass(frozen=True)
class _MatchFraction:
    match_fraction: float


@dataclass(frozen=True)
class _EdgeView:
    i: int
    j: int
    kind: str
    matches: _MatchFraction


@dataclass
class AgentResult:
    """An agent's results as the coordinator holds them: what :mod:`.outputs` reads of an
    :class:`~como3r.frontend.agent.AgentFrontend` (``agent``, ``keyframes``, ``edges``,
    ``stats``, ``trajectory()``, ``keyframe_trajectory()``).

    A finished agent's trajectory is composed from its anchored records (C-Sec. A.8); a
    failed agent's is its keyframes only.
    """

    agent: int
    keyframes: list[_KeyframeView] = field(default_factory=list)
    edges: list[_EdgeView] = field(default_factory=list)
    stats: FrontendStats = field(default_factory=FrontendStats)
    finished: AgentFinished | None = None

    def apply_pointmap_update(self, update: PointmapUpdate) -> None:
        """Take the coordinator's refined canonical pointmaps (C-Sec. A.7)."""
        apply_pointmap_update(self.keyframes, update)

    def apply_pose_update(self, update: PoseUpdate) -> None:
        """Listed keyframes take the new poses, newer ones follow the newest listed keyframe
        rigidly (:func:`~como3r.frontend.keyframes.apply_pose_update`)."""
        apply_pose_update(self.keyframes, update)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Every tracked frame: ``(frame indices (N,), timestamps (N,), T_WC (N, 8))``."""
        if self.finished is None:
            return self.keyframe_trajectory()
        done = self.finished
        if len(done.anchors) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), torch.zeros(0, 8)
        anchors = torch.stack([self.keyframes[int(a)].T_WC for a in done.anchors])
        return done.frame_indices, done.timestamps, sim3_compose(anchors, done.T_rel.to(anchors))

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Keyframes only: ``(frame indices, timestamps, T_WC (K, 8))``."""
        if not self.keyframes:
            return np.zeros(0, dtype=np.int64), np.zeros(0), torch.zeros(0, 8)
        return (np.array([kf.frame_index for kf in self.keyframes]),
                np.array([kf.timestamp for kf in self.keyframes]),
                torch.stack([kf.T_WC for kf in self.keyframes]))


# ------------------------------------------------------------------------------ coordinator side

_LIVE = ("starting", "running")


@dataclass
class _Slot:
    """The coordinator's view of one agent."""

    agent: int
    frames_expected: int
    result: AgentResult
    status: str = "starting"
    pid: int | None = None
    clock: float = -math.inf
    last_frame: int = -1
    frames_done: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    keyframes_received: int = 0
    seconds: float = 0.0
    sent_seq: int = 0
    updates: list[PoseUpdate] = field(default_factory=list)
    error: str | None = None
    last_heard: float = field(default_factory=time.monotonic)
    reanchored: int = 0


class _Runtime:
    """Runs the coordinator loop over the agents, whatever carries their messages.

    Args:
        hub: the transport to the agents.
        frames: frames each agent ``0 .. N-1`` will process, where known before it starts
            (its ``AgentStarted`` says it otherwise).
        inputs: the agent inputs, where this process has them (the lockstep schedule).
    """

    def __init__(self, hub: Hub, frames: Sequence[int], config: Config, spec: PriorSpec,
                 options: RuntimeOptions, progress: ProgressCallback | None,
                 live: LiveCallback | None = None,
                 inputs: Sequence[AgentInput] | None = None) -> None:
        self.hub = hub
        self.inputs = inputs
        self.config = config
        self.options = options
        self.progress = progress
        self.live = live
        self.prior, codebook = build_prior(spec, config)
        self.coordinator = Coordinator(self.prior, config, codebook, len(frames))
        self.coordinator_live = (
            None if live is None else
            CoordinatorLive(live, self.coordinator, config.visualization.map_min_confidence))
        self.pending: list[tuple[tuple[float, int, int, int], KeyframeMessage]] = []
        self._arrivals = 0
        self.slots = [_Slot(agent, count, AgentResult(agent)) for agent, count in enumerate(frames)]
        self.finish_threads = options.torch_threads

    def start(self, paths: Sequence[Path | None], spec: PriorSpec) -> None:
        """Hand each agent its task: its input (None: the agent brings its own) and the
        prior it builds."""
        self.hub.start([AgentTask(
            agent=agent, input_path="" if path is None else str(path),
            config=config_to_dict(self.config), prior=prior_fields(spec),
            torch_threads=self.options.torch_threads, lockstep=self.options.lockstep,
            max_message_bytes=self.options.max_message_bytes,
            log_level=logging.getLogger().getEffectiveLevel(), live=self.live is not None)
            for agent, path in enumerate(paths)])

    # ---------------------------------------------------------------- drivers

    def run(self, finish_threads: int) -> None:
        """Drive all agents to the end, then run the coordinator's cleanup; free-running,
        with ``finish_threads`` torch threads (lockstep keeps the serial schedule's one)."""
        if self.options.lockstep:
            self._run_lockstep()
        else:
            while any(s.status in _LIVE for s in self.slots):
                self._pump(0.5)
                self._process_pending()
                self._check_timeouts([s for s in self.slots if s.status in _LIVE])
            torch.set_num_threads(max(1, finish_threads))
        self.finish_threads = torch.get_num_threads()
        self._process_pending(force=True, progress=self.progress)
        self._finish()

    def _run_lockstep(self) -> None:
        """Agents take turns in the single-process schedule (by timestamp, then agent)."""
        self._pump_until(lambda: all(s.status != "starting" for s in self.slots), self.slots)
        for agent, index in _frame_schedule(self.inputs, self.config.input.subsample):
            slot = self.slots[agent]
            if slot.status != "running":
                continue
            self.hub.send(agent, Step(index))
            slot.last_heard = time.monotonic()
            self._pump_until(lambda: slot.last_frame >= index or slot.status != "running", [slot])
            self._process_pending(force=True)
        self._pump_until(lambda: all(s.status not in _LIVE for s in self.slots), self.slots)

    def _pump_until(self, condition: Callable[[], bool], watched: Sequence[_Slot]) -> None:
        while not condition():
            self._pump(0.5)
            self._check_timeouts([s for s in watched if s.status in _LIVE])

    def _pump(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for messages and departures, handle them, and
        acknowledge what was stored."""
        for event in self.hub.events(timeout):
            slot = self.slots[event.agent]
            if isinstance(event, Received):
                if slot.status in _LIVE:  # a failed agent's trailing messages are ignored
                    slot.last_heard = time.monotonic()
                    self._handle(slot, event.message)
            elif isinstance(event, Rejected):
                logger.warning("dropped a message from agent %d: %s", event.agent, event.error)
            elif isinstance(event, Joined):
                logger.info("agent %d joined", event.agent)
            elif slot.status in _LIVE:  # Left before its AgentFinished
                self._fail(slot, event.reason)
        self.hub.acknowledge()

    def _handle(self, slot: _Slot, message: Any) -> None:
        agent = message.packet.agent if isinstance(message, KeyframeMessage) else message.agent
        if agent != slot.agent:
            logger.warning("dropped a %s for agent %d from agent %d", type(message).__name__,
                           agent, slot.agent)
        elif isinstance(message, AgentStarted):
            slot.status, slot.pid = "running", message.pid
            slot.frames_expected = message.frames
        elif isinstance(message, KeyframeMessage):
            packet = message.packet
            heapq.heappush(self.pending, ((packet.timestamp, slot.agent, packet.kf_id,
                                           self._arrivals), message))
            self._arrivals += 1
            slot.keyframes_received += 1
        elif isinstance(message, FrameDone):
            self._frame_done(slot, message)
        elif isinstance(message, FrameEvent):
            if self.live is not None:
                self.live(message)
        elif isinstance(message, AgentFinished):
            slot.result.finished = message
            slot.status, slot.clock = "finished", math.inf
            logger.info("agent %d finished its stream", slot.agent)
        elif isinstance(message, AgentFailed):
            if message.details:
                logger.error("agent %d traceback:\n%s", slot.agent, message.details)
            self._fail(slot, message.error)

    def _frame_done(self, slot: _Slot, message: FrameDone) -> None:
        slot.clock, slot.last_frame = message.timestamp, message.frame_index
        slot.frames_done += 1
        slot.outcomes[message.outcome] += 1
        slot.seconds += message.seconds
        self._report(slot, tracking_state(message.outcome))

    def _report(self, slot: _Slot, state: str) -> None:
        """The agent's progress, from its messages so far, to the progress callback."""
        if self.progress is not None:
            self.progress(AgentProgress(slot.agent, slot.frames_done, slot.frames_expected,
                                        slot.keyframes_received, slot.outcomes["lost"],
                                        slot.outcomes["relocalized"], state))

    def _fail(self, slot: _Slot, error: str) -> None:
        slot.status, slot.error, slot.clock = "failed", error, math.inf
        self._report(slot, "failed")
        if any(other.status != "failed" for other in self.slots):
            logger.error("agent %d failed: %s (the other agents continue)", slot.agent, error)
        else:  # the last one: the run ends in one error line naming every agent's failure
            logger.info("agent %d failed: %s", slot.agent, error)
        self.hub.drop(slot.agent)

    def _check_timeouts(self, watched: Sequence[_Slot]) -> None:
        """Fail the agents silent for longer than ``agent_timeout_s``. What an agent sent
        while this process was busy (a global BA can outlast the timeout) is read first:
        silence is the agent's, not the coordinator's deafness."""
        limit = self.options.agent_timeout_s
        if any(time.monotonic() - slot.last_heard > limit for slot in watched):
            self._pump(0.0)
        for slot in watched:
            if slot.status in _LIVE and time.monotonic() - slot.last_heard > limit:
                self._fail(slot, f"no message for {limit:.0f} s (hung)")

    # ---------------------------------------------------------------- keyframes and updates

    def _process_pending(self, force: bool = False,
                         progress: PhaseCallback | None = None) -> None:
        """Hand waiting keyframes to the coordinator in ``(timestamp, agent)`` order, each
        once no running agent can still send an earlier one; ``progress`` hears of each
        (the backlog once the agents stopped: the coordinator may trail them by many)."""
        queued = len(self.pending)
        while self.pending:
            (timestamp, agent, _, _), message = self.pending[0]
            if not force and not all((s.clock, s.agent) > (timestamp, agent)
                                     for s in self.slots if s.agent != agent):
                return
            report_phase(progress, "queued keyframes", "retrieval, verification, global BA",
                         queued - len(self.pending), queued)
            heapq.heappop(self.pending)
            self._add_keyframe(self.slots[agent], message)

    def _add_keyframe(self, slot: _Slot, message: KeyframeMessage) -> None:
        packet, keyframes = message.packet, slot.result.keyframes
        if packet.kf_id != len(keyframes):
            self._fail(slot, f"protocol error: keyframe {packet.kf_id} after {len(keyframes)}")
            return
        stale = message.applied_seq < slot.sent_seq
        if stale and packet.kf_id > 0 and message.T_WC_previous is not None:
            # exported before the agent applied our latest update: keep the agent's relative
            # pose to its previous keyframe, on our pose of that keyframe (C-Sec. A.8)
            T_rel = sim3_compose(sim3_inverse(message.T_WC_previous), packet.T_WC)
            packet = replace(packet, T_WC=sim3_compose(keyframes[-1].T_WC.to(T_rel), T_rel))
            slot.reanchored += 1
        if packet.previous is not None:
            self._refresh_view(slot, packet.previous)
        keyframes.append(_KeyframeView(packet.kf_id, packet.frame_index, packet.timestamp,
                                       packet.T_WC.clone(), packet.X_hat, packet.C_hat,
                                       packet.colors, K=packet.K))
        updates = self.coordinator.add_keyframe(packet)
        for update in updates:
            self._send_update(update)
        if self.coordinator_live is not None:
            self.coordinator_live.keyframe_added(packet, updates)

    @staticmethod
    def _refresh_view(slot: _Slot, refresh: PointmapRefresh) -> None:
        view = slot.result.keyframes[refresh.kf_id]
        view.X_hat, view.C_hat, view.K = refresh.X_hat, refresh.C_hat, refresh.K
        view.fused_frames = refresh.fused_frames

    def _send_update(self, update: PoseUpdate) -> None:
        slot = self.slots[update.agent]
        slot.sent_seq += 1
        slot.updates.append(update)
        slot.result.apply_pose_update(update)
        if slot.status in _LIVE:
            self.hub.send(slot.agent, PoseUpdateMessage(update=update, seq=slot.sent_seq))

    # ---------------------------------------------------------------- the end

    def _finish(self) -> None:
        """Final pointmaps to the coordinator, the terminal alternation, final poses and
        refined pointmaps to the results."""
        final_poses = {}
        for slot in self.slots:
            done = slot.result.finished
            if done is not None and slot.status == "finished":
                if done.final is not None:
                    self._refresh_view(slot, done.final)
                    self.coordinator.refresh(slot.agent, done.final)
                if len(done.keyframe_T_WC) == len(slot.result.keyframes):
                    final_poses[slot.agent] = done.keyframe_T_WC
        cleanup = self.coordinator.finish(final_poses, self.progress)
        for update in cleanup.updates:
            self._send_update(update)
        for slot in self.slots:
            self._settle(slot)
        for update in cleanup.pointmaps:
            self.slots[update.agent].result.apply_pointmap_update(update)
        if self.coordinator_live is not None:
            self.coordinator_live.finish([slot.result for slot in self.slots])

    def _settle(self, slot: _Slot) -> None:
        """A finished agent's own keyframe poses plus the updates it never applied."""
        result, done = slot.result, slot.result.finished
        if slot.status != "finished" or done is None:
            result.finished = None
            result.stats = FrontendStats(
                frames=slot.frames_done, lost=slot.outcomes["lost"],
                relocalized=slot.outcomes["relocalized"], keyframes=len(result.keyframes),
                tracked=slot.frames_done - slot.outcomes["lost"])
            return
        if len(done.keyframe_T_WC) != len(result.keyframes):
            slot.error = (f"reported {len(done.keyframe_T_WC)} keyframes but sent "
                          f"{len(result.keyframes)}")
            slot.status, result.finished = "failed", None
            logger.error("agent %d: %s", slot.agent, slot.error)
            return
        for view, pose in zip(result.keyframes, done.keyframe_T_WC):
            view.T_WC = pose.clone()
        for update in slot.updates[done.applied_seq:]:
            result.apply_pose_update(update)
        result.stats = done.stats
        result.edges = [_EdgeView(e.i, e.j, e.kind, _MatchFraction(e.match_fraction))
                        for e in done.edges]

    def stop(self, interrupted: bool = False) -> None:
        """Stop the agents still running and release the transport. ``interrupted``
        (Ctrl-C): terminate at once instead of asking and waiting (an agent still starting
        up would only read the request after its imports)."""
        self.hub.stop([s.agent for s in self.slots if s.status in _LIVE], interrupted)

    def runtime_metrics(self) -> dict[str, Any]:
        """Per-agent status and bytes exchanged per message type (both directions)."""
        agents = []
        by_type: Counter[str] = Counter()
        for slot in self.slots:
            channel = self.hub.traffic(slot.agent)
            by_type.update(channel.bytes_sent)
            by_type.update(channel.bytes_received)
            agents.append({
                "agent": slot.agent, "status": slot.status, "error": slot.error,
                "pid": slot.pid, "exitcode": self.hub.exitcode(slot.agent),
                "frames_expected": slot.frames_expected, "frames_done": slot.frames_done,
                "keyframes_received": len(slot.result.keyframes),
                "pose_updates_sent": slot.sent_seq, "keyframes_reanchored": slot.reanchored,
                "bytes_to_agent": dict(channel.bytes_sent),
                "bytes_from_agent": dict(channel.bytes_received),
                "messages_to_agent": dict(channel.messages_sent),
                "messages_from_agent": dict(channel.messages_received),
            })
        return {"mode": "multiprocess", "transport": self.hub.name,
                "lockstep": self.options.lockstep,
                "torch_threads": self.options.torch_threads,
                "finish_torch_threads": self.finish_threads,
                "max_message_bytes": self.options.max_message_bytes,
                "agents": agents, "bytes_by_type": dict(by_type),
                "bytes_total": sum(by_type.values()),
                "failed_agents": [s.agent for s in self.slots if s.status == "failed"]}


# ------------------------------------------------------------------------------ entry point


def run_multiprocess(
    agent_paths: Sequence[Path],
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
    options: RuntimeOptions | None = None,
    live: LiveCallback | None = None,
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

    Raises:
        InputError: bad agent input (checked here before any process starts), or every
            agent failed.
    """
    options = options or RuntimeOptions()
    inputs = open_agents(agent_paths, config)
    frames = [len(range(0, a.num_frames, config.input.subsample)) for a in inputs]
    hub = PipeHub(agent_process_main, options.max_message_bytes, options.shutdown_grace_s)
    return coordinate(hub, list(agent_paths), frames, out, config, prior_spec, options,
                      inputs=inputs, overwrite=overwrite, progress=progress, live=live)


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
        overwrite, progress, live: as for :func:`run_multiprocess`.

    Raises:
        InputError: every agent failed.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, options.torch_threads))
    runtime: _Runtime | None = None
    interrupted = False
    try:
        with atomic_output_dir(out, overwrite=overwrite) as staging:
            runtime = _Runtime(hub, frames, config, prior_spec, options, progress, live,
                               inputs)
            runtime.start(agent_paths, prior_spec)
            runtime.run(finish_threads=threads)
            runtime.stop()
            if all(s.status == "failed" for s in runtime.slots):
                raise InputError("every agent failed: " + "; ".join(
                    f"agent {s.agent}: {s.error}" for s in runtime.slots))
            summary = _write(staging, runtime, inputs)
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
    """The output folder of :func:`pipeline.run`, from the agents' results."""
    config, coordinator = runtime.config, runtime.coordinator
    results = [s.result for s in runtime.slots]
    seconds = [s.result.finished.seconds if s.result.finished else s.seconds for s in runtime.slots]
    metrics, components = outputs.write_run_files(staging, results, coordinator, config,
                                                  runtime.prior.describe(), seconds,
                                                  runtime.progress)
    metrics["runtime"] = runtime.runtime_metrics()
    summary = RunSummary(out=staging)
    for slot, s in zip(runtime.slots, seconds):
        summary.agents.append({"agent": slot.agent, "status": slot.status,
                               **outputs.agent_row(slot.result, s)})
        if slot.status == "failed":
            summary.notes.append(
                f"agent {slot.agent} failed: {slot.error}; its outputs hold the "
                f"{len(slot.result.keyframes)} keyframes the coordinator received")
    outputs.evaluate_and_finish(staging, summary, metrics, inputs, components, results,
                                coordinator, config, runtime.progress)
    return summary
