"""The multi-process runtime's own metrics (:mod:`.processes`): ``metrics.json``'s
``runtime`` section, per agent (status, map segments, bytes and messages each way, keyframe
bytes by part, the verification it served for the coordinator) and in total (bytes by
message type, backlog, failed agents, whether the agents verified)."""

from __future__ import annotations

from collections import Counter
from typing import Any, Protocol

from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.backlog import Backlog
from como3r.runtime.remote_verification import AgentVerifiers
from como3r.runtime.results import AgentSlot, MapSegment, SegmentPlace
from como3r.transport.keyframe_bytes import PartCounter
from como3r.transport.links import Hub, Traffic


class MetricsSource(Protocol):
    """What the metrics read of the runtime (:class:`~.processes._Runtime` is one)."""

    hub: Hub
    options: RuntimeOptions
    slots: list[AgentSlot]
    segments: list[MapSegment]
    places: dict[int, SegmentPlace]
    finish_threads: int
    backlog: Backlog
    keyframe_parts: dict[int, PartCounter]
    verifiers: AgentVerifiers | None


def runtime_metrics(runtime: MetricsSource) -> dict[str, Any]:
    """Per-agent status and bytes exchanged per message type (both directions)."""
    agents = []
    by_type: Counter[str] = Counter()
    for slot in runtime.slots:
        channel = Traffic() if slot.status == "map" else runtime.hub.traffic(slot.agent)
        by_type.update(channel.bytes_sent)
        by_type.update(channel.bytes_received)
        segments = [s for s in runtime.segments if s.agent == slot.agent]
        agents.append(
            {
                "agent": slot.agent,
                "status": slot.status,
                "error": slot.error,
                "pid": slot.pid,
                "exitcode": None if slot.status == "map" else runtime.hub.exitcode(slot.agent),
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
                        "in_outputs": s.index in runtime.places,
                    }
                    for s in segments
                ],
                "bytes_to_agent": dict(channel.bytes_sent),
                "bytes_from_agent": dict(channel.bytes_received),
                "messages_to_agent": dict(channel.messages_sent),
                "messages_from_agent": dict(channel.messages_received),
                "send_backlog": None if channel.backlog is None else channel.backlog.to_json(),
                "keyframe_bytes_by_part": runtime.keyframe_parts.get(
                    slot.agent, PartCounter()
                ).per_keyframe(),
                "verification": None
                if runtime.verifiers is None
                else runtime.verifiers.metrics(slot.agent),
            }
        )
    return {
        "mode": "multiprocess",
        "transport": runtime.hub.name,
        "lockstep": runtime.options.lockstep,
        "torch_threads": runtime.options.torch_threads,
        "finish_torch_threads": runtime.finish_threads,
        "max_message_bytes": runtime.options.max_message_bytes,
        "agents": agents,
        "bytes_by_type": dict(by_type),
        "bytes_total": sum(by_type.values()),
        "failed_agents": [s.agent for s in runtime.slots if s.status == "failed"],
        "backlog": runtime.backlog.to_json(),
        "verification_on_agents": runtime.verifiers is not None,
        # keyframes whose verification the agents had not returned when their input ended
        "verification_out_at_end": None
        if runtime.verifiers is None
        else runtime.verifiers.out_at_end,
    }
