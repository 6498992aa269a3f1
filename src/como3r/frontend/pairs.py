"""Dense keyframe-pair edges: symmetric decode, two-way matching, match fractions.

Every edge of every graph (intra-agent sequential and loop edges, verified inter-agent
edges) is built here, so they all carry the same payload (C-Sec. A.3): for the ordered
pair (i, j), the pixel ``m`` of keyframe i matched to every pixel ``n`` of keyframe j,
its validity and the per-match confidence ``q_mn = sqrt(Q_i,m Q_j,n)`` (C-Eq. 7). The
residual of an edge is evaluated on the keyframes' *current* canonical pointmaps, so an
edge survives fusion and depth refinement unchanged.

The match fraction ``nu`` of a direction is the share of pixels with a valid match whose
confidence exceeds ``Q_min``; an edge is kept when ``min(nu_i, nu_j)`` reaches the
threshold of its use (C-Eq. 12: ``tau_inter`` across agents).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from como3r.config import MatchingConfig
from como3r.frontend.matching import match_confidence, match_pointmaps
from como3r.prior.base import Encoding, PairPrediction, Prior


@dataclass(frozen=True)
class DirectedMatches:
    """Matches of the ordered pair (i, j): pixel ``idx[n]`` of i for each pixel n of j.

    Attributes:
        idx: ``(P_j,)`` int64 linear pixel of keyframe i per pixel of keyframe j.
        valid: ``(P_j,)`` bool: geometrically valid and ``q > Q_min``.
        q: ``(P_j,)`` per-match confidence.
    """

    idx: Tensor
    valid: Tensor
    q: Tensor

    @property
    def match_fraction(self) -> float:
        """Share of pixels of j with a valid match (``nu``)."""
        return float(self.valid.float().mean()) if self.valid.numel() else 0.0


@dataclass(frozen=True)
class PairLink:
    """Both directions of a decoded keyframe pair.

    Attributes:
        ij: matches for the edge (i, j) (pixels of j looked up in i).
        ji: matches for the edge (j, i) (pixels of i looked up in j).
    """

    ij: DirectedMatches
    ji: DirectedMatches

    @property
    def min_match_fraction(self) -> float:
        """``min(nu_i, nu_j)`` of C-Eq. 12."""
        return min(self.ij.match_fraction, self.ji.match_fraction)


def directed_matches(
    pred: PairPrediction, matching: MatchingConfig, q_min: float, p_init: Tensor | None = None
) -> DirectedMatches:
    """Match every pixel of view j (``X_ji``) to a pixel of view i (``X_ii``).

    Args:
        pred: prediction of the ordered pair (i, j), shapes ``(H, W, ...)``.
        matching: matching parameters.
        q_min: minimum match confidence.
        p_init: optional ``(1, P, 2)`` warm start.
    """
    m = match_pointmaps(
        pred.X_ii[None], pred.X_ji[None], pred.D_ii[None], pred.D_ji[None], matching, p_init
    )
    q = match_confidence(pred.Q_ji.reshape(1, -1), pred.Q_ii[None], m.idx)[0]
    return DirectedMatches(idx=m.idx[0], valid=m.valid[0] & (q > q_min), q=q)


def link_pairs(
    prior: Prior,
    pairs: Sequence[tuple[Encoding, Encoding]],
    matching: MatchingConfig,
    q_min: float,
) -> list[PairLink]:
    """Decode each pair symmetrically (one batched call) and match both directions."""
    if not pairs:
        return []
    predictions = prior.decode_symmetric(pairs)
    return [
        PairLink(ij=directed_matches(p_ij, matching, q_min), ji=directed_matches(p_ji, matching, q_min))
        for p_ij, p_ji in predictions
    ]


def gather_points(X: Tensor, idx: Tensor) -> Tensor:
    """Rows ``idx (P,)`` of a pointmap ``X (H, W, 3)`` -> ``(P, 3)``."""
    return X.reshape(-1, 3)[idx]


def empty_matches(num_pixels: int, device: torch.device) -> DirectedMatches:
    """Matches with nothing valid (a placeholder for a failed direction)."""
    return DirectedMatches(
        idx=torch.zeros(num_pixels, dtype=torch.long, device=device),
        valid=torch.zeros(num_pixels, dtype=torch.bool, device=device),
        q=torch.zeros(num_pixels, device=device),
    )
