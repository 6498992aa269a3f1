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
Brent's bounded search (scipy). Two uses:

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
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import GlobalBAConfig, TrackingConfig
from como3r.frontend.graph import make_factors
from como3r.frontend.pairs import DirectedMatches, matched_points
from como3r.geometry.lie import sim3_compose, sim3_identity, sim3_inverse
from como3r.geometry.units import median_point_range
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.values import PoseValues


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
        tolerance: the search's absolute tolerance on ``delta`` (scipy's ``xatol``).
        max_matches: matches per direction and pair (evenly subsampled).
        max_iters: Gauss-Newton iterations of each relative solve.

    Returns:
        The correction with the smallest energy.
    """
    # local: scipy.optimize costs a process ~0.2 s CPU to import; only self-calibration searches
    from scipy.optimize import minimize_scalar

    energy = _PairEnergy(pairs, tracking, max_matches, max_iters)
    # Brent's bounded search (golden sections and parabolic steps): on the pairs of
    # tests/frontend/test_focal.py 7-10 relative solves where a golden-section search took
    # 17 (the estimates within 2e-4 of its)
    found = minimize_scalar(
        energy,
        bounds=(-search, search),
        args=(prior_sigma,),
        method="bounded",
        options={"xatol": tolerance},
    )
    best, f_best = float(found.x), float(found.fun)
    f_zero = energy(0.0, prior_sigma)
    if f_zero <= f_best:
        best, f_best = 0.0, f_zero
    return FocalEstimate(best, energy.evaluations, f_zero - f_best)


@dataclass(frozen=True)
class _Direction:
    """One matched direction of a pair, subsampled: pixels of node ``j`` looked up in node
    ``i``, with the points it compares (C-Eq. 17) and which side takes the correction."""

    i: int
    j: int
    X_i: Tensor  # (n, 3) points of i at the matched pixels
    X_j: Tensor  # (n, 3) points of j
    q: Tensor  # (n,)
    K_i: Tensor  # (3, 3)
    rescales_i: bool
    rescales_j: bool


class _PairEnergy:
    """Summed robust energy of the pairs' relative solves at a trial correction.

    Every pair is two nodes (its anchor, pinned at the identity, and its moving keyframe)
    of one batch, so one Gauss-Newton loop solves all pairs (their blocks are independent);
    each evaluation starts from the poses the previous one found (the search's trial
    corrections are close to each other).
    """

    def __init__(
        self, pairs: Sequence[FocalPair], tracking: TrackingConfig, max_matches: int, max_iters: int
    ) -> None:
        self.tracking = tracking
        self.max_iters = max_iters
        self.evaluations = 0
        self.directions: list[_Direction] = []
        for k, pair in enumerate(pairs):
            anchor, moving = 2 * k, 2 * k + 1
            self.directions += [
                _direction(
                    anchor,
                    moving,
                    pair.X_anchor,
                    pair.X_moving,
                    pair.K_anchor,
                    pair.in_anchor,
                    max_matches,
                    pair.shared,
                    True,
                ),
                _direction(
                    moving,
                    anchor,
                    pair.X_moving,
                    pair.X_anchor,
                    pair.K_moving,
                    pair.in_moving,
                    max_matches,
                    True,
                    pair.shared,
                ),
            ]
        identity = sim3_identity(dtype=torch.float64)
        self.poses = torch.stack(
            [T for pair in pairs for T in (identity, pair.T_anchor_moving.double())]
        )
        self.pinned = torch.arange(2 * len(pairs)) % 2 == 0
        # the solves' step tolerance in the pairs' own length (geometry.units)
        self.length = float(median_point_range(torch.cat([d.X_i for d in self.directions])))

    def __call__(self, log_focal: float, prior_sigma: float) -> float:
        self.evaluations += 1
        factors = self._factors(math.exp(log_focal))
        solved, _ = gauss_newton_irls(
            factors,
            PoseValues(self.poses, self.pinned),
            GlobalBAConfig(),
            max_iters=self.max_iters,
            length_scale=self.length,
        )
        self.poses = solved.poses
        data = float(factors.cost(solved.poses.to(factors.q.dtype)))
        return 0.5 * (log_focal / prior_sigma) ** 2 + data

    def _factors(self, factor: float):
        """The calibrated factors of every direction with the rescaled sides moved to the
        focal length times ``factor`` (x and y of their points over ``factor``, C-Eq. 16)."""
        n = max(d.q.numel() for d in self.directions)
        shrink = torch.tensor([1.0 / factor, 1.0 / factor, 1.0])
        X_i, X_j, q, valid, K = [], [], [], [], []
        for d in self.directions:
            pad = n - d.q.numel()
            X_i.append(_padded(d.X_i * shrink.to(d.X_i) if d.rescales_i else d.X_i, pad))
            X_j.append(_padded(d.X_j * shrink.to(d.X_j) if d.rescales_j else d.X_j, pad))
            q.append(_padded(d.q, pad))
            valid.append(torch.arange(n) < d.q.numel())
            K_i = d.K_i.clone()
            if d.rescales_i:  # as geometry.camera.rescale_focal
                K_i[0, 0] *= factor
                K_i[1, 1] *= factor
            K.append(K_i)
        X_i_t = torch.stack(X_i)
        return make_factors(
            torch.tensor([d.i for d in self.directions]),
            torch.tensor([d.j for d in self.directions]),
            X_i_t,
            torch.stack(X_j),
            torch.stack(q),
            torch.stack(valid),
            self.tracking,
            torch.stack(K).to(X_i_t),
        )


def _direction(
    i: int,
    j: int,
    X_i: Tensor,
    X_j: Tensor,
    K_i: Tensor,
    matches: DirectedMatches,
    max_matches: int,
    rescales_i: bool,
    rescales_j: bool,
) -> _Direction:
    """The edge (i, j) of a pair, its valid matches evenly subsampled to ``max_matches``."""
    X_i_matched, X_j_matched, q = matched_points(matches, X_i, X_j, max_matches)
    return _Direction(
        i,
        j,
        X_i_matched,
        X_j_matched,
        q,
        K_i,
        rescales_i,
        rescales_j,
    )


def _padded(x: Tensor, pad: int) -> Tensor:
    """``x (n, ...)`` with ``pad`` zero rows appended (invalid matches)."""
    return torch.cat([x, x.new_zeros((pad, *x.shape[1:]))]) if pad else x


def relative_pose(T_WC_anchor: Tensor, T_WC_moving: Tensor) -> Tensor:
    """``(8,)`` pose of the moving keyframe in the anchor keyframe's camera."""
    return sim3_compose(sim3_inverse(T_WC_anchor), T_WC_moving)
