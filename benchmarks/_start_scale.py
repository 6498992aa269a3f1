"""A robot's odometry start-scale error, estimated from its own prior chain (issue 37).

A monocular VIO is off in scale until its scale estimate converges, at the start of a
trajectory (F-Sec. IV-C); a LiDAR-inertial odometry is metric from the start. The prior
(MASt3R-like) registers pairs of the robot's own keyframes with metric relative poses, up to
its own scale error. Over a pair of keyframes ``(i, j)`` the ratio of the odometry's distance
to the prior's is, in the model of :mod:`~.odometry_sim`,

    log(|o_j - o_i| / |t_prior(i, j)|) = a + log(1 + e0 g_ij) + n_ij,
    g_ij = mean of exp(-d / L) over the travelled distance d from d_i to d_j,

with ``a`` the prior's log scale against the odometry's converged one, ``e0`` the odometry's
start-scale error, ``L`` its convergence length and ``n_ij`` the prior's error of that
distance. A metric odometry has ``e0 = 0``: the ratio is flat along the path up to the
prior's noise. :func:`estimate_start_error` fits ``(a, e0)`` by weighted least squares under
the prior's noise model :func:`pair_log_sigma` and gives ``e0``'s standard error.

Not used by a run: measured with ``benchmarks/start_scale.py`` (issue 37's 3-robot scenes,
prior ``v2``, seeds 0-2), it does not tell a VIO from a metric odometry. The prior's distance
between keyframes ``n`` spacings apart has a log error of RMS 0.49-0.59 / 0.23-0.52 /
0.27-0.47 at ``n = 1 / 3 / 5`` (its pair scale, range and drift errors; F-Eq. 6's
``|t_prior|`` carries them all), so one robot's ``e0`` is known to 0.2-0.9, no better than
the VIO's 0.25-0.3 start error itself; and on two of three seeds the prior's own distances
are short at the robots' starts, so a metric odometry's ratio is not flat either.
:func:`start_discount` keeps a discount off unless the deviation is significant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The shape of the prior's log error of a keyframe distance, ``sqrt(FLOOR^2 + (SPREAD /
#: n)^2)`` at ``n`` keyframe spacings: the pairs' relative weights (the fit's scatter sets
#: the level). 0.54 / 0.26 / 0.22 at 1 / 3 / 5, near seed 1's RMS (module docstring).
PRIOR_LOG_FLOOR = 0.2
PRIOR_LOG_SPREAD = 0.5


@dataclass(frozen=True)
class StartScale:
    """A robot's estimated odometry start-scale error.

    Attributes:
        error: ``e0``, the fraction by which the odometry's first step is too long (negative:
            too short); 0 without enough pairs.
        sigma: its standard error (``inf`` without enough pairs).
        pairs: how many keyframe pairs it was fitted on.
    """

    error: float
    sigma: float
    pairs: int


def pair_log_sigma(spacings: np.ndarray) -> np.ndarray:
    """``(P,)`` the prior's log error of the distance between keyframes ``spacings`` apart
    (:data:`PRIOR_LOG_FLOOR`, :data:`PRIOR_LOG_SPREAD`)."""
    n = np.maximum(np.asarray(spacings, dtype=np.float64), 1e-6)
    return np.sqrt(PRIOR_LOG_FLOOR**2 + (PRIOR_LOG_SPREAD / n) ** 2)


def start_weights(start: np.ndarray, end: np.ndarray, decay: float) -> np.ndarray:
    """``(P,)`` ``g_ij``: the mean of ``exp(-d / decay)`` over ``[start, end]`` (module
    docstring; ``start``, ``end`` and ``decay`` in the same units, ``end > start``)."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    return decay * (np.exp(-start / decay) - np.exp(-end / decay)) / (end - start)


def estimate_start_error(
    odometry_distance: np.ndarray,
    prior_distance: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    decay: float,
) -> StartScale:
    """Fit a robot's odometry start-scale error to its keyframe pairs (module docstring).

    Args:
        odometry_distance: ``(P,)`` ``|o_j - o_i|`` of each pair, odometry units.
        prior_distance: ``(P,)`` the prior's ``|t(i, j)|`` (its registration of the pair).
        start, end: ``(P,)`` odometry distance travelled from the robot's first keyframe to
            ``i`` and to ``j``, in keyframe spacings.
        decay: the convergence length ``L`` of the start error, in keyframe spacings.

    Returns:
        ``e0`` and its standard error: a Gauss-Newton fit of ``(a, e0)`` with weights
        ``1 / pair_log_sigma(end - start)^2``, ``e0`` kept in ``[-0.9, 0.9]``; the standard
        error scaled by the pairs' weighted scatter about the fit (reduced chi-square), so
        it follows the prior's actual noise.
    """
    od = np.asarray(odometry_distance, dtype=np.float64)
    pd = np.asarray(prior_distance, dtype=np.float64)
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    ok = np.isfinite(od) & np.isfinite(pd) & (od > 0) & (pd > 0) & (end > start)
    if ok.sum() < 3:
        return StartScale(0.0, float("inf"), int(ok.sum()))
    # F-Eq. 6's ratio |t_odom| / |t_prior|, over pairs of several spacings.
    y = np.log(od[ok] / pd[ok])
    g = start_weights(start[ok], end[ok], decay)
    w = 1.0 / pair_log_sigma(end[ok] - start[ok]) ** 2
    e0 = 0.0
    for _ in range(20):
        model = np.log1p(e0 * g)
        J = np.stack([np.ones_like(g), g / (1.0 + e0 * g)], axis=1)
        H = J.T @ (w[:, None] * J)
        if np.linalg.cond(H) > 1e12:
            return StartScale(0.0, float("inf"), int(ok.sum()))
        a = float(np.sum(w * (y - model)) / np.sum(w))
        step = np.linalg.solve(H, J.T @ (w * (y - a - model)))
        e0 = float(np.clip(e0 + step[1], -0.9, 0.9))
        if abs(step[1]) < 1e-6:
            break
    J = np.stack([np.ones_like(g), g / (1.0 + e0 * g)], axis=1)
    residual = y - a - np.log1p(e0 * g)
    # The noise model sets the pairs' relative weights; their scatter about the fit, its
    # level (weighted least squares with the reduced chi-square).
    scatter = float(np.sum(w * residual**2)) / max(len(y) - 2, 1)
    covariance = np.linalg.inv(J.T @ (w[:, None] * J)) * scatter
    return StartScale(e0, float(np.sqrt(covariance[1, 1])), int(ok.sum()))


def start_discount(estimate: StartScale, significance: float = 2.0) -> float:
    """The start discount (``pose_graph.odom_start_scale_sigma`` of one robot,
    :func:`como3r.decentralized.factor_noise.start_scale_sigma`): ``|e0|`` where ``e0`` is more than
    ``significance`` standard errors from 0 (the ratio is not flat), else 0."""
    if not abs(estimate.error) > significance * estimate.sigma:
        return 0.0
    return abs(estimate.error)
