"""One agent's results as the runtimes hold them (manual: docs/outputs.md, "Run output"):
:class:`AgentResult`, its keyframes as :class:`KeyframeView` s (poses the agent's, the rest
read from the graph that holds them), its edges and, at its end, its final report
(:func:`final_report`). The multi-process runtime keeps one per map segment and joins an
agent's segments for the outputs (:mod:`.results`, which re-exports these names).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from como3r.frontend.agent import AgentFrontend, FrontendStats
from como3r.frontend.keyframes import Keyframe, apply_pose_update
from como3r.frontend.packets import PointmapRefresh, PointmapUpdate, PoseUpdate
from como3r.frontend.paging import read_fields
from como3r.geometry.lie import sim3_compose
from como3r.transport.messages import AgentFinished, EdgeSummary

if TYPE_CHECKING:  # an agent's process imports this module and needs no back-end (~0.5 s CPU)
    from como3r.backend.global_graph import GlobalGraph


@dataclass
class KeyframeView:
    """What the outputs need of a keyframe, its pose the agent's and the rest read from
    the coordinator's graph, which holds (or pages in) the pointmaps: a view keeps no large
    array, so the coordinator's memory stays bounded (:mod:`como3r.store.paging`).

    The graph gets every change a view is told of before or as the view does (a refreshed
    pointmap, a focal length, a refined pointmap), so a view only reads them: writing one
    of them is ignored.

    Attributes:
        kf_id: the keyframe's id in its agent's outputs.
        frame_index: its frame in the agent's stream.
        timestamp: seconds.
        T_WC: ``(8,)`` its pose, as its agent has it.
        graph: the coordinator's graph.
        agent: the keyframe's agent in ``graph`` (its coordinator id).
        graph_kf_id: its keyframe id there (``kf_id`` is renumbered when an agent's map
            segments are joined).
    """

    kf_id: int
    frame_index: int
    timestamp: float
    T_WC: Tensor
    graph: GlobalGraph
    agent: int
    graph_kf_id: int

    @property
    def keyframe(self) -> Keyframe:
        """The graph's keyframe."""
        return self.graph.keyframes[self.graph.global_index(self.agent, self.graph_kf_id)]

    # read back without keeping a paged-out keyframe's arrays: writing the outputs reads
    # every keyframe once
    X_hat = property(lambda self: read_fields(self.keyframe, "X_hat"), lambda self, value: None)
    C_hat = property(lambda self: read_fields(self.keyframe, "C_hat"), lambda self, value: None)
    colors = property(lambda self: read_fields(self.keyframe, "colors"), lambda self, value: None)
    K = property(lambda self: self.keyframe.K, lambda self, value: None)
    fused_frames = property(lambda self: self.keyframe.fused_frames, lambda self, value: None)

    def rescale_focal(self, focal: float) -> None:
        """Nothing: the graph has moved the keyframe to the focal length already."""

    def mean_confidence(self) -> Tensor:
        """``(H, W)`` confidence per contributing frame."""
        kf = self.keyframe
        return read_fields(kf, "C_hat") / kf.fused_frames


def graph_view(
    graph: GlobalGraph, agent: int, kf_id: int, frame_index: int, timestamp: float, T_WC: Tensor
) -> KeyframeView:
    """The view of keyframe ``kf_id`` of ``agent`` in ``graph`` with pose ``T_WC``."""
    return KeyframeView(kf_id, frame_index, timestamp, T_WC, graph, agent, kf_id)


def stored_views(
    graph: GlobalGraph, agent: int, source: GlobalGraph | None = None, as_agent: int | None = None
) -> list[KeyframeView]:
    """``agent``'s keyframes as ``graph`` holds them (a session store read back), in keyframe
    order, with their current poses; their arrays read from ``source`` (default ``graph``)
    as agent ``as_agent`` (default ``agent``) there."""
    return [
        graph_view(
            graph if source is None else source,
            agent if as_agent is None else as_agent,
            kf.kf_id,
            kf.frame_index,
            kf.timestamp,
            kf.T_WC.clone(),
        )
        for kf in (graph.keyframes[g] for g in graph.agent_keyframes(agent))
    ]


def final_report(frontend: AgentFrontend, seconds: float, applied_seq: int) -> AgentFinished:
    """An agent front-end's final report: its last fused pointmap, statistics, every tracked
    frame anchored on its keyframe (C-Sec. A.8), its keyframes' poses and edges.

    Args:
        frontend: the agent's front-end at the end of its stream.
        seconds: its processing time.
        applied_seq: pose updates it applied.
    """
    records = sorted(frontend.records, key=lambda r: r.frame_index)
    kf_frames, kf_stamps, kf_poses = frontend.keyframe_trajectory()
    final = None
    if len(frontend.keyframes):
        last = frontend.keyframes.last
        final = PointmapRefresh(last.kf_id, last.X_hat, last.C_hat, last.fused_frames, last.K)
    return AgentFinished(
        agent=frontend.agent,
        final=final,
        stats=frontend.stats,
        seconds=seconds,
        applied_seq=applied_seq,
        frame_indices=np.array([r.frame_index for r in records], dtype=np.int64),
        timestamps=np.array([r.timestamp for r in records], dtype=np.float64),
        anchors=np.array([r.anchor for r in records], dtype=np.int64),
        T_rel=(
            torch.stack([r.T_rel for r in records])
            if records
            else torch.zeros(0, 8, dtype=torch.float64)
        ),
        keyframe_frames=kf_frames.astype(np.int64),
        keyframe_timestamps=kf_stamps.astype(np.float64),
        keyframe_T_WC=kf_poses,
        edges=[EdgeSummary(e.i, e.j, e.kind, e.matches.match_fraction) for e in frontend.edges],
    )


@dataclass(frozen=True)
class MatchFraction:
    """An edge's match fraction (what the outputs read of its matches)."""

    match_fraction: float


@dataclass(frozen=True)
class EdgeView:
    """One edge of an agent's local keyframe graph, between keyframes ``i`` and ``j``."""

    i: int
    j: int
    kind: str
    matches: MatchFraction


@dataclass
class AgentResult:
    """One map segment as the coordinator holds it: what :mod:`.outputs` reads of an
    :class:`~como3r.frontend.agent.AgentFrontend` (``agent``, ``keyframes``, ``edges``,
    ``stats``, ``trajectory()``, ``keyframe_trajectory()``); ``agent`` is the
    coordinator's id of the segment.

    A segment whose process finished has the trajectory composed from its anchored records
    (C-Sec. A.8); any other segment's is its keyframes only.
    """

    agent: int
    keyframes: list[KeyframeView] = field(default_factory=list)
    edges: list[EdgeView] = field(default_factory=list)
    stats: FrontendStats = field(default_factory=FrontendStats)
    finished: AgentFinished | None = None

    def apply_pointmap_update(self, update: PointmapUpdate) -> None:
        """Nothing to take: the views read the coordinator's refined canonical pointmaps
        (C-Sec. A.7) from its graph (as a front-end's ``apply_pointmap_update`` is called,
        the single-process runtime calls this for a saved map's agents)."""

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
        return (
            np.array([kf.frame_index for kf in self.keyframes]),
            np.array([kf.timestamp for kf in self.keyframes]),
            torch.stack([kf.T_WC for kf in self.keyframes]),
        )
