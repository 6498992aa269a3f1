"""Gauge synchronization of the agents' independent world frames (C-Sec. 3.4, A.4, C.4).

Every monocular agent starts in its own arbitrary Sim(3) gauge. Two pieces of state bring
them into one:

* :class:`GaugeComponents`, a union-find over agent ids. A component is a set of agents
  already sharing one world frame; its root is its LOWEST agent id, so the component that
  holds agent 0 is always rooted at 0 and is the global gauge anchor. When a verified
  inter-agent edge joins two components, the one with the higher root is transported
  into the gauge of the one with the lower root (C-Sec. A.4: "anchoring each newly
  connected pair on its lower-indexed agent with agent 0 as the global gauge"), in any
  meeting order (agents 2 and 3 may merge before either meets agent 0; C-Sec. C.4).
* :func:`solve_gauge_transform`, the similarity ``T*`` that maps the moving component's
  world frame onto the anchor's: Umeyama (C-Eq. 14) on matched canonical points lifted into
  both world frames when there are at least ``N_c^min`` of them, else the rigid snap
  ``T* = T_WC_anchor T_WC_moving^-1`` of the edge's endpoints. ``T*`` is then
  left-multiplied onto every keyframe pose of the moving component (C-Eq. 15).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.errors import GeometryError
from como3r.geometry.lie import sim3_act_points, sim3_compose, sim3_inverse
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3

logger = logging.getLogger(__name__)

#: A lifted correspondence whose residual after the first Umeyama fit exceeds this many
#: times the median residual is dropped before the refit: occlusions and depth-distorted
#: pixels of a learned prior must not bias a transform that moves a whole agent.
OUTLIER_MEDIAN_FACTOR = 3.0


class GaugeComponents:
    """Union-find over agent ids; each component shares one world frame.

    Agents are added lazily (an agent id never seen is a singleton component). The root of
    a component is its lowest agent id.
    """

    def __init__(self) -> None:
        self._parent: dict[int, int] = {}

    def add(self, agent: int) -> None:
        """Register ``agent`` as a singleton component if it is new."""
        self._parent.setdefault(int(agent), int(agent))

    def find(self, agent: int) -> int:
        """Root (lowest agent id) of the component of ``agent``."""
        self.add(agent)
        root = int(agent)
        while self._parent[root] != root:
            root = self._parent[root]
        node = int(agent)
        while self._parent[node] != root:  # path compression
            self._parent[node], node = root, self._parent[node]
        return root

    def same(self, a: int, b: int) -> bool:
        """Whether agents ``a`` and ``b`` already share a gauge."""
        return self.find(a) == self.find(b)

    def union(self, a: int, b: int) -> tuple[int, int]:
        """Merge the components of ``a`` and ``b``.

        Returns:
            ``(anchor root, moved root)``: the lower root stays, the higher one joins it.
            Both equal the common root if ``a`` and ``b`` were already together.
        """
        root_a, root_b = self.find(a), self.find(b)
        anchor, moved = min(root_a, root_b), max(root_a, root_b)
        self._parent[moved] = anchor
        return anchor, moved

    def members(self, agent: int) -> list[int]:
        """Sorted agents of the component containing ``agent``."""
        root = self.find(agent)
        return sorted(a for a in self._parent if self.find(a) == root)

    def components(self) -> list[list[int]]:
        """All components as sorted agent lists, ordered by root (agent 0's first)."""
        groups: dict[int, list[int]] = {}
        for agent in sorted(self._parent):
            groups.setdefault(self.find(agent), []).append(agent)
        return [groups[root] for root in sorted(groups)]


@dataclass(frozen=True)
class GaugeTransform:
    """The similarity that carries a moving component into the anchor's gauge.

    Attributes:
        T: ``(8,)`` Sim(3) ``T*`` with ``x_anchor = T* x_moving`` (C-Eq. 14).
        method: ``"umeyama"`` or ``"rigid_snap"``.
        correspondences: lifted point pairs available (after outlier rejection for Umeyama).
        rmse: RMS residual of the fit over the kept pairs [anchor world units], NaN for a
            rigid snap.
    """

    T: Tensor
    method: str
    correspondences: int
    rmse: float


def solve_gauge_transform(
    x_moving: Tensor,
    x_anchor: Tensor,
    weights: Tensor,
    T_WC_moving: Tensor,
    T_WC_anchor: Tensor,
    min_correspondences: int,
) -> GaugeTransform:
    """``T*`` from lifted correspondences (C-Eq. 14) or the rigid snap of C-Sec. A.4.

    Args:
        x_moving: ``(N, 3)`` matched canonical points lifted into the moving world frame.
        x_anchor: ``(N, 3)`` their partners lifted into the anchor's world frame.
        weights: ``(N,)`` non-negative per-pair weights (match confidences ``q``).
        T_WC_moving: ``(8,)`` pose of the edge's endpoint in the moving component.
        T_WC_anchor: ``(8,)`` pose of the edge's endpoint in the anchor component.
        min_correspondences: ``N_c^min``; fewer pairs fall back to the rigid snap.

    Returns:
        The transform, with how it was obtained.
    """
    if x_moving.shape[0] >= min_correspondences:
        try:
            return _umeyama_transport(x_moving, x_anchor, weights, min_correspondences)
        except GeometryError as exc:
            logger.warning("gauge: Umeyama failed (%s); falling back to a rigid snap", exc)
    T = sim3_compose(T_WC_anchor, sim3_inverse(T_WC_moving.to(T_WC_anchor)))
    return GaugeTransform(
        T=T, method="rigid_snap", correspondences=int(x_moving.shape[0]), rmse=float("nan")
    )


def _umeyama_transport(
    x_moving: Tensor, x_anchor: Tensor, weights: Tensor, min_correspondences: int
) -> GaugeTransform:
    """Weighted Umeyama, refit once without the pairs far off the first fit."""
    src, dst, w = x_moving.double(), x_anchor.double(), weights.double()
    T = umeyama_sim3(src, dst, w)
    residual = (sim3_act_points(T, src) - dst).norm(dim=-1)
    keep = residual <= OUTLIER_MEDIAN_FACTOR * residual.median()
    if int(keep.sum()) >= min_correspondences:
        src, dst, w = src[keep], dst[keep], w[keep]
        T = umeyama_sim3(src, dst, w)
    rmse = umeyama_rmse(T, src, dst, w)
    return GaugeTransform(
        T=T.to(x_anchor.dtype), method="umeyama", correspondences=int(src.shape[0]), rmse=rmse
    )


def edge_log_scale(
    x_source: Tensor, x_target: Tensor, weights: Tensor, min_correspondences: int
) -> float:
    """Log scale of the similarity (Umeyama, refit without outliers as for ``T*``) taking
    an edge's lifted points ``x_source (N, 3)`` onto their matches ``x_target (N, 3)``
    (weights ``(N,)``): 0 for an edge that agrees with the map's scale, ``log s`` for one
    whose points are ``s`` times as far apart. NaN with fewer than ``min_correspondences``
    pairs or a degenerate fit (no scale to test)."""
    if x_source.shape[0] < min_correspondences:
        return float("nan")
    try:
        scale = float(_umeyama_transport(x_source, x_target, weights, min_correspondences).T[7])
    except GeometryError:
        return float("nan")
    return math.log(scale) if scale > 0 else float("nan")


def residual_ratio(x_i: Tensor, x_j: Tensor, centre_i: Tensor) -> float:
    """How far an edge's matched points disagree, relative to their range.

    ``median ||x_i - x_j|| / median ||x_i - c_i||`` for matched points lifted into one world
    frame. Scale-free: a relative rotation error of theta gives about theta (radians), a
    translation error of d about d over the median range. Infinite without points.

    Args:
        x_i: ``(N, 3)`` endpoint-i points in the world.
        x_j: ``(N, 3)`` their matches from endpoint j, lifted with the pose to be tested.
        centre_i: ``(3,)`` camera centre of endpoint i in the same world frame.
    """
    if x_i.shape[0] == 0:
        return float("inf")
    distance = (x_i - x_j).norm(dim=-1).median()
    reach = (x_i - centre_i.to(x_i)).norm(dim=-1).median()
    return float(distance / reach.clamp_min(torch.finfo(x_i.dtype).tiny))


def transport(T: Tensor, T_WC: Tensor) -> Tensor:
    """Left-multiply ``T (8,)`` onto poses ``T_WC (..., 8)`` (C-Eq. 15)."""
    return sim3_compose(T.to(T_WC).expand_as(T_WC), T_WC)


def lift(T_WC: Tensor, X: Tensor) -> Tensor:
    """Camera-frame points ``X (N, 3)`` into the world frame of ``T_WC (8,)``."""
    return sim3_act_points(T_WC, X)
