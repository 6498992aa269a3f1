"""The multi-process runtime's own state in the session store, and a coordinator taking it
up again (issue 14: ``como3r coordinator --resume``).

The coordinator's state (keyframes, poses, edges, gauges, pose updates made per agent) is
in the store after every message (:mod:`como3r.store.writer`). What the runtime of
:mod:`.processes` knows beside it goes there too, before every acknowledgement
(:meth:`~como3r.store.writer.SessionStore.record_runtime`): per agent its status, progress
counters and the number of the last message it handled; per map segment its agent and what
its process confirmed having applied; each agent process's final report
(:class:`~como3r.transport.messages.AgentFinished`); and the transport's state (who holds each
agent id, the stream position acknowledged: :meth:`~como3r.transport.links.Hub.durable`).

A coordinator killed at any moment and started again with ``--resume`` rebuilds from the
store (:func:`restore_runtime`): the segments' keyframes from the stored graph, the agents'
counters, their reports. Agents still running are *away* until their liveliness token is
seen again; they then re-send every message not acknowledged, of which the runtime takes
what the store does not have (:meth:`~como3r.runtime.processes._Runtime._received`). The
keyframes keep their ``(timestamp, agent)`` order across the restart: an agent that was
present orders them by its stored clock until it is back, and while it re-sends by the
latest keyframe it re-sent (:meth:`~.results.AgentSlot.order_clock`; its stored clock may be
past the keyframes the killed coordinator had not taken). Pose
updates the dead coordinator sent may have been lost on the way, and their contents are not
stored: each one an agent may still lack is replaced by the current poses of the agent's
keyframes, the state the last of them led to (an update carries all of an agent's keyframes
and the coordinator moves the keyframes of agents it updates only together with an update),
so the agent's update sequence stays gapless.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from typing import TYPE_CHECKING, Any, Protocol

from como3r.errors import StoreError
from como3r.runtime.results import AgentResult, AgentSlot, MapSegment, stored_views
from como3r.store.reader import Session

if TYPE_CHECKING:
    from como3r.coordination.coordinator import Coordinator
    from como3r.transport.links import Hub

logger = logging.getLogger(__name__)


class StatefulRuntime(Protocol):
    """What this module reads and restores of the multi-process runtime
    (:class:`~como3r.runtime.processes._Runtime`, which imports this module: it is named
    here by what it holds, not imported)."""

    slots: list[AgentSlot]
    segments: list[MapSegment]
    hub: Hub
    coordinator: Coordinator
    cleaned_up: bool


#: the counters of an agent slot kept as they are
SLOT_FIELDS = (
    "status",
    "pid",
    "frames_expected",
    "frames_done",
    "clock",
    "last_frame",
    "lost_frames",
    "keyframes_received",
    "keyframes_waiting",
    "seconds",
    "error",
    "absences",
    "restarts",
    "handled_seq",
)
#: the fields of a map segment kept as they are
SEGMENT_FIELDS = ("index", "agent", "after_frame", "confirmed_seq", "reanchored")


def snapshot(runtime: StatefulRuntime, hub: dict[str, Any]) -> dict[str, Any]:
    """The runtime's state beside the coordinator's (JSON-able).

    Args:
        runtime: the multi-process runtime.
        hub: its transport's state (:meth:`~como3r.transport.links.Hub.durable`).
    """
    return {
        "slots": [
            {
                **{name: getattr(slot, name) for name in SLOT_FIELDS},
                "outcomes": dict(slot.outcomes),
                "segment": slot.segment.index,
            }
            for slot in runtime.slots
        ],
        "segments": [
            {name: getattr(segment, name) for name in SEGMENT_FIELDS}
            for segment in runtime.segments
        ],
        "hub": hub,
    }


def restore_runtime(runtime: StatefulRuntime, session: Session) -> None:
    """Take up the stored runtime state in a new runtime whose coordinator has restored
    ``session`` already (before the runtime starts its transport).

    Raises:
        StoreError: the store holds no runtime state (not written by a coordinator of
            agent processes) or one of another number of agents.
    """
    state = session.runtime
    if state is None:
        raise StoreError(
            f"{session.path}: the stored session was not run by a coordinator "
            f"of agent processes; continue it with como3r run --resume"
        )
    if len(state["slots"]) != len(runtime.slots):
        raise StoreError(
            f"{session.path}: the stored session has {len(state['slots'])} "
            f"agents, this coordinator {len(runtime.slots)} (--agents)"
        )
    runtime.segments = [_segment(saved, runtime, session) for saved in state["segments"]]
    if [s.index for s in runtime.segments] != list(range(len(session.agents))):
        raise StoreError(
            f"{session.path}: inconsistent session store: the runtime's map "
            f"segments are not the coordinator's agents"
        )
    now = time.monotonic()
    for slot, saved in zip(runtime.slots, state["slots"]):
        for name in SLOT_FIELDS:  # (a store of an older version lacks keyframes_waiting)
            setattr(slot, name, saved.get(name, getattr(slot, name)))
        slot.outcomes = Counter(saved["outcomes"])
        slot.segment = runtime.segments[saved["segment"]]
        slot.last_heard = now
    runtime.cleaned_up = session.finished
    stored = runtime.hub.resume(state["hub"])
    for slot in runtime.slots:
        if stored.get(slot.agent, slot.handled_seq) < slot.handled_seq:
            slot.resend_until = slot.handled_seq  # even from a process that has finished
        if slot.expected():  # until its token is seen again
            slot.away_since, slot.away_reason = now, "not back since the coordinator restarted"
            # the order of the keyframes waits for it as before the restart: which agent
            # reconnects first must not decide what the others' keyframes are matched with
            slot.awaited = True
    away = [slot.agent for slot in runtime.slots if slot.away_since is not None]
    logger.warning(
        "coordinator resumed from %s: %d keyframes; waiting for agents %s to "
        "re-send what it had not stored",
        session.path,
        len(session.graph),
        away,
    )


def _segment(saved: dict[str, Any], runtime: StatefulRuntime, session: Session) -> MapSegment:
    """A map segment with its keyframes as the store holds them and its pose updates."""
    index = saved["index"]
    report = session.reports.get(index)
    segment = MapSegment(
        index,
        saved["agent"],
        AgentResult(index, stored_views(session.graph, index), finished=report),
        sent_seq=session.agents[index].updates_sent,
    )
    for name in SEGMENT_FIELDS:
        setattr(segment, name, saved[name])
    if segment.sent_seq:  # the ones applied are never sent or applied again
        current = runtime.coordinator.current_poses(index, "resume")
        if current is None:
            raise StoreError(
                f"{session.path}: inconsistent session store: agent {index} "
                f"was sent pose updates but has no keyframes"
            )
        segment.updates = [current] * segment.sent_seq
    return segment
