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

Ordering. The coordinator hands keyframes to :class:`Coordinator` by ``(timestamp,
agent)``: a keyframe waits until every other running agent has reported a frame at or after
it (each agent's ``FrameDone`` is its clock; it stays back while the agent holds keyframes
made earlier, a self-calibrated camera's first ones), so retrieval sees the same database in
any run, and the coordinator verifies a batch in that order too, so which candidates a
keyframe verifies depends on the gauge merges before it only, as in one process. (The
single-process runner hands a self-calibrated agent's first keyframes over when it releases
them, after the other agents' keyframes of those frames: the first retrievals differ.) What
the batching still changes is when the in-stream global BA runs (once per batch) and so the
poses an edge is judged at and the agents track on. Agents run free
and apply updates asynchronously, so a keyframe may be exported before its agent saw the
latest update; the coordinator then re-anchors it on its predecessor's current pose (the
relative pose is the agent's). Results therefore match the single-process run up to the
global solver's convergence. ``RuntimeOptions.lockstep`` additionally makes every agent wait
for a ``Step`` before each frame, in the single-process schedule, and before ending its
stream, in agent order; after sending a keyframe it waits until the coordinator took it
(alone) and sent the updates it caused, so its next keyframe and its final report carry them
(a merge's gauge and focal length) as in one process. This reproduces
:func:`como3r.runtime.pipeline.run` (serially: for testing and debugging).

Failures, and agents away and back, are the agents' events (:mod:`.agent_events`).
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import torch

from como3r.config import Config, config_to_dict
from como3r.coordination.coordinator import Coordinator
from como3r.data.agent_input import AgentInput
from como3r.frontend.packets import KeyframePacket, PoseUpdate
from como3r.geometry.lie import sim3_compose, sim3_inverse
from como3r.live import LiveCallback
from como3r.progress import (
    PhaseCallback,
    ProgressCallback,
    report_phase,
)
from como3r.runtime.agent_events import AgentEvents, RuntimeOptions, Waiting
from como3r.runtime.agent_worker import END, TAKEN, prior_fields
from como3r.runtime.backlog import Backlog
from como3r.runtime.ingest import STAGE as INGEST
from como3r.runtime.ingest import received
from como3r.runtime.interrupts import checkpoint, finishing
from como3r.runtime.live import CoordinatorLive
from como3r.runtime.map_session import SavedMap, map_results
from como3r.runtime.pipeline import (
    PriorSpec,
    _frame_schedule,
    build_prior,
    run_frames,
)
from como3r.runtime.remote_verification import AgentVerifiers
from como3r.runtime.results import (
    AgentResult,
    AgentSlot,
    EdgeView,
    MapSegment,
    MatchFraction,
    SegmentPlace,
    graph_view,
)
from como3r.store.writer import SessionStore
from como3r.transport.keyframe_bytes import PartCounter
from como3r.transport.links import Event, Hub, Joined, Left, Received
from como3r.transport.messages import (
    AgentFinished,
    AgentStarted,
    AgentTask,
    KeyframeMessage,
    PoseUpdateMessage,
    Step,
)
from como3r.transport.verification_messages import VerificationReply

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ coordinator side


_LIVE = ("starting", "running")
#: a batch of waiting keyframes (``global_ba.max_batch_keyframes``) goes to the coordinator
#: in parts of at most this many, each its own transaction and page-out, the global BA after
#: the last (issue 41: while a batch is handled its keyframes are all in memory, 15 MB each
#: at 512x384 with the simulated prior's encodings, besides the working set). Measured with
#: benchmarks/team_scale.py (--sizes 4 16 --frames 48, session 40), 16 agents: whole batches
#: of 16 instead of 32 took the coordinator's peak 4496 -> 3942 MB, but its global BAs
#: 18 -> 25 and their time 33.8 -> 47.2 s; parts of 16 took it 4732 -> 4221 MB with the
#: BA's time as before (39.8 / 35.8 s), the 4-agent run's batches being smaller anyway
HANDOVER_KEYFRAMES = 16


class _Runtime(AgentEvents):
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
        self.pending: list[tuple[tuple[float, int, int, int], Waiting]] = []
        #: where the coordinator's state and this runtime's are kept (set by coordinate())
        self.store: SessionStore | None = None
        #: the coordinator's terminal alternation ran (a resumed coordinator's store says so)
        self.cleaned_up = False
        self._arrivals = 0
        #: how far the coordinator trails the agents (metrics.json: runtime.backlog)
        self.backlog = Backlog()
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
        #: the agents' processes verifying for the coordinator (verification.on_agents)
        self.verifiers = self._agent_verifiers()

    def _agent_verifiers(self) -> AgentVerifiers | None:
        """Verification on the agents where the configuration asks for it and the agents
        run free (a lockstep run keeps the single process's schedule)."""
        if not self.config.verification.on_agents:
            return None
        if self.options.lockstep:
            logger.warning(
                "verification.on_agents: a lockstep run keeps the serial schedule; the "
                "coordinator verifies itself"
            )
            return None
        return AgentVerifiers(self.coordinator, self.hub)

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
                send_encoding=not self.coordinator.encodings.can_reencode(self.first + k),
                verify=self.verifiers is not None,
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
            + [w.frame_index for w in self._waiting(old)]
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
        slot.away_since, slot.last_heard, slot.awaited = None, time.monotonic(), False
        slot.keyframes_waiting, slot.resend_until = 0, -1  # the old process's never come
        slot.restarts += 1
        return replace(
            self.tasks[agent],
            resume_after=resume_after,
            # the segment's keyframes arrive under its own id
            send_encoding=not self.coordinator.encodings.can_reencode(slot.segment.index),
        )

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
                if not self.pending:  # idle: one keyframe a batch budget deferred (.deferral)
                    for update in self.coordinator.verify_deferred_one():
                        self._send_update(update)
                self._check_timeouts([s for s in self.slots if s.expected()])
            if self.verifiers is not None:
                self.verifiers.out_at_end = self.verifiers.out
            torch.set_num_threads(max(1, finish_threads))
        self.finish_threads = torch.get_num_threads()
        self._process_pending(force=True, progress=self.progress)
        self._await_verifications()
        finishing()  # every keyframe is handled: a first Ctrl-C now lets the outputs be written
        self._acknowledge()  # every keyframe is stored: finished agents may leave
        self._finish()

    def _run_lockstep(self) -> None:
        """Agents take turns in the single-process schedule (by timestamp, then agent),
        then end their streams in agent order, as :func:`~.pipeline.run` does."""
        self._pump_until(lambda: all(s.status != "starting" for s in self.slots), self.slots)
        selected = [
            run_frames(a, self.config.input.subsample, self.prior_name) for a in self.inputs
        ]
        turns = [(self.first + k, index) for k, index in _frame_schedule(self.inputs, selected)]
        for agent, index in turns + [(slot.agent, END) for slot in self.slots]:
            if self.slots[agent].status == "running":
                self._turn(self.slots[agent], index)
        self._pump_until(lambda: not any(s.expected() for s in self.slots), self.slots)

    def _turn(self, slot: AgentSlot, index: int) -> None:
        """Lockstep: the agent's turn at frame ``index`` (``END``: its stream's end) until it
        reports the frame, finishes or fails; each keyframe it sends goes to the coordinator
        alone, as it arrives, and is answered by ``Step(TAKEN)`` after the updates it caused."""
        self.hub.send(slot.agent, Step(index))
        slot.last_heard = time.monotonic()
        while True:
            taken = len(self.pending)
            self._process_pending(force=True)
            for _ in range(taken if slot.status == "running" else 0):
                self.hub.send(slot.agent, Step(TAKEN))
            if slot.status != "running" or (index != END and slot.last_frame >= index):
                return
            self._pump(0.5)
            self._check_timeouts([slot])

    # ---------------------------------------------------------------- keyframes and updates

    def _received(self, slot: AgentSlot, event: Received) -> None:
        """A message, its decode charged to the coordinator's ingest where it is a keyframe
        or the final report (their lossy codings: :mod:`.ingest`); on pipes the CPU time of
        the reader thread that decoded it (:mod:`como3r.transport.pipe_readers`): the
        coordinator's process pays it, no longer its thread."""
        if isinstance(event.message, (KeyframeMessage, AgentFinished)):
            self.coordinator.stats.add_time(INGEST, event.seconds)
        super()._received(slot, event)

    def _process_pending(self, force: bool = False, progress: PhaseCallback | None = None) -> None:
        """Hand the waiting keyframes whose turn has come to the coordinator in batches
        (:meth:`~como3r.coordination.coordinator.Coordinator.add_keyframes`, at most
        ``global_ba.max_batch_keyframes`` each, in parts of :data:`HANDOVER_KEYFRAMES` with
        the global BA after the last), in ``(timestamp, agent)`` order, each once
        no running agent present can still send an earlier one (``force``: all of them).
        The backlog is sampled first (:mod:`.backlog`) and shown as the coordinator's line
        while agents run; ``progress`` hears of each batch (the backlog once the agents
        stopped: the coordinator may trail them by many)."""
        self._hand_over_verifications()
        ended = not any(s.expected() for s in self.slots)
        self.backlog.sample((key[0] for key, _ in self.pending), ended)
        if self.progress is not None and not ended and self.pending:
            report_phase(
                self.progress,
                "backlog",
                self.backlog.text(),
                self.backlog.handled,
                self.backlog.handled + len(self.pending),
            )
        queued, limit = len(self.pending), max(1, self.config.global_ba.max_batch_keyframes)
        while self.pending:
            checkpoint()  # between batches: a backlog can take long
            batch: list[Waiting] = []
            while self.pending and len(batch) < limit:
                (timestamp, agent, _, _), waiting = self.pending[0]
                if not force and not all(
                    (s.order_clock(), s.agent) > (timestamp, agent)
                    for s in self.slots
                    if s.agent != agent
                ):
                    break
                heapq.heappop(self.pending)
                batch.append(waiting)
            if not batch:
                return
            report_phase(
                progress,
                "queued keyframes",
                "retrieval, verification, global BA",
                queued - len(self.pending) - len(batch),
                queued,
            )
            for first in range(0, len(batch), HANDOVER_KEYFRAMES):
                last = first + HANDOVER_KEYFRAMES >= len(batch)
                self._add_keyframes(batch[first : first + HANDOVER_KEYFRAMES], solve=last)

    def _add_keyframes(self, batch: Sequence[Waiting], solve: bool = True) -> None:
        """One batch of keyframes to the coordinator (its global BA after it if ``solve``);
        its updates to the agents."""
        packets = []
        for waiting in batch:
            message, seconds = waiting.message()  # decoded again if held as its bytes
            self.coordinator.stats.add_time(INGEST, seconds)
            packet = self._packet(waiting.segment, message)
            if packet is not None:
                packets.append(received(packet, self.coordinator))
        if not packets:
            return
        updates = self.coordinator.add_keyframes(packets, solve)
        for update in updates:
            self._send_update(update)
        if self.verifiers is not None:
            self.verifiers.dispatch({s.segment.index: s.agent for s in self.slots})
        self.backlog.handed(packet.timestamp for packet in packets)
        if self.coordinator_live is not None:
            for k, packet in enumerate(packets):  # the map moved once, after the batch
                self.coordinator_live.keyframe_added(
                    packet, updates if k == len(packets) - 1 else []
                )

    def _packet(self, segment: MapSegment, message: KeyframeMessage) -> KeyframePacket | None:
        """The coordinator's packet of a received keyframe (its segment's agent id, re-anchored
        if it is stale), its view appended to the segment's result; None (the agent failed)
        for a keyframe out of order."""
        packet, keyframes = message.packet, segment.result.keyframes
        if packet.kf_id != len(keyframes):
            self._fail(
                self.slots[segment.agent],
                f"protocol error: keyframe {packet.kf_id} after {len(keyframes)}",
            )
            return None
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
        return packet

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

    # ---------------------------------------------------------------- verification on agents

    def _verifier_event(self, event: Event) -> bool:
        verifiers = self.verifiers
        if verifiers is None:
            return False
        if isinstance(event, Received) and isinstance(event.message, VerificationReply):
            self.slots[event.agent].last_heard = time.monotonic()
            self.coordinator.stats.add_time(INGEST, event.seconds)  # its matches' decode
            verifiers.received(event.agent, event.message)
            return True
        if isinstance(event, Received) and isinstance(event.message, AgentStarted):
            verifiers.join(event.agent)  # its task said verify (a process taking over too)
        elif isinstance(event, Joined) and self.slots[event.agent].status in _LIVE:
            verifiers.join(event.agent)  # back after it was away
        elif isinstance(event, Left) and event.agent in verifiers.serving:
            verifiers.left(event.agent)  # away or gone: its jobs are verified here
        return False

    def _fail(self, slot: AgentSlot, error: str) -> None:
        if self.verifiers is not None:
            self.verifiers.left(slot.agent)
        super()._fail(slot, error)

    def _hand_over_verifications(self, solve: bool = True) -> None:
        """The agents' verifications received so far to the coordinator; the updates they
        made to the agents. The global BA after them only if ``solve`` and no keyframe
        waits: else the next batch's BA solves with their edges (one BA per batch, as when
        the coordinator verifies: at 16 agents of benchmarks/team_scale.py a BA after every
        hand-over ran 32 BAs instead of 18, the coordinator's serial work per keyframe 297
        -> 451 ms)."""
        if self.verifiers is not None:
            for update in self.verifiers.hand_over(solve and not self.pending):
                self._send_update(update)

    def _await_verifications(self) -> None:
        """After the last keyframe: wait for the verifications still out (an agent process
        silent for ``agent_timeout_s`` has its jobs taken back: the coordinator verifies
        them), hand them over, and release the processes whose streams ended."""
        verifiers = self.verifiers
        if verifiers is None:
            return
        total = verifiers.out
        while verifiers.out:
            report_phase(
                self.progress,
                "verification on the agents",
                f"{verifiers.out} keyframe(s) out",
                total - verifiers.out,
                total,
            )
            self._pump(0.5)
            for agent in verifiers.overdue(self.options.agent_timeout_s):
                logger.warning(
                    "agent %d: no verification reply for %.0f s; the coordinator verifies "
                    "its keyframes",
                    agent,
                    self.options.agent_timeout_s,
                )
                verifiers.left(agent)
            self._hand_over_verifications(solve=False)
        self._hand_over_verifications(solve=False)  # the terminal cleanup solves
        if total:
            report_phase(self.progress, "verification on the agents", "done", total, total)
        verifiers.release(s.agent for s in self.slots if s.status == "finished")

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
                    self.coordinator.refresh(segment.index, received(done.final, self.coordinator))
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

    def stop(self, interrupted: bool = False) -> None:
        """Stop the agents still running and release the transport. ``interrupted``
        (Ctrl-C): terminate at once instead of asking and waiting (an agent still starting
        up would only read the request after its imports)."""
        if self.verifiers is not None and not interrupted:
            self.verifiers.release(s.agent for s in self.slots if s.status == "finished")
        self.hub.stop([s.agent for s in self.slots if s.status in _LIVE], interrupted)
