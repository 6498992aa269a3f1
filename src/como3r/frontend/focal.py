"""Focal lengths from keyframe pairs: the energy of a trial focal correction and its search.

A self-calibrated agent (:mod:`como3r.frontend.calibration`) locks every keyframe to one
pinhole camera (C-Eq. 16), and a learned prior gets that field of view wrong by several
percent per image (MUSt3R: 4 deg mean field-of-view error). A canonical pointmap on the rays
of a focal length ``f exp(delta)`` instead of ``f`` is ``X' = (x exp(-delta), y exp(-delta),
z)``: the same depths, stretched across the image. Two keyframes that see one surface
stretched differently, or stretched alike but through cameras turned against each other,
disagree in a way no Sim(3) aligns.

So a verified keyframe pair observes the focal length: for a trial ``delta`` the pair's
pointmaps and intrinsics are rescaled, its relative Sim(3) is solved on the calibrated
factors (C-Eq. 17, both directions, the first keyframe pinned), and the summed robust energy
(C-Eq. 5) plus a weak prior ``(delta / prior_sigma)^2 / 2`` is minimised over ``delta`` by
golden-section search. Two uses:

* an agent's own pairs (:attr:`FocalPair.shared`: one camera, both keyframes take the
  correction): the agent's camera from its first keyframes' multi-view geometry
  (:func:`como3r.frontend.calibration.refine_focal`);
* at a merge (C-Sec. A.3), pairs between the anchor and the moving component: only the
  moving keyframe takes the correction, and the whole moving component then shares the
  anchor agent's focal length (:meth:`~como3r.backend.global_graph.GlobalGraph.
  rescale_focal`; a como3r addition: the paper's agents are calibrated or take each
  prediction's own rays).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from como3r.config import GlobalBAConfig, TrackingConfig
from como3r.frontend.graph import make_factors
from como3r.frontend.pairs import DirectedMatches, gather_points
from como3r.geometry.camera import rescale_focal
from como3r.geometry.lie import sim3_compose, sim3_identity, sim3_inverse
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.values import PoseValues

#: Golden-section ratio of the search.
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True)
class FocalPair:
    """A verified keyframe pair: an anchor keyframe and a moving one.

    Attributes:
        X_anchor, X_moving: ``(H, W, 3)`` canonical pointmaps on their cameras' rays.
        K_anchor, K_moving: ``(3, 3)`` their intrinsics at the pointmaps' resolution.
        T_anchor_moving: ``(8,)`` Sim(3) pose of the moving keyframe in the anchor's camera
            (the start of each relative solve).
        in_anchor: every pixel of the moving keyframe looked up in the anchor keyframe.
        in_moving: every pixel of the anchor keyframe looked up in the moving keyframe.
        shared: both keyframes are one camera (an agent's own pair) and take the correction
            together; False: the moving keyframe alone (a merge).
    """

    X_anchor: Tensor
    X_moving: Tensor
    K_anchor: Tensor
    K_moving: Tensor
    T_anchor_moving: Tensor
    in_anchor: DirectedMatches
    in_moving: DirectedMatches
    shared: bool = False


@dataclass(frozen=True)
class FocalEstimate:
    """A log focal correction and how it was found.

    Attributes:
        log_focal: ``delta``; the moving focal lengths are multiplied by ``exp(delta)``.
        evaluations: relative solves run per pair.
        energy_gain: energy at ``delta = 0`` minus energy at the estimate (>= 0).
    """

    log_focal: float
    evaluations: int
    energy_gain: float


def estimate_log_focal(
    pairs: Sequence[FocalPair],
    tracking: TrackingConfig,
    search: float = 0.3,
    prior_sigma: float = 0.1,
    tolerance: float = 1e-3,
    max_matches: int = 4096,
    max_iters: int = 10,
) -> FocalEstimate:
    """The log focal correction of the moving (or shared) keyframes that best fits ``pairs``.

    Args:
        pairs: verified keyframe pairs (at least one).
        tracking: noise model and Huber breakpoint of the factors (C-Eq. 7-8, 17).
        search: the correction is searched in ``[-search, search]``.
        prior_sigma: RMS of the weak zero-mean prior on the correction (two agents' focal
            estimates, each about 8 % off, differ by about 0.1 in log).
        tolerance: width of the final bracket.
        max_matches: matches per direction and pair (evenly subsampled).
        max_iters: Gauss-Newton iterations of each relative solve.

    Returns:
        The correction with the smallest energy.
    """
    energy = _PairEnergy(pairs, tracking, max_matches, max_iters)
    low, high = -search, search
    a = high - _INV_PHI * (high - low)
    b = low + _INV_PHI * (high - low)
    f_a, f_b = energy(a, prior_sigma), energy(b, prior_sigma)
    while high - low > tolerance:
        if f_a <= f_b:
            high, b, f_b = b, a, f_a
            a = high - _INV_PHI * (high - low)
            f_a = energy(a, prior_sigma)
        else:
            low, a, f_a = a, b, f_b
            b = low + _INV_PHI * (high - low)
            f_b = energy(b, prior_sigma)
    best, f_best = (a, f_a) if f_a <= f_b else (b, f_b)
    f_zero = energy(0.0, prior_sigma)
    if f_zero <= f_best:
        best, f_best = 0.0, f_zero
    return FocalEstimate(best, energy.evaluations, f_zero - f_best)


class _PairEnergy:
    """Summed robust energy of the pairs' relative solves at a trial correction."""

    def __init__(self, pairs: Sequence[FocalPair], tracking: TrackingConfig, max_matches: int,
                 max_iters: int) -> None:
        self.pairs = list(pairs)
        self.tracking = tracking
        self.max_matches = max_matches
        self.max_iters = max_iters
        self.evaluations = 0

    def __call__(self, log_focal: float, prior_sigma: float) -> float:
        self.evaluations += 1
        total = 0.5 * (log_focal / prior_sigma) ** 2
        for pair in self.pairs:
            total += self._pair(pair, log_focal)
        return total

    def _pair(self, pair: FocalPair, log_focal: float) -> float:
        X_m, K_m = rescale_focal(pair.X_moving, pair.K_moving, log_focal)
        X_a, K_a = ((rescale_focal(pair.X_anchor, pair.K_anchor, log_focal)) if pair.shared
                    else (pair.X_anchor, pair.K_anchor))
        # node 0: the anchor keyframe (pinned at the identity), node 1: the moving one
        factors = [
            _directed_factor(0, 1, X_a, X_m, K_a, pair.in_anchor, self.tracking,
                             self.max_matches),
            _directed_factor(1, 0, X_m, X_a, K_m, pair.in_moving, self.tracking,
                             self.max_matches),
        ]
        start = torch.stack([sim3_identity(dtype=torch.float64), pair.T_anchor_moving.double()])
        values = PoseValues(start, torch.tensor([True, False]))
        solved, _ = gauss_newton_irls(factors, values, GlobalBAConfig(), max_iters=self.max_iters)
        return sum(float(f.cost(solved.poses.to(X_a.dtype))) for f in factors)


def _directed_factor(i: int, j: int, X_i: Tensor, X_j: Tensor, K_i: Tensor,
                     matches: DirectedMatches, tracking: TrackingConfig, max_matches: int):
    """The calibrated factor of one edge (i, j): pixels of j looked up in i (C-Eq. 17)."""
    pixels = torch.nonzero(matches.valid).flatten()
    if pixels.numel() > max_matches:
        pixels = pixels[torch.linspace(0, pixels.numel() - 1, max_matches).long()]
    X_i_m = gather_points(X_i, matches.idx[pixels])[None]
    X_j_m = X_j.reshape(-1, 3)[pixels][None]
    q = matches.q[pixels][None]
    return make_factors(torch.tensor([i]), torch.tensor([j]), X_i_m, X_j_m, q,
                        torch.ones_like(q, dtype=torch.bool), tracking, K_i[None].to(X_i_m))


def relative_pose(T_WC_anchor: Tensor, T_WC_moving: Tensor) -> Tensor:
    """``(8,)`` pose of the moving keyframe in the anchor keyframe's camera."""
    return sim3_compose(sim3_inverse(T_WC_anchor), T_WC_moving)

