"""An agent's results as the coordinator of the multi-process runtime holds them, and the
view of them the output files take (manual: docs/outputs.md, "Run output"); one map
segment's own result is :mod:`.agent_result`'s (re-exported here).

Each process that ran an agent leaves one *map segment*: an :class:`AgentResult` under a
coordinator agent id of its own. An agent whose process was restarted (``como3r agent``
with the same ``--id``, issue 13) has several; the new process starts a fresh map, which the
coordinator associates with its earlier map and the other agents' exactly as it associates
two agents, and merges into their gauge once a cross-agent edge is verified. The outputs are
per agent: :class:`SegmentedResult` joins an agent's segments that share one gauge
component, and :class:`SegmentedCoordinator` states the coordinator's graph, components and
metrics in agent ids and keyframe numbers (a later segment's keyframes are numbered after the
earlier ones'). With one segment per agent both are the identity.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from como3r.frontend.agent import FrontendStats
from como3r.frontend.packets import PoseUpdate
from como3r.runtime.agent_result import (
    AgentResult,
    EdgeView,
    KeyframeView,
    MatchFraction,
    final_report,
    graph_view,
    stored_views,
)

if TYPE_CHECKING:  # an agent's process imports this module and needs no back-end (~0.5 s CPU)
    from como3r.coordination.coordinator import Coordinator

# an agent's own result (agent_result.py) is part of this module's interface
__all__ = [
    "AgentResult",
    "AgentSlot",
    "EdgeView",
    "KeyframeView",
    "MapSegment",
    "MatchFraction",
    "SegmentPlace",
    "SegmentedCoordinator",
    "SegmentedResult",
    "agent_results",
    "final_report",
    "graph_view",
    "left_out",
    "output_places",
    "stored_views",
]


@dataclass
class MapSegment:
    """One process's map of an agent: a coordinator agent of its own (``index``).

    ``sent_seq`` counts the pose updates made for it, ``confirmed_seq`` the newest its
    process said it had applied (what to send again after a reconnect)."""

    index: int
    agent: int
    result: AgentResult
    after_frame: int = -1  # its process started after this frame
    sent_seq: int = 0
    confirmed_seq: int = 0
    updates: list[PoseUpdate] = field(default_factory=list)
    reanchored: int = 0


@dataclass
class AgentSlot:
    """The coordinator's view of one agent, over all the processes that ran it
    (``segment``: the current one's map)."""

    agent: int
    frames_expected: int
    segment: MapSegment
    status: str = "starting"
    pid: int | None = None
    clock: float = -math.inf
    last_frame: int = -1
    frames_done: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    lost_frames: list[int] = field(default_factory=list)
    keyframes_received: int = 0
    keyframes_waiting: int = 0  # made by its process, not sent yet (its last FrameDone)
    seconds: float = 0.0
    error: str | None = None
    last_heard: float = field(default_factory=time.monotonic)
    away_since: float | None = None
    away_reason: str = ""
    absences: int = 0
    restarts: int = 0
    handled_seq: int = -1  # the number of its process's last message handled
    #: (a resumed coordinator) its process re-sends messages up to this number, some of
    #: them not stored; -1: nothing to wait for
    resend_until: int = -1
    #: away only since the coordinator restarted: its stored clock still orders the
    #: keyframes until it is back (it comes back with what it sent since), or fails
    awaited: bool = False
    #: (while re-sending) the timestamp of the latest keyframe its process re-sent, -inf
    #: before the first: the keyframes still to be re-sent come after it
    resent_clock: float = -math.inf

    def expected(self) -> bool:
        """Whether the coordinator waits for messages of its process: it runs, or it re-sends
        what a resumed coordinator lacks."""
        return self.status in ("starting", "running") or self.resend_until >= 0

    def order_clock(self) -> float:
        """The clock the keyframe ordering waits for: none while away, unless
        :attr:`awaited`; while its process re-sends what a resumed coordinator had not
        stored, :attr:`resent_clock`: the stored clock may be past keyframes the killed
        coordinator held back unstored (a finished agent's is infinite), which then came
        after the other agents' later keyframes."""
        if self.away_since is not None and not self.awaited:
            return math.inf
        return self.resent_clock if self.resend_until >= 0 else self.clock


@dataclass
class SegmentedResult:
    """An agent's results over the map segments its processes left, in the order they ran;
    the outputs read it as they read an :class:`AgentResult`.

    Args:
        agent: the agent's id.
        parts: its segments that share one gauge component.
        stats: its counters over all its processes.
    """

    agent: int
    parts: Sequence[AgentResult]
    stats: FrontendStats
    keyframes: list[KeyframeView] = field(init=False)
    edges: list[EdgeView] = field(init=False)

    def __post_init__(self) -> None:
        self.keyframes, self.edges, offset = [], [], 0
        for part in self.parts:
            self.keyframes.extend(
                replace(kf, kf_id=kf.kf_id + offset) if offset else kf for kf in part.keyframes
            )
            self.edges.extend(
                replace(e, i=e.i + offset, j=e.j + offset) if offset else e for e in part.edges
            )
            offset += len(part.keyframes)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Every tracked frame of every part, by frame index: ``(frame indices (N,),
        timestamps (N,), T_WC (N, 8))``."""
        if len(self.parts) == 1:
            return self.parts[0].trajectory()
        pieces = [part.trajectory() for part in self.parts]
        frames = np.concatenate([p[0] for p in pieces]).astype(np.int64)
        order = np.argsort(frames, kind="stable")
        stamps = np.concatenate([np.asarray(p[1], dtype=np.float64) for p in pieces])
        poses = torch.cat([p[2].double() for p in pieces])
        return frames[order], stamps[order], poses[torch.from_numpy(order)]

    def keyframe_trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]:
        """Keyframes only: ``(frame indices, timestamps, T_WC (K, 8))``."""
        return AgentResult(self.agent, self.keyframes).keyframe_trajectory()


@dataclass(frozen=True)
class SegmentPlace:
    """Where a coordinator agent (map segment) goes in the outputs: agent ``agent``,
    keyframes numbered from ``offset``."""

    agent: int
    offset: int


class SegmentedCoordinator:
    """The coordinator as the output files read it (``components()``,
    ``graph_document()``, ``metrics()``, ``pre_refinement``), in agent ids.

    Args:
        coordinator: the run's coordinator (its agents are map segments).
        places: each segment that is in the outputs, by its coordinator id; segments left
            out (and their edges) are not shown.
    """

    def __init__(self, coordinator: Coordinator, places: Mapping[int, SegmentPlace]) -> None:
        self.coordinator, self.places = coordinator, places

    def components(self) -> list[list[int]]:
        """Gauge components as agent lists, agent 0's first."""
        groups = [
            sorted({self.places[s].agent for s in c if s in self.places})
            for c in self.coordinator.components()
        ]
        return sorted((g for g in groups if g), key=lambda g: g[0])

    def graph_document(self) -> dict[str, Any]:
        """:meth:`Coordinator.graph_document` with ``[agent, keyframe]`` keys."""
        document = self.coordinator.graph_document()
        document["keyframes"] = [
            {**k, "agent": key[0], "keyframe": key[1]}
            for k in document["keyframes"]
            if (key := self._key((k["agent"], k["keyframe"]))) is not None
        ]
        document["edges"] = [
            {**e, "from": key_from, "to": key_to}
            for e in document["edges"]
            if (key_from := self._key(e["from"])) is not None
            and (key_to := self._key(e["to"])) is not None
        ]
        document["candidates"] = [
            {**c, "from": key_from, "to": key_to}
            for c in document["candidates"]
            if (key_from := self._key(c["from"])) is not None
            and (key_to := self._key(c["to"])) is not None
        ]
        document["gauge_events"] = [self._gauge_event(e) for e in document["gauge_events"]]
        document["components"] = self.components()
        return document

    def metrics(self) -> dict[str, Any]:
        """:meth:`Coordinator.metrics` with agent ids."""
        stats = self.coordinator.metrics()
        stats["components"] = self.components()
        stats["gauge_events"] = [self._gauge_event(e) for e in stats["gauge_events"]]
        stats["alternation"] = [
            {**a, "agents": self._agents(a["agents"])} for a in stats["alternation"]
        ]
        focal: dict[str, float] = {}
        for segment, value in stats["focal_lengths"].items():
            if int(segment) in self.places:
                focal.setdefault(str(self.places[int(segment)].agent), value)
        stats["focal_lengths"] = focal
        return stats

    @property
    def pre_refinement(self) -> dict[int, list[Any]]:
        """Each agent's keyframes before the terminal depth refinement, where every segment
        of it in the outputs has them."""
        kept: dict[int, list[int]] = {}
        for segment, place in self.places.items():
            kept.setdefault(place.agent, []).append(segment)
        before = self.coordinator.pre_refinement
        return {
            agent: [kf for s in sorted(segments) for kf in before[s]]
            for agent, segments in kept.items()
            if all(s in before for s in segments)
        }

    def _key(self, key: Sequence[int]) -> list[int] | None:
        place = self.places.get(int(key[0]))
        return None if place is None else [place.agent, int(key[1]) + place.offset]

    def _agents(self, segments: Sequence[int]) -> list[int]:
        return sorted({self.places[s].agent for s in segments if s in self.places})

    def _gauge_event(self, event: dict[str, Any]) -> dict[str, Any]:
        anchor = self.places.get(event["anchor_component"])
        return {
            **event,
            "moved_agents": self._agents(event["moved_agents"]),
            "anchor_component": event["anchor_component"] if anchor is None else anchor.agent,
            "edges": [
                [a, b]
                for a, b in (map(self._key, pair) for pair in event["edges"])
                if a is not None and b is not None
            ],
        }


def output_places(
    components: Sequence[Sequence[int]], segments: Sequence[tuple[int, int, int]]
) -> dict[int, SegmentPlace]:
    """Which map segments the outputs show, and where.

    An agent's outputs hold its segments in one gauge component, the one with most of its
    keyframes (ties: its earliest segment's); a segment never associated with that
    component lives in a frame of its own and is left out.

    Args:
        components: the coordinator's gauge components (coordinator agent ids).
        segments: ``(coordinator id, agent, keyframes)`` of every segment, in the order
            they were made.

    Returns:
        Coordinator id -> place, for the segments shown.
    """
    root = {member: component[0] for component in components for member in component}
    weight: dict[int, dict[int, int]] = {}  # agent -> component root -> keyframes
    for index, agent, keyframes in segments:
        counts = weight.setdefault(agent, {})
        counts[root[index]] = counts.get(root[index], 0) + keyframes
    places: dict[int, SegmentPlace] = {}
    offsets: dict[int, int] = {}
    for index, agent, keyframes in segments:
        counts = weight[agent]
        if root[index] == max(counts, key=counts.__getitem__):  # first-seen wins ties
            places[index] = SegmentPlace(agent, offsets.get(agent, 0))
            offsets[agent] = offsets.get(agent, 0) + keyframes
    return places


def agent_results(
    slots: Sequence[AgentSlot], segments: Sequence[MapSegment], components: Sequence[Sequence[int]]
) -> tuple[list[SegmentedResult], dict[int, SegmentPlace]]:
    """Each agent's results for the outputs, its segments placed by
    :func:`output_places` and joined, with the places."""
    places = output_places(
        components, [(s.index, s.agent, len(s.result.keyframes)) for s in segments]
    )
    results = []
    for slot in slots:
        mine = [s for s in segments if s.agent == slot.agent]
        parts = [s.result for s in mine if s.index in places]
        results.append(
            SegmentedResult(
                slot.agent,
                parts,
                _agent_stats(slot, len(mine), sum(len(p.keyframes) for p in parts)),
            )
        )
    return results, places


def _agent_stats(slot: AgentSlot, segments: int, keyframes: int) -> FrontendStats:
    """An agent's counters over its ``segments`` processes: its last process's report where
    it finished, with the frame counts of them all (``keyframes``: in its outputs)."""
    done = slot.segment.result.finished
    if done is not None and segments == 1:
        return done.stats
    base = done.stats if done is not None else FrontendStats()
    return replace(
        base,
        frames=slot.frames_done,
        lost=slot.outcomes["lost"],
        relocalized=slot.outcomes["relocalized"],
        keyframes=keyframes,
        tracked=slot.frames_done - slot.outcomes["lost"],
        lost_frames=list(slot.lost_frames),
    )


def left_out(segments: Sequence[MapSegment], places: Mapping[int, SegmentPlace]) -> list[str]:
    """A note per map segment not in the outputs (it never met its agent's main map)."""
    return [
        f"agent {s.agent}: the map of its process from after frame {s.after_frame} "
        f"({len(s.result.keyframes)} keyframes) was never associated with the rest of "
        f"its map; it is left out of the outputs"
        for s in segments
        if s.index not in places
    ]
