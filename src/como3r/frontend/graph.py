"""Keyframe graphs: edges between keyframes and the factors they give (C-Sec. 3.3, A.3).

A graph edge (i, j) stores only what the pair's decode produced (matches, validity,
confidences: :class:`~como3r.frontend.pairs.DirectedMatches`); :func:`build_factors`
turns a list of edges into one batch of factors (ray-and-range, or pixel and log-depth
when calibrated) on the keyframes' current canonical pointmaps, padding edges of different pixel counts, so the per-agent local solve
and the coordinator's global bundle adjustment build their problems with the same code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import torch
from torch import Tensor

from como3r.config import TrackingConfig
from como3r.frontend.pairs import DirectedMatches, gather_points
from como3r.geometry.camera import project
from como3r.geometry.units import median_point_range
from como3r.optim.factors import CalibratedFactors, RayRangeFactors


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
    i: Tensor, j: Tensor, X_i: Tensor, X_j: Tensor, q: Tensor, valid: Tensor,
    tracking: TrackingConfig, K_i: Tensor | None = None,
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
        return RayRangeFactors(i, j, X_i, X_j, q, valid, sigma_ray=tracking.sigma_ray,
                               sigma_dist=tracking.sigma_dist, huber_k=tracking.huber_k,
                               range_scale=median_point_range(X_i, valid))
    # X_i lies on K_i's rays (C-Eq. 16), so its projection is exactly its pixel
    return CalibratedFactors(i, j, X_j, project(X_i, K_i[:, None]), X_i[..., 2], K_i, q, valid,
                             sigma_pixel=tracking.sigma_pixel, sigma_depth=tracking.sigma_depth,
                             huber_k=tracking.huber_k)


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
    P = max(e.matches.idx.numel() for e in edges)
    X_i, X_j, q, valid = [], [], [], []
    for e in edges:
        kf_i, kf_j = keyframe(e.i), keyframe(e.j)
        pad = P - e.matches.idx.numel()
        X_i.append(_pad(gather_points(kf_i.X_hat, e.matches.idx), pad))
        X_j.append(_pad(kf_j.X_hat.reshape(-1, 3), pad))
        q.append(_pad(e.matches.q, pad))
        valid.append(_pad(e.matches.valid, pad))
    device = edges[0].matches.idx.device
    intrinsics = [keyframe(e.i).K for e in edges]
    K_i = torch.stack(intrinsics).to(X_i[0]) if all(K is not None for K in intrinsics) else None
    return make_factors(
        torch.tensor([pose_index(e.i) for e in edges], device=device),
        torch.tensor([pose_index(e.j) for e in edges], device=device),
        torch.stack(X_i), torch.stack(X_j), torch.stack(q), torch.stack(valid), tracking, K_i,
    )


def _pad(x: Tensor, pad: int) -> Tensor:
    """Append ``pad`` zero rows (invalid matches) to ``x (P, ...)``."""
    if pad == 0:
        return x
    return torch.cat([x, x.new_zeros((pad, *x.shape[1:]))])
