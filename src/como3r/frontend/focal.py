"""Focal lengths from keyframe pairs: the energy of a focal correction and its joint solve.

A self-calibrated agent (:mod:`como3r.frontend.calibration`) locks every keyframe to one
pinhole camera (C-Eq. 16), and a learned prior gets that field of view wrong by several
percent per image (MUSt3R: 4 deg mean field-of-view error). A canonical pointmap on the rays
of a focal length ``f exp(delta)`` instead of ``f`` is ``X' = (x exp(-delta), y exp(-delta),
z)``: the same depths, stretched across the image. Two keyframes that see one surface
stretched differently, or stretched alike but through cameras turned against each other,
disagree in a way no Sim(3) aligns.

So a verified keyframe pair observes the focal length: at a trial ``delta`` the pair's
pointmaps and intrinsics are rescaled and compared on the calibrated factors (C-Eq. 17,
both directions, the first keyframe pinned), and the summed robust energy (C-Eq. 5) plus a
weak prior ``(delta / prior_sigma)^2 / 2`` is minimised over the pairs' relative Sim(3)s
and ``delta`` together: one Gauss-Newton solve with Huber IRLS whose normal equations
(C-Eq. 25) have one more column, ``delta``'s (:mod:`como3r.optim.focal_kernels`). Two uses:

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

import copy
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import GlobalBAConfig, TrackingConfig
from como3r.errors import InputError
from como3r.frontend.graph import make_factors
from como3r.frontend.pairs import DirectedMatches, matched_points
from como3r.geometry.lie import sim3_adjoint, sim3_compose, sim3_identity, sim3_inverse
from como3r.geometry.units import median_point_range
from como3r.optim.factors import endpoint_blocks
from como3r.optim.focal_kernels import focal_blocks
from como3r.optim.linear import dense_attempts
from como3r.optim.match_factors import CalibratedFactors
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.values import PoseValues

#: Iterations of the joint solve at most (it took 3-13 on the merges of a 16-agent replay).
JOINT_MAX_ITERS = 40


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
        evaluations: Gauss-Newton iterations run (each linearizes every pair once): the
            relative solve at ``delta = 0``'s, then the joint solve's.
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

    The relative Sim(3)s are first solved at ``delta = 0`` (the energy without a
    correction), then, from there, jointly with ``delta`` (:meth:`_PairProblem.solve_joint`);
    the correction is kept only if it lowers the energy. Issue 41: this replaced Brent's
    bounded search over ``delta`` (scipy), whose every trial ran a relative solve of its
    own, 8-11 per merge, most stopping at ``max_iters`` (Huber IRLS converges linearly, its
    steps shrinking about 0.6 per iteration): on the 15 merges of a 16-agent replay the
    joint solve lands within 9e-5 of the minimum of the energy over ``delta`` with every
    relative solve converged, where Brent's search landed up to 5.2e-4 from it, for a
    third of the CPU (59 against 181 ms a merge), and scipy is no longer imported.

    Args:
        pairs: verified keyframe pairs (at least one).
        tracking: noise model and Huber breakpoint of the factors (C-Eq. 7-8, 17).
        search: the correction is held in ``[-search, search]``.
        prior_sigma: RMS of the weak zero-mean prior on the correction (two agents' focal
            estimates, each about 8 % off, differ by about 0.1 in log).
        tolerance: the estimate's absolute tolerance on ``delta``: the joint solve stops
            once its steps, shrinking geometrically, leave ``delta`` within a tenth of it
            of their limit.
        max_matches: matches per direction and pair (evenly subsampled).
        max_iters: Gauss-Newton iterations of the relative solve at ``delta = 0``.

    Returns:
        The correction with the smallest energy.
    """
    problem = _PairProblem(pairs, tracking, max_matches)
    zero, iterations = problem.solve_poses(0.0, max_iters)
    f_zero = problem.energy(zero, 0.0, prior_sigma)
    values, best, joint = problem.solve_joint(zero, search, prior_sigma, tolerance)
    f_best = problem.energy(values.poses, best, prior_sigma)
    if f_zero <= f_best:
        best, f_best = 0.0, f_zero
    return FocalEstimate(best, iterations + joint, f_zero - f_best)


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


class _PairProblem:
    """The pairs' relative solves as one problem in their poses and the correction.

    Every pair is two nodes (its anchor, pinned at the identity, and its moving keyframe)
    of one batch, so one Gauss-Newton loop solves all pairs (their blocks are independent,
    tied only by the shared correction). The calibrated factors (C-Eq. 17) are built once at
    ``delta = 0``; a trial correction multiplies the rescaled sides' ``fx, fy`` by
    ``exp(delta)`` and the x and y of their matched points by ``exp(-delta)``
    (:func:`~como3r.geometry.camera.rescale_focal`: every point keeps its pixel and depth).
    """

    def __init__(
        self, pairs: Sequence[FocalPair], tracking: TrackingConfig, max_matches: int
    ) -> None:
        self.huber_k = tracking.huber_k
        # (3,) whitening of the pixel and log-depth components (C-Eq. 7, 17)
        self.inv_sigmas = (
            1 / tracking.sigma_pixel,
            1 / tracking.sigma_pixel,
            1 / tracking.sigma_depth,
        )
        directions: list[_Direction] = []
        for k, pair in enumerate(pairs):
            anchor, moving = 2 * k, 2 * k + 1
            directions += [
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
        self.start = PoseValues(
            torch.stack(
                [T for pair in pairs for T in (identity, pair.T_anchor_moving.double().cpu())]
            ),
            torch.arange(2 * len(pairs)) % 2 == 0,
        )
        # the solves' step tolerance in the pairs' own length (geometry.units)
        self.length = float(median_point_range(torch.cat([d.X_i for d in directions])))
        self.factors = _factors(directions, tracking)
        # (E,) 1 where an edge's camera i (its K) or camera j (its points) takes the correction
        self.rescales_i = torch.tensor([d.rescales_i for d in directions], dtype=torch.float64)
        self.rescales_j = torch.tensor([d.rescales_j for d in directions], dtype=torch.float64)

    def at(self, log_focal: float) -> CalibratedFactors:
        """The factors at a trial correction (a shallow copy: the other per-match arrays
        are shared)."""
        factors = copy.copy(self.factors)
        X_j, K = self.factors.X_j, self.factors.K.clone()
        shrink = torch.exp(-log_focal * self.rescales_j).to(X_j)[:, None, None]
        factors.X_j = torch.cat([X_j[..., :2] * shrink, X_j[..., 2:]], dim=-1)
        grow = torch.exp(log_focal * self.rescales_i).to(K)
        K[:, 0, 0] *= grow
        K[:, 1, 1] *= grow
        factors.K = K
        return factors

    def energy(self, poses: Tensor, log_focal: float, prior_sigma: float) -> float:
        """Robust energy of every pair (C-Eq. 5) plus the prior, at ``poses (N, 8)``."""
        data = float(self.at(log_focal).cost(poses))
        return 0.5 * (log_focal / prior_sigma) ** 2 + data

    def solve_poses(self, log_focal: float, max_iters: int) -> tuple[Tensor, int]:
        """The relative Sim(3)s at a fixed correction (Gauss-Newton with Huber IRLS, from
        the pairs' own poses); returns them ``(N, 8)`` and the iterations run."""
        solved, report = gauss_newton_irls(
            self.at(log_focal),
            self.start,
            GlobalBAConfig(),
            max_iters=max_iters,
            length_scale=self.length,
        )
        return solved.poses, report.iterations

    def solve_joint(
        self, poses: Tensor, search: float, prior_sigma: float, tolerance: float
    ) -> tuple[PoseValues, float, int]:
        """Poses and correction together: Gauss-Newton with Huber IRLS on C-Eq. 25's normal
        equations with one more column, the correction's (:meth:`linearize`), its steps held
        in ``[-search, search]``.

        Stops once the correction's steps, shrinking geometrically, leave it less than
        ``tolerance / 10`` from their limit and the poses move by less than
        ``GlobalBAConfig.step_tol`` (translations in the pairs' length), or after
        :data:`JOINT_MAX_ITERS`. Returns the poses, the correction and the iterations run.
        """
        config = GlobalBAConfig()
        values, log_focal = PoseValues(poses, self.start.pinned), 0.0
        free = torch.cat([values.free.repeat_interleave(7), torch.ones(1, dtype=torch.bool)])
        iterations, previous = 0, 0.0
        while iterations < JOINT_MAX_ITERS:
            iterations += 1
            H, g = self.linearize(values.poses, log_focal)
            H[-1, -1] += 1.0 / prior_sigma**2
            g[-1] += log_focal / prior_sigma**2
            attempts = dense_attempts(
                H[free][:, free], g[free], 0.0, config.tikhonov_base, config.tikhonov_retries
            )
            step = next((s for s in attempts if s is not None), None)
            if step is None:
                break
            tau = torch.zeros(values.num_poses * 7, dtype=torch.float64)
            tau[free[:-1]] = step[:-1]
            tau = tau.reshape(-1, 7)
            moved = min(max(log_focal + float(step[-1]), -search), search)
            change, log_focal = abs(moved - log_focal), moved
            values = values.retract(tau)
            size = float(torch.cat([tau[:, :3] / self.length, tau[:, 3:]], dim=-1).norm())
            # IRLS converges linearly: with steps shrinking by ``ratio``, the correction is
            # still ``change * ratio / (1 - ratio)`` from its limit (a first step: as if 0.5)
            ratio, previous = change / previous if previous > 0 else 0.5, change
            if change * ratio < 0.1 * tolerance * (1 - ratio) and size < config.step_tol:
                break
        return values, log_focal, iterations

    def linearize(self, poses: Tensor, log_focal: float) -> tuple[Tensor, Tensor]:
        """Dense normal equations ``H (7N + 1, 7N + 1)``, ``g (7N + 1,)`` float64 of the
        pairs' energy in the poses' left tangents and the correction (its row last), with
        Huber-IRLS weights at ``poses (N, 8)`` (C-Eq. 7-8, 25).

        Every edge's blocks in the tangent of ``T_ij = T_WC_i^-1 T_WC_j`` (C-Eq. 13) come
        from one pass of the global BA's compiled loop (:func:`~como3r.optim.focal_kernels.
        focal_blocks`): the pose rows, and camera i's and camera j's log focal columns at
        the trial correction of each side that takes it. ``delta`` moves both sides that
        do, so its column is their sum weighted by :attr:`rescales_i` and
        :attr:`rescales_j`. The pose rows and that column are projected onto the endpoints
        by C-Eq. 11 (``J_i = -J Ad``, ``J_j = J Ad``, ``Ad = Ad(T_WC_i^-1)``).
        """
        factors = self.factors
        T_WC_i = poses[factors.i]
        T_ij = sim3_compose(sim3_inverse(T_WC_i), poses[factors.j])
        H_edge, g_edge = focal_blocks(
            T_ij,
            factors.K,
            torch.exp(log_focal * self.rescales_i),
            torch.exp(-log_focal * self.rescales_j),
            factors.X_j,
            factors.p_i,
            factors.z_i,
            factors.q,
            factors.valid,
            self.inv_sigmas,
            self.huber_k,
        )
        sides = torch.stack([self.rescales_i, self.rescales_j], dim=1)  # (e, 2)
        H_pf = (H_edge[:, :7, 7:] * sides[:, None, :]).sum(-1)
        H_ff = torch.einsum("ea,eab,eb->e", sides, H_edge[:, 7:, 7:], sides)
        g_f = (g_edge[:, 7:] * sides).sum(-1)
        blocks = endpoint_blocks(factors.i, factors.j, H_edge[:, :7, :7], g_edge[:, :7], T_WC_i)
        coupling = (sim3_adjoint(sim3_inverse(T_WC_i)).transpose(1, 2) @ H_pf[..., None])[..., 0]
        n = 7 * poses.shape[0]
        H = torch.zeros(n + 1, n + 1, dtype=torch.float64)
        g = torch.zeros(n + 1, dtype=torch.float64)
        for e, (i, j) in enumerate(zip(factors.i.tolist(), factors.j.tolist())):
            rows_i, rows_j = slice(7 * i, 7 * i + 7), slice(7 * j, 7 * j + 7)
            H[rows_i, rows_i] += blocks.H_ii[e]
            H[rows_j, rows_j] += blocks.H_jj[e]
            H[rows_i, rows_j] += blocks.H_ij[e]
            H[rows_j, rows_i] += blocks.H_ij[e].T
            H[rows_i, n] -= coupling[e]
            H[rows_j, n] += coupling[e]
            g[rows_i] += blocks.g_i[e]
            g[rows_j] += blocks.g_j[e]
        H[n, :n] = H[:n, n]
        H[n, n] = H_ff.sum()
        g[n] = g_f.sum()
        return H, g


def _factors(directions: Sequence[_Direction], tracking: TrackingConfig) -> CalibratedFactors:
    """The calibrated factors of every direction at the keyframes' own focal lengths
    (C-Eq. 16-17), matches padded to the largest direction's."""
    n = max(d.q.numel() for d in directions)
    X_i_t = torch.stack([_padded(d.X_i, n - d.q.numel()) for d in directions])
    factors = make_factors(
        torch.tensor([d.i for d in directions]),
        torch.tensor([d.j for d in directions]),
        X_i_t,
        torch.stack([_padded(d.X_j, n - d.q.numel()) for d in directions]),
        torch.stack([_padded(d.q, n - d.q.numel()) for d in directions]),
        torch.stack([torch.arange(n) < d.q.numel() for d in directions]),
        tracking,
        torch.stack([d.K_i for d in directions]).to(X_i_t),
    )
    if not isinstance(factors, CalibratedFactors):  # make_factors with intrinsics
        raise InputError("estimate_log_focal: the pairs did not give C-Eq. 17 factors")
    return factors


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
    """The edge (i, j) of a pair, its valid matches evenly subsampled to ``max_matches``, on
    the CPU (the correction's column is summed by a compiled CPU loop) in float64: the
    energy is then smooth in the correction (float32 points, rescaled at every trial, round
    differently each time, steps of about 1e-8 of the energy)."""
    X_i_matched, X_j_matched, q = matched_points(matches, X_i, X_j, max_matches)
    return _Direction(
        i,
        j,
        X_i_matched.cpu().double(),
        X_j_matched.cpu().double(),
        q.cpu().double(),
        K_i.cpu().double(),
        rescales_i,
        rescales_j,
    )


def _padded(x: Tensor, pad: int) -> Tensor:
    """``x (n, ...)`` with ``pad`` zero rows appended (invalid matches)."""
    return torch.cat([x, x.new_zeros((pad, *x.shape[1:]))]) if pad else x


def relative_pose(T_WC_anchor: Tensor, T_WC_moving: Tensor) -> Tensor:
    """``(8,)`` pose of the moving keyframe in the anchor keyframe's camera."""
    return sim3_compose(sim3_inverse(T_WC_anchor), T_WC_moving)
