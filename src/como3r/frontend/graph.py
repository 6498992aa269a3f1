"""Keyframe graphs: edges between keyframes and the factors they give (C-Sec. 3.3, A.3).

A graph edge (i, j) stores only what the pair's decode produced (matches, validity,
confidences: :class:`~como3r.frontend.pairs.DirectedMatches`); :func:`build_factors`
turns a list of edges into one batch of factors (ray-and-range, or pixel and log-depth
when calibrated) on the keyframes' current canonical pointmaps, each edge's valid matches
packed and padded to the batch's largest count (:func:`packed_matches`), so the per-agent
local solve and the coordinator's global bundle adjustment build their problems with the
same code.
An agent's local solve takes its old edges (both keyframes outside the newest few) as the
quadratic models a :class:`QuadraticEdgeCache` keeps of them, so its memory and time do not
grow with the graph (issue 14, bounded memory).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor

from como3r.config import TrackingConfig
from como3r.frontend import cpu_kernels
from como3r.frontend.pairs import DirectedMatches
from como3r.geometry.camera import project
from como3r.geometry.units import median_point_range, median_range
from como3r.optim.factors import QuadraticEdges
from como3r.optim.match_factors import CalibratedFactors, RayRangeFactors
from como3r.optim.system import EdgeBlocks

#: edges linearized at once when their quadratic models are made (bounds the dense factors)
QUADRATIC_CHUNK_EDGES = 64


@dataclass(frozen=True)
class Edge:
    """A directed dense edge between two keyframes.

    Attributes:
        i: key of keyframe i (an agent-local id, or a global index in the coordinator).
        j: key of keyframe j.
        matches: pixel of i for every pixel of j, validity and confidence.
        kind: ``"sequential"``, ``"loop"`` or ``"inter"``.
    """

    i: int
    j: int
    matches: DirectedMatches
    kind: str = "sequential"


def make_factors(
    i: Tensor,
    j: Tensor,
    X_i: Tensor,
    X_j: Tensor,
    q: Tensor,
    valid: Tensor,
    tracking: TrackingConfig,
    K_i: Tensor | None = None,
) -> RayRangeFactors | CalibratedFactors:
    """Factors for matched point pairs: ray-and-range (C-Eq. 6) or, with intrinsics,
    pixel and log-depth (C-Eq. 17).

    Args:
        i, j: ``(E,)`` pose indices; the residual depends on ``T_ij = T_WC_i^-1 T_WC_j``.
        X_i: ``(E, P, 3)`` target points in camera i (on the calibrated rays if ``K_i``).
        X_j: ``(E, P, 3)`` matched points in camera j.
        q: ``(E, P)`` match confidences; valid: ``(E, P)`` bool.
        tracking: noise model and Huber breakpoint (C-Eq. 7-8).
        K_i: ``(E, 3, 3)`` intrinsics of camera i for a calibrated run.
    """
    if K_i is None:
        # sigma_dist is relative to the scene: times the median range of i's points (units.py)
        return RayRangeFactors(
            i,
            j,
            X_i,
            X_j,
            q,
            valid,
            sigma_ray=tracking.sigma_ray,
            sigma_dist=tracking.sigma_dist,
            huber_k=tracking.huber_k,
            range_scale=median_point_range(X_i, valid),
        )
    # X_i lies on K_i's rays (C-Eq. 16), so its projection is exactly its pixel
    return CalibratedFactors(
        i,
        j,
        X_j,
        project(X_i, K_i[:, None]),
        X_i[..., 2],
        K_i,
        q,
        valid,
        sigma_pixel=tracking.sigma_pixel,
        sigma_depth=tracking.sigma_depth,
        huber_k=tracking.huber_k,
    )


class Pointmap(Protocol):
    """What a solve reads of a keyframe (a :class:`~.keyframes.Keyframe` has both)."""

    @property
    def X_hat(self) -> Tensor:
        """``(H, W, 3)`` canonical pointmap in the keyframe's camera frame."""

    @property
    def K(self) -> Tensor | None:
        """``(3, 3)`` intrinsics of a calibrated run, else None."""


def build_factors(
    edges: Sequence[Edge],
    keyframe: Callable[[int], Pointmap],
    pose_index: Callable[[int], int],
    tracking: TrackingConfig,
) -> RayRangeFactors | CalibratedFactors:
    """One factor batch over graph ``edges`` on the current canonical pointmaps.

    Keyframes with intrinsics (a calibrated run, C-Sec. A.5) give C-Eq. 17 factors.

    Args:
        edges: the graph's edges.
        keyframe: maps an edge endpoint key to its keyframe (or what a solve reads of it).
        pose_index: maps an edge endpoint key to its row in the pose tensor.
        tracking: noise model and Huber breakpoint (C-Eq. 7-8).

    Returns:
        A factor batch with ``E = len(edges)`` and ``P`` the largest pixel count.
    """
    X_i, X_j, q, valid = packed_matches(edges, keyframe)
    device = edges[0].matches.idx.device
    intrinsics = [keyframe(e.i).K for e in edges]
    K_i = torch.stack(intrinsics).to(X_i) if all(K is not None for K in intrinsics) else None
    return make_factors(
        torch.tensor([pose_index(e.i) for e in edges], device=device),
        torch.tensor([pose_index(e.j) for e in edges], device=device),
        X_i,
        X_j,
        q,
        valid,
        tracking,
        K_i,
    )


def thinned(edge: Edge, max_matches: int) -> tuple[Edge, float]:
    """``edge`` with its valid matches thinned to every ``k``-th in pixel order, ``k`` the
    smallest stride leaving at most ``max_matches`` (0: all kept), and the weight of each
    kept match: valid matches over kept ones (1 where none were dropped).

    Not in the paper (issue 41): a global solve's cost is its edges' matches, 10^5 an edge
    at 512x384, and the prior's errors are smooth across the image, so an even subset
    constrains the relative pose as all of them do, at a share of the cost and memory.
    """
    matches = edge.matches
    valid = matches.valid
    count = int(valid.sum())
    if max_matches <= 0 or count <= max_matches:
        return edge, 1.0
    stride = -(-count // max_matches)
    rank = torch.cumsum(valid, 0) - 1
    kept = valid & (rank % stride == 0)
    return (
        replace(edge, matches=DirectedMatches(matches.idx, kept, matches.q)),
        count / int(kept.sum()),
    )


#: Edges per factor batch of a global solve (a batch pads its edges to its largest match
#: count, so edges are batched by count)
EDGES_PER_BATCH = 8


def count_batches(
    edges: Sequence[Edge], max_matches: int
) -> list[tuple[list[int], list[Edge], Tensor | None]]:
    """``edges`` thinned (:func:`thinned`) and grouped :data:`EDGES_PER_BATCH` at a time by
    ascending valid-match count, so a batch pads little: per group the edges' positions in
    ``edges``, the thinned edges and their weights ``(e,)`` float64 (None where all are 1)."""
    chosen = [thinned(e, max_matches) for e in edges]
    order = sorted(range(len(edges)), key=lambda p: int(chosen[p][0].matches.valid.sum()))
    groups = []
    for s in range(0, len(order), EDGES_PER_BATCH):
        at = order[s : s + EDGES_PER_BATCH]
        weights = [chosen[p][1] for p in at]
        groups.append(
            (
                at,
                [chosen[p][0] for p in at],
                None
                if all(w == 1.0 for w in weights)
                else torch.tensor(weights, dtype=torch.float64),
            )
        )
    return groups


def packed_matches(
    edges: Sequence[Edge], keyframe: Callable[[int], Pointmap]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The edges' valid matches, each edge's packed to the front of its row in pixel order
    and padded with invalid ones to the largest count ``P`` (at least 1).

    The factors drop invalid matches anyway (they weigh nothing: C-Eq. 5, 7), and with a
    third to two thirds of a pair's pixels unmatched, packing before the batch is made
    spares the batch those rows.

    Returns:
        ``X_i (E, P, 3)`` points of keyframe i at the matched pixels, ``X_j (E, P, 3)``
        points of keyframe j, ``q (E, P)`` confidences, ``valid (E, P)`` bool.
    """
    counts = [int(e.matches.valid.sum()) for e in edges]
    P = max(1, *counts)
    first = keyframe(edges[0].i).X_hat
    X_i = first.new_zeros((len(edges), P, 3))
    X_j = torch.zeros_like(X_i)
    q = edges[0].matches.q.new_zeros((len(edges), P))
    valid = torch.zeros((len(edges), P), dtype=torch.bool, device=first.device)
    for k, e in enumerate(edges):
        X_hat_i, X_hat_j = keyframe(e.i).X_hat.reshape(-1, 3), keyframe(e.j).X_hat.reshape(-1, 3)
        if first.device.type == "cpu":
            cpu_kernels.pack_valid(
                X_hat_i.to(X_i),
                X_hat_j.to(X_j),
                e.matches.idx,
                e.matches.valid,
                e.matches.q.to(q),
                X_i[k],
                X_j[k],
                q[k],
                valid[k],
            )
            continue
        n = torch.nonzero(e.matches.valid).squeeze(-1)
        X_i[k, : counts[k]] = X_hat_i[e.matches.idx[n]]
        X_j[k, : counts[k]] = X_hat_j[n]
        q[k, : counts[k]] = e.matches.q[n]
        valid[k, : counts[k]] = True
    return X_i, X_j, q, valid


class QuadraticEdgeCache:
    """Quadratic models (:class:`~como3r.optim.factors.QuadraticEdges`) of a graph's old
    edges, kept between solves, so a solve over every edge holds dense factors only for the
    edges near the newest keyframes (bounded memory, issue 14).

    A model is made again, from the edge's dense factors, whenever it is linearized while
    either endpoint's pointmap changed since it was made (``version``), or while the edge's
    relative pose is more than ``tol`` from the model's: rotation and log-scale in radians
    and nepers, translation in units of keyframe i's median range. With ``tol`` -> 0 a
    solve is the all-dense one. Rows are indexed by the edge's position in the graph's
    append-only edge list.
    """

    def __init__(self) -> None:
        self._T0 = torch.zeros(0, 8, dtype=torch.float64)
        self._H = torch.zeros(0, 7, 7, dtype=torch.float64)
        self._g = torch.zeros(0, 7, dtype=torch.float64)
        self._c = torch.zeros(0, dtype=torch.float64)
        self._length = torch.ones(0, dtype=torch.float64)  # keyframe i's median range
        self._versions = torch.full((0, 2), -1, dtype=torch.int64)  # -1: no model
        self.remade = 0  # models made, over the cache's life

    def factor(
        self,
        edges: Sequence[Edge],
        old: Sequence[int],
        points: Callable[[], Callable[[int], Pointmap]],
        version: Callable[[int], int],
        tracking: TrackingConfig,
        tol: float,
    ) -> ModeledEdges:
        """The edges ``old`` (positions in ``edges``) as one factor of a solve whose pose
        index is the keyframe key.

        Args:
            edges: the graph's edges.
            old: positions of the edges to model.
            points: makes a fresh reader of what a solve reads of a keyframe (one per chunk
                of edges linearized, so read-backs are let go chunk by chunk).
            version: the current version of a keyframe's pointmaps.
            tracking: noise model and Huber breakpoint (C-Eq. 7-8).
            tol: relinearization tolerance (class docstring).
        """
        self._grow(len(edges))
        ij = torch.tensor([(edges[n].i, edges[n].j) for n in old], dtype=torch.int64)
        versions = torch.tensor(
            [(version(i), version(j)) for i, j in ij.tolist()], dtype=torch.int64
        )
        return ModeledEdges(
            self,
            edges,
            torch.tensor(list(old), dtype=torch.int64),
            ij.reshape(-1, 2),
            versions.reshape(-1, 2),
            points,
            tracking,
            tol,
        )

    def models(self, factor: ModeledEdges, poses: Tensor) -> QuadraticEdges:
        """The models of ``factor``'s edges at ``poses`` ``(N, 8)``, stale ones made again."""
        rows = factor.rows
        stale = (self._versions[rows] != factor.versions).any(1)
        moved = self._model(rows, factor.ij).motion(poses).abs()
        moved[:, :3] /= self._length[rows, None]
        stale |= (moved > factor.tol).any(1)
        for start in range(0, int(stale.sum()), QUADRATIC_CHUNK_EDGES):
            chunk = rows[stale][start : start + QUADRATIC_CHUNK_EDGES]
            self._remake(
                chunk,
                [factor.edges[n] for n in chunk.tolist()],
                factor.points(),
                poses,
                factor.tracking,
            )
        self._versions[rows] = factor.versions
        return self._model(rows, factor.ij)

    def _model(self, rows: Tensor, ij: Tensor) -> QuadraticEdges:
        return QuadraticEdges(
            ij[:, 0], ij[:, 1], self._T0[rows], self._H[rows], self._g[rows], self._c[rows]
        )

    def _remake(
        self,
        rows: Tensor,
        edges: list[Edge],
        keyframe: Callable[[int], Pointmap],
        poses: Tensor,
        tracking: TrackingConfig,
    ) -> None:
        model = build_factors(edges, keyframe, lambda k: k, tracking).quadratic_model(poses)
        self._T0[rows], self._H[rows], self._g[rows], self._c[rows] = (
            model.T0,
            model.H,
            model.g,
            model.c,
        )
        self._length[rows] = torch.stack([median_range(keyframe(e.i).X_hat) for e in edges]).to(
            torch.float64
        )
        self.remade += len(edges)

    def _grow(self, size: int) -> None:
        """Room for ``size`` rows (capacity doubles)."""
        have = self._T0.shape[0]
        if size <= have:
            return
        extra = max(size, 2 * have) - have
        self._T0 = torch.cat([self._T0, self._T0.new_zeros(extra, 8)])
        self._T0[have:, 6:] = 1.0  # identity poses, so an unused row's motion is finite
        self._H = torch.cat([self._H, self._H.new_zeros(extra, 7, 7)])
        self._g = torch.cat([self._g, self._g.new_zeros(extra, 7)])
        self._c = torch.cat([self._c, self._c.new_zeros(extra)])
        self._length = torch.cat([self._length, self._length.new_ones(extra)])
        self._versions = torch.cat([self._versions, self._versions.new_full((extra, 2), -1)])


@dataclass(frozen=True, eq=False)
class ModeledEdges:
    """Old edges entering a solve by their quadratic models (a Factor), made again where
    stale at every linearization (:class:`QuadraticEdgeCache`).

    Attributes:
        cache: where the models are kept.
        edges: the graph's edges; rows: ``(E,)`` positions of the modeled ones.
        ij: ``(E, 2)`` their endpoints (pose indices); versions: ``(E, 2)`` the endpoints'
            pointmap versions.
        points, tracking, tol: as in :meth:`QuadraticEdgeCache.factor`.
    """

    cache: QuadraticEdgeCache
    edges: Sequence[Edge]
    rows: Tensor
    ij: Tensor
    versions: Tensor
    points: Callable[[], Callable[[int], Pointmap]]
    tracking: TrackingConfig
    tol: float

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to."""
        return int(self.ij.max()) if self.ij.numel() else -1

    def linearize(self, poses: Tensor) -> EdgeBlocks:
        """Per-edge Gauss-Newton blocks at ``poses`` ``(N, 8)``."""
        return self.cache.models(self, poses).linearize(poses)

    def cost(self, poses: Tensor) -> Tensor:
        """The models' energy at ``poses`` ``(N, 8)``, a float64 scalar."""
        return self.cache.models(self, poses).cost(poses)
