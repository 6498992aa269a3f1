"""The two non-linear least-squares loops of como3r (C-Sec. B.2).

Both iterate: linearize every factor at the current poses (Huber-IRLS weights recomputed
from the current residuals), assemble the block normal equations, solve C-Eq. 25, retract.

* :func:`gauss_newton_irls` — the per-agent local solve and the global bundle adjustment:
  ``lambda = 0`` (pinned at all call sites in the paper), Tikhonov escalation only, no cost
  evaluation, stop when ``||tau||_2 < step_tol``. A divergence guard refuses a non-finite
  or implausible step, keeps the previous poses and reports ``diverged=True``.
* :func:`levenberg_marquardt_irls` — the per-frame tracker: evaluates the robust cost,
  accepts a step only if it lowers it, adapts lambda by x10 / /10, and stops on a small
  relative cost decrease or step, or with failure once lambda exceeds ``lambda_max``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import torch

from como3r.config import GlobalBAConfig, LocalSolveConfig, TrackingConfig
from como3r.errors import InputError
from como3r.optim.factors import Factor
from como3r.optim.linear import Backend, SolveStatus, solve
from como3r.optim.system import BlockSystem, assemble
from como3r.optim.values import PoseValues

_T = TypeVar("_T")

logger = logging.getLogger(__name__)

# Limits of a plausible Gauss-Newton step on one pose. A step beyond them is not a
# linearisation step but the product of a blown-up system: more than half a turn, a
# tenfold scale change, or a move of more than 100 diameters of the pose graph.
MAX_ROTATION_STEP = math.pi
MAX_LOG_SCALE_STEP = math.log(10.0)
MAX_TRANSLATION_STEP_EXTENTS = 100.0

# Default number of Tikhonov attempts of the tracker (C-Sec. B.2: R = 6 for every solve).
TRACKER_TIKHONOV_RETRIES = 6


@dataclass
class SolveReport:
    """What one non-linear solve did.

    Attributes:
        iterations: outer iterations run (linearizations plus, for LM, rejected retries).
        converged: a convergence criterion was met.
        reason: why the loop stopped: ``"step_tol"``, ``"rel_cost_tol"``, ``"max_iters"``,
            ``"lambda_max"``, ``"solve_failed"``, ``"diverged"``, ``"non_finite_cost"`` or
            ``"no_free_poses"``.
        cost_history: robust cost of every accepted iterate, starting with the initial
            one (LM only; empty for Gauss-Newton, which never evaluates the cost).
        tikhonov_retries: total number of Tikhonov escalations over all linear solves.
        failed_solves: linear solves in which every Tikhonov attempt failed.
        seconds: wall-clock time of the solve.
        diverged: the divergence guard refused a step (Gauss-Newton only).
        final_lambda: LM damping at exit (LM only).
    """

    iterations: int = 0
    converged: bool = False
    reason: str = "max_iters"
    cost_history: list[float] = field(default_factory=list)
    tikhonov_retries: int = 0
    failed_solves: int = 0
    seconds: float = 0.0
    diverged: bool = False
    final_lambda: float | None = None

    @property
    def initial_cost(self) -> float | None:
        """Cost of the initial poses, where it was computed."""
        return self.cost_history[0] if self.cost_history else None

    @property
    def final_cost(self) -> float | None:
        """Cost of the returned poses, where it was computed."""
        return self.cost_history[-1] if self.cost_history else None


def gauss_newton_irls(
    factors: Factor | Sequence[Factor],
    values: PoseValues,
    config: LocalSolveConfig | GlobalBAConfig | None = None,
    *,
    max_iters: int | None = None,
    step_tol: float | None = None,
    tikhonov_base: float | None = None,
    retries: int | None = None,
    lm_lambda: float | None = None,
    backend: Backend = "auto",
    length_scale: float = 1.0,
) -> tuple[PoseValues, SolveReport]:
    """Tikhonov-regularised Gauss-Newton with Huber IRLS (local solve and global BA).

    Args:
        factors: one factor batch or several (e.g. ray-range and calibrated edges).
        values: initial poses; pinned poses stay fixed (the gauge anchor, C-Sec. A.3).
        config: defaults for the keyword arguments: ``LocalSolveConfig`` (the default) or
            ``GlobalBAConfig`` (whose ``max_iters_stream`` is used; pass
            ``max_iters=config.max_iters_cleanup`` for a cleanup pass).
        max_iters, step_tol, tikhonov_base, retries, lm_lambda: override the config.
        backend: linear-solver backend, see :func:`como3r.optim.linear.solve`.
        length_scale: the scene's length (e.g. its median depth) in pose units: the step's
            translation rows are divided by it before ``||tau||_2`` is compared with
            ``step_tol``, so the tolerance means the same at every scene scale (1 keeps the
            paper's absolute norm, right at its 1 m reference depth).

    Returns:
        The refined poses and a :class:`SolveReport`. On divergence the poses are those of
        the last good iterate.
    """
    if not length_scale > 0:
        raise InputError(f"gauss_newton_irls: length_scale must be > 0, got {length_scale}")
    config = LocalSolveConfig() if config is None else config
    default_iters = (
        config.max_iters_stream if isinstance(config, GlobalBAConfig) else config.max_iters
    )
    max_iters = _pick(max_iters, default_iters)
    step_tol = _pick(step_tol, config.step_tol)
    tikhonov_base = _pick(tikhonov_base, config.tikhonov_base)
    retries = _pick(retries, config.tikhonov_retries)
    lm_lambda = _pick(lm_lambda, config.lm_lambda)
    factors = _check_problem(factors, values, max_iters)

    start = time.perf_counter()
    report = SolveReport()
    if values.num_free == 0:
        report.converged, report.reason = True, "no_free_poses"
        return values, _finish(report, start)
    for iteration in range(1, max_iters + 1):
        report.iterations = iteration
        system = _linearize(factors, values)
        solution = solve(
            system,
            values.free,
            lm_lambda=lm_lambda,
            tikhonov_base=tikhonov_base,
            retries=retries,
            backend=backend,
        )
        report.tikhonov_retries += solution.escalations
        if solution.status is SolveStatus.FAILED:
            report.failed_solves += 1
            report.reason = "solve_failed"
            break
        tau = solution.step
        candidate = values.retract(tau)
        problem = _implausible_step(tau, values, candidate)
        if problem:
            logger.warning(
                "Gauss-Newton step %d refused (%s); keeping the previous poses", iteration, problem
            )
            report.diverged, report.reason = True, "diverged"
            break
        values = candidate
        step_norm = _relative_step_norm(tau, length_scale)
        logger.debug("GN iteration %d: |tau| = %.3e", iteration, step_norm)
        if step_norm < step_tol:
            report.converged, report.reason = True, "step_tol"
            break
    return values, _finish(report, start)


def _relative_step_norm(tau: torch.Tensor, length_scale: float) -> float:
    """``||tau||_2`` of a ``(N, 7)`` step with its translations ``tau[:, :3]`` in units of
    ``length_scale`` (rotation and log-scale rows are unitless already)."""
    if length_scale == 1.0:
        return float(torch.linalg.vector_norm(tau))
    return float(
        torch.linalg.vector_norm(torch.cat([tau[..., :3] / length_scale, tau[..., 3:]], dim=-1))
    )


def levenberg_marquardt_irls(
    factors: Factor | Sequence[Factor],
    values: PoseValues,
    config: TrackingConfig | None = None,
    *,
    max_iters: int | None = None,
    rel_cost_tol: float | None = None,
    step_tol: float | None = None,
    lambda_init: float | None = None,
    lambda_max: float | None = None,
    tikhonov_floor: float | None = None,
    retries: int = TRACKER_TIKHONOV_RETRIES,
    backend: Backend = "auto",
    length_scale: float = 1.0,
) -> tuple[PoseValues, SolveReport]:
    """Levenberg-Marquardt with Huber IRLS and cost-based acceptance (the tracker, C-Eq. 2).

    Args:
        factors: one factor batch or several.
        values: initial poses; for tracking ``[identity (pinned), T_kf initial guess]``.
        config: defaults for the keyword arguments (``TrackingConfig()`` if omitted).
        max_iters, rel_cost_tol, step_tol, lambda_init, lambda_max, tikhonov_floor:
            override the config (C-Tab. 3: 50 / 1e-3 / 1e-3 / 1e-6 / 1e3 / 1e-9).
        retries: Tikhonov attempts per linear solve, starting at ``tikhonov_floor``.
        backend: linear-solver backend.
        length_scale: the scene's length in pose units (the tracker: the keyframe's median
            range), as for :func:`gauss_newton_irls`: ``step_tol`` is then a fraction of it.

    Returns:
        The refined poses (the last accepted iterate) and a :class:`SolveReport` whose
        ``cost_history`` holds the robust cost of every accepted iterate.
    """
    if not length_scale > 0:
        raise InputError(f"levenberg_marquardt_irls: length_scale must be > 0, got {length_scale}")
    config = TrackingConfig() if config is None else config
    max_iters = _pick(max_iters, config.max_iters)
    rel_cost_tol = _pick(rel_cost_tol, config.rel_cost_tol)
    step_tol = _pick(step_tol, config.step_tol)
    lam = _pick(lambda_init, config.lambda_init)
    lambda_max = _pick(lambda_max, config.lambda_max)
    tikhonov_floor = _pick(tikhonov_floor, config.tikhonov_floor)
    factors = _check_problem(factors, values, max_iters)

    start = time.perf_counter()
    report = SolveReport()
    cost = _total_cost(factors, values)
    report.cost_history.append(cost)
    if not math.isfinite(cost):
        report.reason = "non_finite_cost"
        return values, _finish(report, start, lam)
    if values.num_free == 0:
        report.converged, report.reason = True, "no_free_poses"
        return values, _finish(report, start, lam)
    system: BlockSystem | None = None
    for iteration in range(1, max_iters + 1):
        report.iterations = iteration
        if system is None:  # a rejected step keeps the linearization and only re-damps
            system = _linearize(factors, values)
        solution = solve(
            system,
            values.free,
            lm_lambda=lam,
            tikhonov_base=tikhonov_floor,
            retries=retries,
            backend=backend,
        )
        report.tikhonov_retries += solution.escalations
        step_norm = _relative_step_norm(solution.step, length_scale)
        accepted, new_cost = False, math.inf
        if solution.status is SolveStatus.FAILED:
            report.failed_solves += 1
        else:
            candidate = values.retract(solution.step)
            new_cost = _total_cost(factors, candidate)
            accepted = new_cost < cost
        logger.debug(
            "LM iteration %d: cost %.6e -> %.6e, |tau| = %.3e, lambda = %.1e",
            iteration,
            cost,
            new_cost,
            step_norm,
            lam,
        )
        if accepted:
            relative_decrease = (cost - new_cost) / cost
            values, cost, system = candidate, new_cost, None
            report.cost_history.append(cost)
            lam /= 10.0
            if relative_decrease < rel_cost_tol:
                report.converged, report.reason = True, "rel_cost_tol"
                break
        if step_norm < step_tol and solution.status is not SolveStatus.FAILED:
            report.converged, report.reason = True, "step_tol"
            break
        if not accepted:
            lam = max(lam * 10.0, tikhonov_floor)  # a zero lambda must still grow
            if lam > lambda_max:
                report.reason = "lambda_max"
                break
    return values, _finish(report, start, lam)


def _pick(value: _T | None, default: _T) -> _T:
    return default if value is None else value


def _check_problem(
    factors: Factor | Sequence[Factor], values: PoseValues, max_iters: int
) -> list[Factor]:
    """Validate the arguments shared by both loops and return the factors as a list."""
    factor_list = list(factors) if isinstance(factors, Sequence) else [factors]
    if not factor_list:
        raise InputError("optimizer: no factors given")
    if max_iters < 1:
        raise InputError(f"optimizer: max_iters must be >= 1, got {max_iters}")
    for factor in factor_list:
        if factor.max_pose_index >= values.num_poses:
            raise InputError(
                f"optimizer: a factor refers to pose {factor.max_pose_index} but the values "
                f"hold {values.num_poses} poses"
            )
    return factor_list


def _linearize(factors: list[Factor], values: PoseValues) -> BlockSystem:
    return assemble(values.num_poses, [f.linearize(values.poses) for f in factors])


def _total_cost(factors: list[Factor], values: PoseValues) -> float:
    return float(sum(f.cost(values.poses) for f in factors))


def _implausible_step(tau: torch.Tensor, before: PoseValues, after: PoseValues) -> str:
    """Why a step ``(N, 7)`` from ``before`` to ``after`` is not a plausible one ('' if it is)."""
    if not bool(tau.isfinite().all()) or not bool(after.poses.isfinite().all()):
        return "non-finite step"
    rotation = float(torch.linalg.vector_norm(tau[:, 3:6], dim=-1).max())
    if rotation > MAX_ROTATION_STEP:
        return f"rotation step of {rotation:.3g} rad"
    log_scale = float(tau[:, 6].abs().max())
    if log_scale > MAX_LOG_SCALE_STEP:
        return f"log-scale step of {log_scale:.3g}"
    translations = before.poses[:, :3].to(torch.float64)
    extent = float(torch.linalg.vector_norm(translations.amax(0) - translations.amin(0)))
    moved = after.poses[:, :3].to(torch.float64) - translations
    displacement = float(torch.linalg.vector_norm(moved, dim=-1).max())
    if extent > 0 and displacement > MAX_TRANSLATION_STEP_EXTENTS * extent:
        return f"translation step of {displacement:.3g} over a graph of extent {extent:.3g}"
    return ""


def _finish(report: SolveReport, start: float, lam: float | None = None) -> SolveReport:
    report.seconds = time.perf_counter() - start
    report.final_lambda = lam
    return report
