"""The live events of a run (:mod:`como3r.live`) built from what the run already holds.

Both runtimes call the same builders, so a viewer sees the same events from
``--single-process`` and from the multi-process runtime:

* :func:`frame_event` -- from an agent's front-end right after a frame (in the
  multi-process runtime inside the agent process, which sends the event as a message);
* :class:`CoordinatorLive` -- in the coordinator's process: keyframe and map events from the
  coordinator's global graph as keyframes arrive and pose updates leave, and the final
  events from the agents' results once the terminal alternation is done.

Nothing here runs unless a ``live`` callback was given to the run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch
from torch import Tensor

from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import KeyframePacket, PoseUpdate
from como3r.geometry.camera import estimate_focal
from como3r.geometry.lie import sim3_act, sim3_compose
from como3r.live import (
    FRAME_IMAGE_LONG_SIDE,
    KEYFRAME_POINTS,
    FrameEvent,
    KeyframeEvent,
    LiveCallback,
    MapEvent,
    TrajectoryEvent,
)
from como3r.progress import tracking_state

if TYPE_CHECKING:  # an agent's process imports this module and needs no back-end (~0.5 s CPU)
    from como3r.coordination.coordinator import Coordinator


class _PointmapKeyframe(Protocol):
    """What the builders read of a keyframe (a front-end's, the coordinator's, or the
    multi-process runtime's view of one)."""

    kf_id: int
    frame_index: int
    T_WC: Tensor
    X_hat: Tensor

    def mean_confidence(self) -> Tensor: ...


class _AgentOutcome(Protocol):
    """What the final events read of an agent's results (an
    :class:`~como3r.frontend.agent.AgentFrontend` or the multi-process runtime's
    ``AgentResult``)."""

    agent: int
    keyframes: Any  # iterable of _PointmapKeyframe
    edges: Any  # iterable of edges with i, j, kind

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, Tensor]: ...


def frame_event(
    frontend: AgentFrontend, index: int, timestamp: float, outcome: str, colors: np.ndarray
) -> FrameEvent:
    """The event of the frame ``frontend`` has just processed.

    Args:
        frontend: the agent's front-end, after ``process`` returned ``outcome``.
        index: the frame's index in the agent's stream.
        timestamp: its timestamp [s].
        outcome: what ``process`` returned.
        colors: ``(H, W, 3)`` uint8 the frame at network resolution.
    """
    records, keyframes = frontend.records, frontend.keyframes
    record = records[-1] if records and records[-1].frame_index == index else None
    T_WC = None
    if record is not None and outcome != "lost":
        anchor = keyframes[record.anchor]
        T_WC = sim3_compose(anchor.T_WC, record.T_rel.to(anchor.T_WC)).double().numpy()
    keyframe = (
        keyframes[record.anchor]
        if record is not None
        else keyframes.last
        if len(keyframes)
        else None
    )
    stride = max(1, math.ceil(max(colors.shape[:2]) / FRAME_IMAGE_LONG_SIDE))
    K = (
        None
        if keyframe is None
        else _intrinsics(keyframe.K, keyframe.X_hat, keyframe.mean_confidence())
    )
    if K is not None:
        K[:2] /= stride  # pixel u of the subsampled image is pixel stride * u of the input
    return FrameEvent(
        agent=frontend.agent,
        frame_index=index,
        timestamp=float(timestamp),
        state=tracking_state(outcome),
        T_WC=T_WC,
        K=K,
        image=np.ascontiguousarray(colors[::stride, ::stride]),
        wall_time=time.time(),
    )


def _intrinsics(K: Tensor | None, X: Tensor, C: Tensor) -> np.ndarray | None:
    """``(3, 3)`` float64 ``K``, else the pinhole an ``(H, W, 3)`` pointmap implies with
    confidences ``(H, W)`` (principal point at the centre; None if it implies none)."""
    if K is not None:
        return K.double().cpu().numpy().copy()
    focal = float(estimate_focal(X, C))
    if not math.isfinite(focal) or focal <= 0:
        return None
    H, W = X.shape[:2]
    return np.array([[focal, 0.0, (W - 1) / 2.0], [0.0, focal, (H - 1) / 2.0], [0.0, 0.0, 1.0]])


def keyframe_points(keyframe: _PointmapKeyframe, min_confidence: float) -> Tensor:
    """``(N, 3)`` the keyframe's points on a grid of at most :data:`KEYFRAME_POINTS`
    pixels whose mean confidence exceeds ``min_confidence``, in its camera frame."""
    X = keyframe.X_hat
    H, W = X.shape[:2]
    stride = max(1, math.ceil(math.sqrt(H * W / KEYFRAME_POINTS)))
    X = X[::stride, ::stride].reshape(-1, 3)
    keep = (
        keyframe.mean_confidence()[::stride, ::stride].reshape(-1) > min_confidence
    ) & torch.isfinite(X).all(-1)
    return X[keep]


def keyframe_event(agent: int, keyframe: _PointmapKeyframe, min_confidence: float) -> KeyframeEvent:
    """The event of one keyframe (:func:`keyframe_points` in its camera frame)."""
    points = keyframe_points(keyframe, min_confidence)
    return KeyframeEvent(
        agent=agent,
        kf_id=keyframe.kf_id,
        frame_index=keyframe.frame_index,
        T_WC=keyframe.T_WC.double().cpu().numpy(),
        points=points.float().cpu().numpy(),
        wall_time=time.time(),
    )


def map_event(
    reason: str,
    keyframes: Mapping[int, Sequence[_PointmapKeyframe]],
    edges: Iterable[tuple[int, int, int, int, str]],
    components: Sequence[Sequence[int]],
    min_confidence: float,
) -> MapEvent:
    """The map of ``keyframes`` (agent -> its keyframes in order) with ``edges``
    ``(agent_i, kf_i, agent_j, kf_j, kind)``."""
    keys, poses, points, owners = [], [], [], []
    for agent, own in keyframes.items():
        for kf in own:
            keys.append((agent, kf.kf_id))
            poses.append(kf.T_WC.double().cpu())
            local = keyframe_points(kf, min_confidence)
            points.append(sim3_act(kf.T_WC[None].to(local), local).float().cpu().numpy())
            owners.append(np.full(len(local), agent, dtype=np.int32))
    edge_list = list(edges)
    return MapEvent(
        reason=reason,
        keyframes=np.array(keys, dtype=np.int64).reshape(-1, 2),
        T_WC=torch.stack(poses).numpy() if poses else np.zeros((0, 8)),
        edges=np.array([e[:4] for e in edge_list], dtype=np.int64).reshape(-1, 4),
        edge_kinds=tuple(e[4] for e in edge_list),
        components=tuple(tuple(int(a) for a in c) for c in components),
        points=np.concatenate(points) if points else np.zeros((0, 3), np.float32),
        point_agents=np.concatenate(owners) if owners else np.zeros(0, np.int32),
        wall_time=time.time(),
    )


class CoordinatorLive:
    """The coordinator's side of the live events (the same in both runtimes).

    Args:
        sink: the run's ``live`` callback.
        coordinator: the run's coordinator (read only).
        min_confidence: the points' mean-confidence threshold
            (``visualization.map_min_confidence``, as for ``map.ply``).
    """

    def __init__(self, sink: LiveCallback, coordinator: Coordinator, min_confidence: float) -> None:
        self.sink, self.coordinator, self.min_confidence = sink, coordinator, min_confidence

    def keyframe_added(self, packet: KeyframePacket, updates: Sequence[PoseUpdate]) -> None:
        """After ``coordinator.add_keyframe(packet)`` returned ``updates``: the new keyframe,
        its predecessor (whose fused pointmap the packet refreshed) and, if poses moved, the
        map."""
        graph = self.coordinator.graph
        for kf_id in range(max(0, packet.kf_id - 1), packet.kf_id + 1):
            keyframe = graph.keyframes[graph.global_index(packet.agent, kf_id)]
            self.sink(keyframe_event(packet.agent, keyframe, self.min_confidence))
        if updates:
            reason = ", ".join(dict.fromkeys(u.reason for u in updates))
            self.sink(
                map_event(
                    reason,
                    self._graph_keyframes(),
                    self._inter_edges(),
                    self.coordinator.components(),
                    self.min_confidence,
                )
            )

    def finish(self, results: Sequence[_AgentOutcome]) -> None:
        """The run's final state, from the agents' results after the terminal alternation:
        every keyframe (refined pointmaps, final poses), the final map with the agents'
        loop edges, and every agent's trajectory."""
        for result in results:
            for keyframe in result.keyframes:
                self.sink(keyframe_event(result.agent, keyframe, self.min_confidence))
        loops = [
            (r.agent, e.i, r.agent, e.j, "loop")
            for r in results
            for e in r.edges
            if e.kind == "loop" and e.i < e.j
        ]
        self.sink(
            map_event(
                "final",
                {r.agent: list(r.keyframes) for r in results},
                [*self._inter_edges(), *loops],
                self.coordinator.components(),
                self.min_confidence,
            )
        )
        for result in results:
            frames, _, T_WC = result.trajectory()
            self.sink(
                TrajectoryEvent(
                    agent=result.agent,
                    frame_indices=np.asarray(frames, dtype=np.int64),
                    T_WC=T_WC.double().cpu().numpy().reshape(-1, 8),
                    wall_time=time.time(),
                )
            )

    def _graph_keyframes(self) -> dict[int, list[Any]]:
        graph = self.coordinator.graph
        return {
            agent: [graph.keyframes[g] for g in graph.agent_keyframes(agent)]
            for agent in range(self.coordinator.num_agents)
        }

    def _inter_edges(self) -> list[tuple[int, int, int, int, str]]:
        graph = self.coordinator.graph
        return [
            (
                graph.agent_of[link.i],
                graph.keyframes[link.i].kf_id,
                graph.agent_of[link.j],
                graph.keyframes[link.j].kf_id,
                "inter",
            )
            for link in graph.links
            if link.kind == "inter"
        ]
