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

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from como3r.config import MatchingConfig
from como3r.frontend.matching import match_confidence, match_pointmaps
from como3r.frontend.timing import StageTimer
from como3r.prior.base import Encoding, PairPrediction, Prior

#: Share of view i's rays left out on each side when taking the box of its field of view:
#: a few stray rays at depth discontinuities must not widen it.
FIELD_OF_VIEW_QUANTILE = 0.01


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
        covisible_ij: share of j's pixels the prediction (i, j) puts where i sees
            (:func:`covisible_fraction`), None when not computed.
        covisible_ji: the same for i's pixels in j.
    """

    ij: DirectedMatches
    ji: DirectedMatches
    covisible_ij: float | None = None
    covisible_ji: float | None = None

    @property
    def covisible_ratio(self) -> float | None:
        """The smaller share, over both directions, of co-visible pixels that match."""
        if self.covisible_ij is None or self.covisible_ji is None:
            return None
        return min(
            _ratio(self.ij.match_fraction, self.covisible_ij),
            _ratio(self.ji.match_fraction, self.covisible_ji),
        )

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
    covisible_min_confidence: float | None = None,
    timer: StageTimer | None = None,
    screen: Callable[[int, DirectedMatches, float | None], bool] | None = None,
) -> list[PairLink | None]:
    """Decode each pair both ways and match both directions.

    With ``covisible_min_confidence`` the links also carry their co-visible fractions;
    ``timer`` is charged with the stage ``matching``. Without ``screen`` both orders of
    every pair are decoded in one batched call. With it, the pairs (i, j) are decoded and
    matched first and ``screen(k, ij, covisible_ij)`` asked for pair k: when it returns False
    the pair cannot pass a test that needs both directions, and its reverse (j, i) is neither
    decoded nor matched (its link is None); the survivors' reverses are decoded in a second
    batched call. A screened-out pair so costs one decode instead of two (MASt3R: a whole
    decoder and head pass).
    """
    if not pairs:
        return []
    timer = StageTimer() if timer is None else timer
    if screen is None:
        return [
            _link(p_ij, p_ji, matching, q_min, covisible_min_confidence, timer)
            for p_ij, p_ji in prior.decode_symmetric(pairs)
        ]
    firsts: list[tuple[DirectedMatches, float | None] | None] = []
    for k, p_ij in enumerate(prior.decode_pairs(pairs)):
        ij, cov_ij = _direction(p_ij, matching, q_min, covisible_min_confidence, timer)
        firsts.append((ij, cov_ij) if screen(k, ij, cov_ij) else None)
    survivors = [k for k, first in enumerate(firsts) if first is not None]
    reverses = prior.decode_pairs([(pairs[k][1], pairs[k][0]) for k in survivors])
    links: list[PairLink | None] = [None] * len(pairs)
    for k, p_ji in zip(survivors, reverses):
        ij, cov_ij = firsts[k]  # type: ignore[misc]
        ji, cov_ji = _direction(p_ji, matching, q_min, covisible_min_confidence, timer)
        links[k] = PairLink(ij, ji, cov_ij, cov_ji)
    return links


def _direction(
    pred: PairPrediction,
    matching: MatchingConfig,
    q_min: float,
    covisible_min_confidence: float | None,
    timer: StageTimer,
) -> tuple[DirectedMatches, float | None]:
    """One direction's matches and (with ``covisible_min_confidence``) co-visible fraction."""
    with timer.stage("matching"):
        matches = directed_matches(pred, matching, q_min)
    covisible = (
        None
        if covisible_min_confidence is None
        else covisible_fraction(pred, matches, covisible_min_confidence)
    )
    return matches, covisible


def _link(
    p_ij: PairPrediction,
    p_ji: PairPrediction,
    matching: MatchingConfig,
    q_min: float,
    covisible_min_confidence: float | None,
    timer: StageTimer,
) -> PairLink:
    """Both directions of a decoded pair."""
    ij, cov_ij = _direction(p_ij, matching, q_min, covisible_min_confidence, timer)
    ji, cov_ji = _direction(p_ji, matching, q_min, covisible_min_confidence, timer)
    return PairLink(ij, ji, cov_ij, cov_ji)


def direction_passes(
    matches: DirectedMatches,
    covisible: float | None,
    min_match_fraction: float,
    min_covisible_ratio: float,
) -> bool:
    """One direction of a link has ``nu >= min_match_fraction`` and, where its co-visible
    fraction is known, matches at least ``min_covisible_ratio`` of its co-visible pixels.

    A link passes ``min(nu_i, nu_j) >= min_match_fraction`` and
    ``covisible_ratio >= min_covisible_ratio`` exactly when both its directions pass.
    """
    if matches.match_fraction < min_match_fraction:
        return False
    return covisible is None or _ratio(matches.match_fraction, covisible) >= min_covisible_ratio


def _ratio(matched: float, covisible: float) -> float:
    """``matched / covisible``, 0 when nothing is co-visible."""
    return matched / covisible if covisible > 0 else 0.0


def covisible_fraction(
    pred: PairPrediction, matches: DirectedMatches, min_confidence: float
) -> float:
    """Share of view j's pixels that the prediction puts where view i confidently sees.

    A pixel n of j is co-visible when its point ``X_ji[n]`` lies in front of camera i and
    inside the box that view i's own rays span on the plane ``z = 1``, and the pixel of i
    it was matched to has confidence ``C_ii >= min_confidence``.

    Args:
        pred: prediction of the ordered pair (i, j), ``X (H, W, 3)`` in camera i.
        matches: every pixel of j looked up in i (from the same prediction).
        min_confidence: confidence a pixel of i needs to count as seen.
    """
    X_i, X_j = pred.X_ii.reshape(-1, 3), pred.X_ji.reshape(-1, 3)
    ahead = X_i[:, 2] > 0
    if not bool(ahead.any()):
        return 0.0
    low, high = _quantiles(
        X_i[ahead, :2] / X_i[ahead, 2:], (FIELD_OF_VIEW_QUANTILE, 1.0 - FIELD_OF_VIEW_QUANTILE)
    )
    depth_j = X_j[:, 2:]
    plane_j = X_j[:, :2] / depth_j.clamp_min(torch.finfo(X_j.dtype).tiny)
    inside = (depth_j[:, 0] > 0) & ((plane_j > low) & (plane_j < high)).all(dim=-1)
    seen = pred.C_ii.reshape(-1)[matches.idx] >= min_confidence
    return float((inside & seen).float().mean())


def _quantiles(x: Tensor, qs: tuple[float, ...]) -> Tensor:
    """``(len(qs), D)`` quantiles of ``x (N, D)`` along its rows, linearly interpolated as
    :func:`torch.quantile`'s. On CPU by numpy's selection (O(N); torch.quantile sorts every
    column once per call: 13x slower for both bounds of a 512x384 view,
    ``benchmarks/matching_kernel.py``; the front-end and the coordinator's verification ask
    once per decoded direction)."""
    if x.device.type != "cpu":
        return torch.quantile(x, torch.tensor(qs, dtype=x.dtype, device=x.device), dim=0)
    return torch.from_numpy(np.quantile(x.numpy(), qs, axis=0)).to(x.dtype)


def gather_points(X: Tensor, idx: Tensor) -> Tensor:
    """Rows ``idx (P,)`` of a pointmap ``X (H, W, 3)`` -> ``(P, 3)``."""
    return X.reshape(-1, 3)[idx]


def matched_points(
    matches: DirectedMatches, X_target: Tensor, X_source: Tensor, most: int = 0
) -> tuple[Tensor, Tensor, Tensor]:
    """Valid matches of ``matches`` as point pairs ``(X_target[idx[n]], X_source[n])``,
    evenly subsampled to at most ``most`` (0: all).

    Args:
        matches: every pixel ``n`` of the source keyframe looked up in the target.
        X_target: ``(H, W, 3)`` target pointmap.
        X_source: ``(H, W, 3)`` source pointmap.
        most: the most pairs kept (a gauge edge's ``gauge.max_correspondences``, a focal
            pair's ``max_matches``).

    Returns:
        ``(M, 3)`` target points, ``(M, 3)`` source points and their match confidences
        ``q (M,)``.
    """
    pixels = torch.nonzero(matches.valid).flatten()
    if 0 < most < pixels.numel():
        pixels = pixels[torch.linspace(0, pixels.numel() - 1, most).long()]
    return (
        gather_points(X_target, matches.idx[pixels]),
        X_source.reshape(-1, 3)[pixels],
        matches.q[pixels],
    )
