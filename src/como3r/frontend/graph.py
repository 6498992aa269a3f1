"""Keyframe graphs: edges between keyframes and the factors they give (C-Sec. 3.3, A.3).

A graph edge (i, j) stores only what the pair's decode produced (matches, validity,
confidences: :class:`~como3r.frontend.pairs.DirectedMatches`); :func:`build_factors`
turns a list of edges into one batch of ray-and-range factors on the keyframes' current
canonical pointmaps, padding edges of different pixel counts, so the per-agent local solve
and the coordinator's global bundle adjustment build their problems with the same code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from como3r.config import TrackingConfig
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.pairs import DirectedMatches, gather_points
from como3r.optim.factors import RayRangeFactors


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


def build_factors(
    edges: Sequence[Edge],
    keyframe: Callable[[int], Keyframe],
    pose_index: Callable[[int], int],
    tracking: TrackingConfig,
) -> RayRangeFactors:
    """One factor batch over ``edges`` on the current canonical pointmaps.

    Args:
        edges: the graph's edges.
        keyframe: maps an edge endpoint key to its keyframe.
        pose_index: maps an edge endpoint key to its row in the pose tensor.
        tracking: noise model and Huber breakpoint (C-Eq. 7-8).

    Returns:
        :class:`RayRangeFactors` with ``E = len(edges)`` and ``P`` the largest pixel count.
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
    return RayRangeFactors(
        torch.tensor([pose_index(e.i) for e in edges], device=device),
        torch.tensor([pose_index(e.j) for e in edges], device=device),
        torch.stack(X_i), torch.stack(X_j), torch.stack(q), torch.stack(valid),
        sigma_ray=tracking.sigma_ray, sigma_dist=tracking.sigma_dist, huber_k=tracking.huber_k,
    )


def _pad(x: Tensor, pad: int) -> Tensor:
    """Append ``pad`` zero rows (invalid matches) to ``x (P, ...)``."""
    if pad == 0:
        return x
    return torch.cat([x, x.new_zeros((pad, *x.shape[1:]))])
