"""The coordinator's side of its agents' messages (:mod:`.processes`): what arrives through
the transport, event by event, into the agents' slots, and what the runtime acknowledges.

Failures. An agent that raises sends ``AgentFailed``; a child process that ends before
finishing is seen by its sentinel; one that stays silent longer than ``agent_timeout_s``
(nothing from it waiting to be read) is stopped. Each of these fails the agent: the failure
is logged, the coordinator keeps the keyframes it received, the other agents run to the end,
and the failed agent's outputs hold its keyframes only; ``metrics.json`` (``runtime``) and
``RunSummary.notes`` say so. Bytes that are not a valid message are logged and dropped.

Away and back (across machines). A networked agent whose link is lost (its liveliness
token gone: a crash, a Wi-Fi gap, or this process frozen past the Zenoh lease, which the
network cannot tell apart) is *away*, not failed: everything it sent is kept, its keyframes
no longer hold back the others' (the ordering of :mod:`.processes` waits only for agents
present; after a coordinator restart it waits for those that were present, which come back
in seconds, and for what they re-send: the order then does not depend on which reconnects
or re-sends first, :mod:`.runtime_state`), and it has
``away_timeout_s`` to come back. The same process reconnecting continues where it was
(it re-sends what was not acknowledged; pose updates it may have missed are sent again). A
new process started with the same id takes over (:meth:`~.processes._Runtime.rejoin`): it starts after
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from como3r.live import FrameEvent, LiveCallback
from como3r.progress import AgentProgress, ProgressCallback, tracking_state
from como3r.runtime.interrupts import checkpoint
from como3r.runtime.results import AgentSlot, MapSegment
from como3r.runtime.runtime_state import snapshot
from como3r.store.writer import SessionStore
from como3r.transport import codec
from como3r.transport.keyframe_bytes import PartCounter
from como3r.transport.links import Event, Hub, Joined, Left, Received, Rejected
from como3r.transport.messages import (
    AgentFailed,
    AgentFinished,
    AgentStarted,
    FrameDone,
    KeyframeMessage,
    PoseUpdateMessage,
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


@dataclass(frozen=True)
class Waiting:
    """A keyframe waiting for its turn, and its number in its sender's stream (None:
    pipes), held as the bytes it came in where the transport kept them (issue 41: a
    512x384 keyframe is 1.2 MB on the wire and 15 MB decoded; a coordinator trailing a team
    of 16 by 50 keyframes held 0.8 GB of them decoded), decoded again when its turn comes.

    Attributes:
        frame_index: the keyframe's frame.
        held: the decoded message where no bytes were kept, else None.
        data: the message's bytes, else None.
        max_bytes: the size cap its decode checks.
    """

    segment: MapSegment
    seq: int | None
    frame_index: int
    held: KeyframeMessage | None
    data: bytes | None
    max_bytes: int

    @classmethod
    def of(
        cls,
        segment: MapSegment,
        message: KeyframeMessage,
        seq: int | None,
        data: bytes | None,
        max_bytes: int,
    ) -> Waiting:
        """``message`` waiting, as its ``data`` where given (the message is let go of)."""
        held = message if data is None else None
        return cls(segment, seq, message.packet.frame_index, held, data, max_bytes)

    def message(self) -> tuple[KeyframeMessage, float]:
        """The message, and the CPU seconds decoding it took on this thread (0 if held)."""
        if self.held is not None:
            return self.held, 0.0
        assert self.data is not None
        start = time.thread_time()
        message = codec.decode(self.data, max_bytes=self.max_bytes, expected=KeyframeMessage)
        return message, time.thread_time() - start


class AgentEvents:
    """The agents' events handled for the runtime (:class:`~.processes._Runtime` is one),
    over the state it sets up."""

    hub: Hub
    options: RuntimeOptions
    progress: ProgressCallback | None
    live: LiveCallback | None
    slots: list[AgentSlot]
    segments: list[MapSegment]
    #: keyframes waiting for their turn: ((timestamp, agent, kf_id, arrival), it)
    pending: list[tuple[tuple[float, int, int, int], Waiting]]
    store: SessionStore | None
    keyframe_parts: dict[int, PartCounter]
    _arrivals: int

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
            if self._verifier_event(event):  # also from an agent whose stream has ended
                continue
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

    def _verifier_event(self, event: Event) -> bool:
        """Whether ``event`` was a verification reply or the departure of an agent
        process that served verification, taken here (:mod:`.remote_verification`); no
        such event without verification on the agents."""
        return False

    def _received(self, slot: AgentSlot, event: Received) -> None:
        """Handle a message, unless the stored state has it already: a coordinator resumed
        from its store gets again what it had not acknowledged (:mod:`.runtime_state`), and
        of that takes only the keyframes it does not hold."""
        if event.seq is not None and slot.resend_until >= 0:
            if event.seq >= slot.resend_until:
                slot.resend_until = -1  # caught up: its stored clock orders again
            elif isinstance(event.message, KeyframeMessage):  # the next ones come after it
                slot.resent_clock = max(slot.resent_clock, event.message.packet.timestamp)
        if event.seq is None or event.seq > slot.handled_seq:
            slot.handled_seq = slot.handled_seq if event.seq is None else event.seq
            self._handle(slot, event.message, event.seq, event.data)
            return
        message, segment = event.message, slot.segment
        if isinstance(message, KeyframeMessage) and message.packet.kf_id == (
            len(segment.result.keyframes) + len(self._waiting(segment))
        ):
            self._queue(segment, message, event.seq, event.data)

    def _waiting(self, segment: MapSegment) -> list[Waiting]:
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
        slot.away_since, slot.last_heard, slot.awaited = None, time.monotonic(), False
        segment = slot.segment  # updates sent while it was away may be lost: again
        for seq in range(segment.confirmed_seq + 1, segment.sent_seq + 1):
            update = segment.updates[seq - 1]
            self.hub.send(
                slot.agent, PoseUpdateMessage(update=replace(update, agent=slot.agent), seq=seq)
            )

    def _handle(
        self, slot: AgentSlot, message: Any, seq: int | None, data: bytes | None = None
    ) -> None:
        agent = message.packet.agent if isinstance(message, KeyframeMessage) else message.agent
        if agent != slot.agent:
            logger.warning(
                "dropped a %s for agent %d from agent %d", type(message).__name__, agent, slot.agent
            )
        elif isinstance(message, AgentStarted):
            slot.status, slot.pid = "running", message.pid
            slot.frames_expected = slot.frames_done + message.frames
        elif isinstance(message, KeyframeMessage):
            self._queue(slot.segment, message, seq, data)
            slot.keyframes_received += 1
            slot.segment.confirmed_seq = max(slot.segment.confirmed_seq, message.applied_seq)
        elif isinstance(message, FrameDone):
            self._frame_done(slot, message)
        elif isinstance(message, FrameEvent):
            if self.live is not None:
                self.live(message)
        elif isinstance(message, AgentFinished):
            slot.segment.result.finished = message
            self.keyframe_parts.setdefault(slot.agent, PartCounter()).add_totals(
                message.keyframe_bytes_by_part, message.keyframes_measured
            )  # the agent measured its keyframe messages as it encoded them
            slot.status, slot.clock = "finished", math.inf
            logger.info("agent %d finished its stream", slot.agent)
        elif isinstance(message, AgentFailed):
            if message.details:
                logger.error("agent %d traceback:\n%s", slot.agent, message.details)
            self._fail(slot, message.error)

    def _queue(
        self,
        segment: MapSegment,
        message: KeyframeMessage,
        seq: int | None,
        data: bytes | None = None,
    ) -> None:
        """Let a keyframe wait for its turn, as ``data`` (its bytes) where given."""
        packet = message.packet
        heapq.heappush(
            self.pending,
            (
                (packet.timestamp, segment.agent, packet.kf_id, self._arrivals),
                Waiting.of(segment, message, seq, data, self.options.max_message_bytes),
            ),
        )
        self._arrivals += 1

    def _frame_done(self, slot: AgentSlot, message: FrameDone) -> None:
        """Count a processed frame; it moves the agent's ordering clock to its timestamp,
        unless keyframes made earlier still wait in the agent (a self-calibrated camera's
        first ones, :meth:`~como3r.frontend.agent.AgentFrontend.settle_camera`): the clock
        then stays at the frame that made the oldest of them, which is sent with its own
        timestamp later, so no other agent's later keyframe is taken before it."""
        if not (message.keyframes_waiting and slot.keyframes_waiting):
            slot.clock = message.timestamp
        slot.last_frame = message.frame_index
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
