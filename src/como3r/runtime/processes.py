"""The coordinator's loop over agent processes (C-Sec. B.1, A.8), on any transport.

Each agent runs :class:`~como3r.runtime.agent_worker.AgentWorker` in its own process; the
coordinator runs here. They exchange only the messages of :mod:`como3r.transport.messages`,
carried by a :class:`~como3r.transport.links.Hub`:
:func:`~como3r.runtime.multiprocess.run_multiprocess` (``como3r run``) starts one process
per agent on this machine and talks to it over two one-way pipes
(:class:`~como3r.transport.pipes.PipeHub`); ``como3r coordinator`` serves agents started
on other machines over Zenoh (:mod:`como3r.runtime.network`). Both go through
:func:`~como3r.runtime.multiprocess.coordinate`, so the loop below is the same. (``spawn``
re-imports the caller's main module, so a script calling ``run_multiprocess`` needs an
``if __name__ == "__main__":`` guard; the ``como3r`` command has one.)

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

Failures. An agent that raises sends ``AgentFailed``; a child process that ends before
finishing is seen by its sentinel; one that stays silent longer than ``agent_timeout_s``
(nothing from it waiting to be read) is stopped. Each of these fails the agent: the failure
is logged, the coordinator keeps the keyframes it received, the other agents run to the end,
and the failed agent's outputs hold its keyframes only; ``metrics.json`` (``runtime``) and
``RunSummary.notes`` say so. Bytes that are not a valid message are logged and dropped.

Away and back (across machines). A networked agent whose link is lost (its liveliness
token gone: a crash, a Wi-Fi gap, or this process frozen past the Zenoh lease, which the
network cannot tell apart) is *away*, not failed: everything it sent is kept, its keyframes
no longer hold back the others' (the ordering above waits only for agents present), and it
has ``away_timeout_s`` to come back. The same process reconnecting continues where it was
(it re-sends what was not acknowledged; pose updates it may have missed are sent again). A
new process started with the same id takes over (:meth:`_Runtime.rejoin`): it starts after
the last frame the coordinator heard of, with a fresh map, as a new *map segment*, a
coordinator agent of its own. Its keyframes are associated with the agent's earlier map and
the others' by the same retrieval and dense verification as any two agents', and the gauge
merge puts it in their frame on the first verified edge: this re-localization needs no
protocol of its own, and a restarted agent that re-localizes nowhere is not forced into a
frame it cannot be placed in. The outputs join an agent's segments that share a gauge
component (:mod:`.results`). Past the timeout the agent fails as above; what it sends after
that is neither taken nor acknowledged.
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from como3r.config import Config, config_to_dict
from como3r.coordination.coordinator import Coordinator
from como3r.data.agent import AgentInput
from como3r.frontend.packets import PoseUpdate
from como3r.geometry.lie import sim3_compose, sim3_inverse
from como3r.live import FrameEvent, LiveCallback
from como3r.progress import (
    AgentProgress,
    PhaseCallback,
    ProgressCallback,
    report_phase,
    tracking_state,
)
from como3r.runtime.agent_worker import prior_fields
from como3r.runtime.interrupts import checkpoint, finishing
from como3r.runtime.live import CoordinatorLive
from como3r.runtime.map_session import SavedMap, map_results
from como3r.runtime.pipeline import (
    PriorSpec,
    _frame_schedule,
    build_prior,
    run_frames,
)
from como3r.runtime.results import (
    AgentResult,
    AgentSlot,
    EdgeView,
    MapSegment,
    MatchFraction,
    SegmentPlace,
    graph_view,
)
from como3r.runtime.runtime_state import snapshot
from como3r.store.writer import SessionStore
from como3r.transport import codec
from como3r.transport.keyframe_bytes import LOSSY_TRANSPORTS, PartCounter, wire_parts
from como3r.transport.links import Hub, Joined, Left, Received, Rejected, Traffic
from como3r.transport.messages import (
    AgentFailed,
    AgentFinished,
    AgentStarted,
    AgentTask,
    FrameDone,
    KeyframeMessage,
    PoseUpdateMessage,
    Step,
)

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
        away_timeout_s: how long a networked agent whose link is lost may stay away (to
            reconnect, or to be restarted with its id) before it counts as failed.
        shutdown_grace_s: how long a stopping agent may take before it is terminated.
    """

    lockstep: bool = False
    torch_threads: int = 1
    max_message_bytes: int = codec.DEFAULT_MAX_BYTES
    agent_timeout_s: float = 900.0
    away_timeout_s: float = 120.0
    shutdown_grace_s: float = 10.0


# ------------------------------------------------------------------------------ coordinator side


@dataclass(frozen=True)
class _Waiting:
    """A keyframe waiting for its turn, and its number in its sender's stream (None:
    pipes)."""

    segment: MapSegment
    message: KeyframeMessage
    seq: int | None


_LIVE = ("starting", "running")


class _Runtime:
    """Runs the coordinator loop over the agents, whatever carries their messages.

    Args:
        hub: the transport to the agents.
        frames: frames each agent ``0 .. N-1`` will process, where known before it starts
            (its ``AgentStarted`` says it otherwise).
        inputs: the agent inputs, where this process has them (the lockstep schedule).
        saved_map: a finished run's map the agents start on (``--map``): its agents are
            ``0 .. M-1`` (status ``"map"``: no process), the ones with processes follow.
    """

    def __init__(
        self,
        hub: Hub,
        frames: Sequence[int],
        config: Config,
        spec: PriorSpec,
        options: RuntimeOptions,
        progress: ProgressCallback | None,
        live: LiveCallback | None = None,
        inputs: Sequence[AgentInput] | None = None,
        saved_map: SavedMap | None = None,
    ) -> None:
        self.hub = hub
        self.inputs = inputs
        self.config = config
        self.options = options
        self.progress = progress
        self.live = live
        self.prior_name = spec.name
        self.prior, codebook = build_prior(spec, config)
        #: the id of the first agent with a process (the saved map's agents come first)
        self.first = 0 if saved_map is None else saved_map.agents
        self.coordinator = Coordinator(self.prior, config, codebook, self.first + len(frames))
        self.coordinator_live = (
            None
            if live is None
            else CoordinatorLive(live, self.coordinator, config.visualization.map_min_confidence)
        )
        #: keyframes waiting for their turn: ((timestamp, agent, kf_id, arrival), it)
        self.pending: list[tuple[tuple[float, int, int, int], _Waiting]] = []
        #: where the coordinator's state and this runtime's are kept (set by coordinate())
        self.store: SessionStore | None = None
        #: the coordinator's terminal alternation ran (a resumed coordinator's store says so)
        self.cleaned_up = False
        self._arrivals = 0
        #: bytes per part of the keyframe messages received, per agent (metrics.json)
        self.keyframe_parts: dict[int, PartCounter] = {}
        saved = [] if saved_map is None else map_results(saved_map)
        self.segments = [MapSegment(r.agent, r.agent, r) for r in saved] + [
            MapSegment(agent, agent, AgentResult(agent))
            for agent in range(self.first, self.first + len(frames))
        ]
        self.slots = [
            AgentSlot(
                r.agent,
                0,
                self.segments[r.agent],
                status="map",
                clock=math.inf,
                seconds=r.finished.seconds if r.finished else 0.0,
            )
            for r in saved
        ]
        self.slots += [
            AgentSlot(self.first + k, count, self.segments[self.first + k])
            for k, count in enumerate(frames)
        ]
        self.finish_threads = options.torch_threads
        self.tasks: dict[int, AgentTask] = {}
        self.places: dict[int, SegmentPlace] = {}

    def start(self, paths: Sequence[Path | None], spec: PriorSpec) -> None:
        """Hand each agent its task: its input (None: the agent brings its own) and the
        prior it builds."""
        self.tasks = {
            self.first + k: AgentTask(
                agent=self.first + k,
                input_path="" if path is None else str(path),
                config=config_to_dict(self.config),
                prior=prior_fields(spec),
                torch_threads=self.options.torch_threads,
                lockstep=self.options.lockstep,
                max_message_bytes=self.options.max_message_bytes,
                log_level=logging.getLogger().getEffectiveLevel(),
                live=self.live is not None,
            )
            for k, path in enumerate(paths)
        }
        self.hub.start(list(self.tasks.values()), self.rejoin)

    def rejoin(self, agent: int) -> AgentTask | str:
        """A new process takes over agent ``agent``'s id (the one before it left): its task,
        which starts after the last frame this coordinator heard of, on a new map segment
        (see the module docstring); or why it cannot (the agent finished or failed)."""
        slot = self.slots[agent]
        if slot.status in ("finished", "map"):
            return f"agent {agent} has finished in this run; it cannot start again"
        if slot.status == "failed":
            return f"agent {agent} failed in this run ({slot.error}); it cannot rejoin"
        old = slot.segment
        resume_after = max(
            [slot.last_frame]
            + [kf.frame_index for kf in old.result.keyframes]
            + [w.message.packet.frame_index for w in self._waiting(old)]
        )
        slot.handled_seq = -1  # the new process numbers its messages from 0
        if old.result.keyframes or self._waiting(old):
            index = self.coordinator.add_agent()
            slot.segment = MapSegment(index, agent, AgentResult(index), after_frame=resume_after)
            self.segments.append(slot.segment)
        else:  # its map is empty: the new process makes it
            old.after_frame = resume_after
        away = (
            ""
            if slot.away_since is None
            else f" after {time.monotonic() - slot.away_since:.1f} s away"
        )
        logger.warning(
            "agent %d: a new process takes over its id%s; it starts after frame %d "
            "on map segment %d (re-localized by cross-agent association)",
            agent,
            away,
            resume_after,
            slot.segment.index,
        )
        slot.away_since, slot.last_heard = None, time.monotonic()
        slot.restarts += 1
        return replace(self.tasks[agent], resume_after=resume_after)

    # ---------------------------------------------------------------- drivers

    def run(self, finish_threads: int) -> None:
        """Drive all agents to the end, then run the coordinator's cleanup; free-running,
        with ``finish_threads`` torch threads (lockstep keeps the serial schedule's one)."""
        if self.options.lockstep:
            self._run_lockstep()
        else:
            while any(s.expected() for s in self.slots):
                self._pump(0.5)
                self._process_pending()
                self._check_timeouts([s for s in self.slots if s.expected()])
            torch.set_num_threads(max(1, finish_threads))
        self.finish_threads = torch.get_num_threads()
        self._process_pending(force=True, progress=self.progress)
        finishing()  # every keyframe is handled: a first Ctrl-C now lets the outputs be written
        self._acknowledge()  # every keyframe is stored: finished agents may leave
        self._finish()

    def _run_lockstep(self) -> None:
        """Agents take turns in the single-process schedule (by timestamp, then agent)."""
        self._pump_until(lambda: all(s.status != "starting" for s in self.slots), self.slots)
        selected = [
            run_frames(a, self.config.input.subsample, self.prior_name) for a in self.inputs
        ]
        for k, index in _frame_schedule(self.inputs, selected):
            slot = self.slots[self.first + k]
            if slot.status != "running":
                continue
            self.hub.send(slot.agent, Step(index))
            slot.last_heard = time.monotonic()
            self._pump_until(lambda: slot.last_frame >= index or slot.status != "running", [slot])  # noqa: B023 (called here, in its loop)
            self._process_pending(force=True)
        self._pump_until(lambda: not any(s.expected() for s in self.slots), self.slots)

    def _pump_until(self, condition: Callable[[], bool], watched: Sequence[AgentSlot]) -> None:
        while not condition():
            self._pump(0.5)
            self._check_timeouts([s for s in watched if s.expected()])

    def _pump(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds for messages and departures, handle them, and
        acknowledge what was stored."""
        checkpoint()  # a first Ctrl-C or SIGTERM stops here: the store holds what was handled
        for event in self.hub.events(timeout):
            slot = self.slots[event.agent]
            if isinstance(event, Received):
                if slot.expected():  # a failed agent's trailing messages are ignored
                    slot.last_heard = time.monotonic()
                    self._received(slot, event)
            elif isinstance(event, Rejected):
                logger.warning("dropped a message from agent %d: %s", event.agent, event.error)
            elif isinstance(event, Joined):
                self._joined(slot)
            elif slot.expected():  # Left before its AgentFinished (or its re-sending)
                self._left(slot, event)
        self._acknowledge()

    def _received(self, slot: AgentSlot, event: Received) -> None:
        """Handle a message, unless the stored state has it already: a coordinator resumed
        from its store gets again what it had not acknowledged (:mod:`.runtime_state`), and
        of that takes only the keyframes it does not hold."""
        if event.seq is not None and event.seq >= slot.resend_until:
            slot.resend_until = -1  # caught up
        if event.seq is None or event.seq > slot.handled_seq:
            slot.handled_seq = slot.handled_seq if event.seq is None else event.seq
            self._handle(slot, event.message, event.seq)
            return
        message, segment = event.message, slot.segment
        if isinstance(message, KeyframeMessage) and message.packet.kf_id == (
            len(segment.result.keyframes) + len(self._waiting(segment))
        ):
            self._queue(segment, message, event.seq)

    def _waiting(self, segment: MapSegment) -> list[_Waiting]:
        return [w for _, w in self.pending if w.segment is segment]

    def _acknowledge(self) -> None:
        """Store this runtime's state, then acknowledge every message whose effect is
        stored: all handled, but for each agent none from its first keyframe still
        waiting for its turn on."""
        held = {}
        for _, waiting in self.pending:
            slot = self.slots[waiting.segment.agent]
            if waiting.segment is slot.segment and waiting.seq is not None:
                held[slot.agent] = min(held.get(slot.agent, waiting.seq), waiting.seq)
        if self.store is not None:
            self.store.record_runtime(
                snapshot(self, self.hub.durable(held)),
                {
                    s.index: s.result.finished
                    for s in self.segments
                    if s.result.finished is not None
                },
            )
        self.hub.acknowledge(held)

    def _left(self, slot: AgentSlot, event: Left) -> None:
        if not event.may_return or self.options.away_timeout_s <= 0:
            self._fail(slot, event.reason)
            return
        slot.away_since, slot.away_reason = time.monotonic(), event.reason
        slot.absences += 1
        logger.warning(
            "agent %d %s; it is away: kept for %.0f s to reconnect or restart with its id",
            slot.agent,
            event.reason,
            self.options.away_timeout_s,
        )
        self._report(slot, "away")

    def _joined(self, slot: AgentSlot) -> None:
        if slot.away_since is None:
            logger.info("agent %d joined", slot.agent)
            return
        logger.warning(
            "agent %d is back after %.1f s away", slot.agent, time.monotonic() - slot.away_since
        )
        slot.away_since, slot.last_heard = None, time.monotonic()
        segment = slot.segment  # updates sent while it was away may be lost: again
        for seq in range(segment.confirmed_seq + 1, segment.sent_seq + 1):
            update = segment.updates[seq - 1]
            self.hub.send(
                slot.agent, PoseUpdateMessage(update=replace(update, agent=slot.agent), seq=seq)
            )

    def _handle(self, slot: AgentSlot, message: Any, seq: int | None) -> None:
        agent = message.packet.agent if isinstance(message, KeyframeMessage) else message.agent
        if agent != slot.agent:
            logger.warning(
                "dropped a %s for agent %d from agent %d", type(message).__name__, agent, slot.agent
            )
        elif isinstance(message, AgentStarted):
            slot.status, slot.pid = "running", message.pid
            slot.frames_expected = slot.frames_done + message.frames
        elif isinstance(message, KeyframeMessage):
            self._queue(slot.segment, message, seq)
            slot.keyframes_received += 1
            self.keyframe_parts.setdefault(slot.agent, PartCounter()).add(
                wire_parts(message, lossy=self.hub.name in LOSSY_TRANSPORTS)
            )
            slot.segment.confirmed_seq = max(slot.segment.confirmed_seq, message.applied_seq)
        elif isinstance(message, FrameDone):
            self._frame_done(slot, message)
        elif isinstance(message, FrameEvent):
            if self.live is not None:
                self.live(message)
        elif isinstance(message, AgentFinished):
            slot.segment.result.finished = message
            slot.status, slot.clock = "finished", math.inf
            logger.info("agent %d finished its stream", slot.agent)
        elif isinstance(message, AgentFailed):
            if message.details:
                logger.error("agent %d traceback:\n%s", slot.agent, message.details)
            self._fail(slot, message.error)

    def _queue(self, segment: MapSegment, message: KeyframeMessage, seq: int | None) -> None:
        packet = message.packet
        heapq.heappush(
            self.pending,
            (
                (packet.timestamp, segment.agent, packet.kf_id, self._arrivals),
                _Waiting(segment, message, seq),
            ),
        )
        self._arrivals += 1

    def _frame_done(self, slot: AgentSlot, message: FrameDone) -> None:
        slot.clock, slot.last_frame = message.timestamp, message.frame_index
        slot.frames_done += 1
        slot.outcomes[message.outcome] += 1
        if message.outcome == "lost":
            slot.lost_frames.append(message.frame_index)
        slot.seconds += message.seconds
        slot.keyframes_waiting = message.keyframes_waiting
        self._report(slot, tracking_state(message.outcome))

    def _report(self, slot: AgentSlot, state: str) -> None:
        """The agent's progress, from its messages so far, to the progress callback."""
        if self.progress is not None:
            self.progress(
                AgentProgress(
                    slot.agent,
                    slot.frames_done,
                    slot.frames_expected,
                    slot.keyframes_received + slot.keyframes_waiting,
                    slot.outcomes["lost"],
                    slot.outcomes["relocalized"],
                    state,
                )
            )

    def _fail(self, slot: AgentSlot, error: str) -> None:
        slot.status, slot.error, slot.clock = "failed", error, math.inf
        slot.away_since, slot.resend_until = None, -1
        self._report(slot, "failed")
        if any(other.status != "failed" for other in self.slots):
            logger.error("agent %d failed: %s (the other agents continue)", slot.agent, error)
        else:  # the last one: the run ends in one error line naming every agent's failure
            logger.info("agent %d failed: %s", slot.agent, error)
        self.hub.drop(slot.agent)

    def _check_timeouts(self, watched: Sequence[AgentSlot]) -> None:
        """Fail the agents away for longer than ``away_timeout_s`` and those silent for
        longer than ``agent_timeout_s``. What an agent sent while this process was busy (a
        global BA can outlast the timeout) is read first: silence is the agent's, not the
        coordinator's deafness."""
        limit, now = self.options.agent_timeout_s, time.monotonic()
        if any(now - slot.last_heard > limit for slot in watched):
            self._pump(0.0)
        for slot in watched:
            now = time.monotonic()
            if not slot.expected():
                continue
            if slot.away_since is not None:
                if now - slot.away_since > self.options.away_timeout_s:
                    self._fail(
                        slot,
                        f"{slot.away_reason} and did not come back within "
                        f"{self.options.away_timeout_s:g} s",
                    )
            elif now - slot.last_heard > limit:
                self._fail(slot, f"no message for {limit:.0f} s (hung)")

    # ---------------------------------------------------------------- keyframes and updates

    def _process_pending(self, force: bool = False, progress: PhaseCallback | None = None) -> None:
        """Hand waiting keyframes to the coordinator in ``(timestamp, agent)`` order, each
        once no running agent present can still send an earlier one; ``progress`` hears of
        each (the backlog once the agents stopped: the coordinator may trail them by many)."""
        queued = len(self.pending)
        while self.pending:
            (timestamp, agent, _, _), waiting = self.pending[0]
            if not force and not all(
                (s.order_clock(), s.agent) > (timestamp, agent)
                for s in self.slots
                if s.agent != agent
            ):
                return
            checkpoint()  # between keyframes: a backlog can take long
            report_phase(
                progress,
                "queued keyframes",
                "retrieval, verification, global BA",
                queued - len(self.pending),
                queued,
            )
            heapq.heappop(self.pending)
            self._add_keyframe(waiting.segment, waiting.message)

    def _add_keyframe(self, segment: MapSegment, message: KeyframeMessage) -> None:
        packet, keyframes = message.packet, segment.result.keyframes
        if packet.kf_id != len(keyframes):
            self._fail(
                self.slots[segment.agent],
                f"protocol error: keyframe {packet.kf_id} after {len(keyframes)}",
            )
            return
        packet = replace(packet, agent=segment.index)
        stale = message.applied_seq < segment.sent_seq
        if stale and packet.kf_id > 0 and message.T_WC_previous is not None:
            # exported before the agent applied our latest update: keep the agent's relative
            # pose to its previous keyframe, on our pose of that keyframe (C-Sec. A.8)
            T_rel = sim3_compose(sim3_inverse(message.T_WC_previous), packet.T_WC)
            packet = replace(packet, T_WC=sim3_compose(keyframes[-1].T_WC.to(T_rel), T_rel))
            segment.reanchored += 1
        keyframes.append(
            graph_view(
                self.coordinator.graph,
                segment.index,
                packet.kf_id,
                packet.frame_index,
                packet.timestamp,
                packet.T_WC.clone(),
            )
        )
        updates = self.coordinator.add_keyframe(packet)
        for update in updates:
            self._send_update(update)
        if self.coordinator_live is not None:
            self.coordinator_live.keyframe_added(packet, updates)

    def _send_update(self, update: PoseUpdate) -> None:
        """Record a coordinator update of a segment, apply it to the segment's result and
        send it to the process running the segment (the agent's id in place of the
        segment's)."""
        segment = self.segments[update.agent]
        slot = self.slots[segment.agent]
        segment.sent_seq += 1
        segment.updates.append(update)
        segment.result.apply_pose_update(update)
        if slot.segment is segment and slot.status in _LIVE and slot.away_since is None:
            self.hub.send(
                slot.agent,
                PoseUpdateMessage(update=replace(update, agent=slot.agent), seq=segment.sent_seq),
            )

    # ---------------------------------------------------------------- the end

    def _finish(self) -> None:
        """Final pointmaps to the coordinator, the terminal alternation, final poses and
        refined pointmaps to the results (a resumed coordinator whose store holds the
        alternation's results settles the agents only)."""
        if self.cleaned_up:
            for slot in self.slots:
                self._settle(slot)
            return
        final_poses = {}
        for slot in self.slots:
            segment, done = slot.segment, slot.segment.result.finished
            if (
                done is not None
                and slot.status == "finished"
                and len(done.keyframe_T_WC) == len(segment.result.keyframes)
            ):  # else failed
                if done.final is not None:
                    self.coordinator.refresh(segment.index, done.final)
                final_poses[segment.index] = done.keyframe_T_WC
        cleanup = self.coordinator.finish(final_poses, self.progress)
        for update in cleanup.updates:
            self._send_update(update)
        for slot in self.slots:
            self._settle(slot)  # the refined pointmaps are the graph's, which views read
        if self.coordinator_live is not None:
            self.coordinator_live.finish([segment.result for segment in self.segments])

    def _settle(self, slot: AgentSlot) -> None:
        """A finished agent's own keyframe poses plus the updates it never applied."""
        segment = slot.segment
        result, done = segment.result, segment.result.finished
        if slot.status == "map":  # as the saved map holds it, with the updates it got
            return
        if slot.status != "finished" or done is None:
            result.finished = None
            return
        if len(done.keyframe_T_WC) != len(result.keyframes):
            slot.error = (
                f"reported {len(done.keyframe_T_WC)} keyframes but sent {len(result.keyframes)}"
            )
            slot.status, result.finished = "failed", None
            logger.error("agent %d: %s", slot.agent, slot.error)
            return
        for view, pose in zip(result.keyframes, done.keyframe_T_WC):
            view.T_WC = pose.clone()
        for update in segment.updates[done.applied_seq :]:
            result.apply_pose_update(update)
        result.stats = done.stats
        result.edges = [
            EdgeView(e.i, e.j, e.kind, MatchFraction(e.match_fraction)) for e in done.edges
        ]

    def _segments_of(self, agent: int) -> list[MapSegment]:
        return [segment for segment in self.segments if segment.agent == agent]

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
            channel = Traffic() if slot.status == "map" else self.hub.traffic(slot.agent)
            by_type.update(channel.bytes_sent)
            by_type.update(channel.bytes_received)
            segments = self._segments_of(slot.agent)
            agents.append(
                {
                    "agent": slot.agent,
                    "status": slot.status,
                    "error": slot.error,
                    "pid": slot.pid,
                    "exitcode": None if slot.status == "map" else self.hub.exitcode(slot.agent),
                    "frames_expected": slot.frames_expected,
                    "frames_done": slot.frames_done,
                    "keyframes_received": sum(len(s.result.keyframes) for s in segments),
                    "pose_updates_sent": sum(s.sent_seq for s in segments),
                    "keyframes_reanchored": sum(s.reanchored for s in segments),
                    "times_away": slot.absences,
                    "restarts": slot.restarts,
                    "map_segments": [
                        {
                            "segment": s.index,
                            "after_frame": s.after_frame,
                            "keyframes": len(s.result.keyframes),
                            "in_outputs": s.index in self.places,
                        }
                        for s in segments
                    ],
                    "bytes_to_agent": dict(channel.bytes_sent),
                    "bytes_from_agent": dict(channel.bytes_received),
                    "messages_to_agent": dict(channel.messages_sent),
                    "messages_from_agent": dict(channel.messages_received),
                    "keyframe_bytes_by_part": self.keyframe_parts.get(
                        slot.agent, PartCounter()
                    ).per_keyframe(),
                }
            )
        return {
            "mode": "multiprocess",
            "transport": self.hub.name,
            "lockstep": self.options.lockstep,
            "torch_threads": self.options.torch_threads,
            "finish_torch_threads": self.finish_threads,
            "max_message_bytes": self.options.max_message_bytes,
            "agents": agents,
            "bytes_by_type": dict(by_type),
            "bytes_total": sum(by_type.values()),
            "failed_agents": [s.agent for s in self.slots if s.status == "failed"],
        }
