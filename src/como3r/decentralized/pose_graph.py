"""Scale-aware multi-robot pose graphs in GTSAM (F-Sec. III-C, F-Eq. 3-8).

Variables are the keyframe poses ``T_alpha,i`` (``gtsam.Pose3``, camera-to-world) and, for
the scale-aware formulations, loop scales ``s`` (doubles). Factors:

* odometry (F-Eq. 4): ``BetweenFactorPose3`` of consecutive keyframes of a robot;
* the gauge: a tight ``PriorFactorPose3`` on the anchor robot's first keyframe;
* loops, by formulation (:data:`~como3r.config_decentralized.FORMULATIONS`):

  - ``base``: ``BetweenFactorPose3`` with the prior's translation scaled once, by odometry
    (F-Eq. 6) or not at all (``scale_init``);
  - ``independent``: :func:`scaled_loop_factor`, the measurement
    ``T_hat(s) = [R_bar, s t_bar]`` of F-Eq. 7 with its own scale variable ``s`` per loop
    (F-Eq. 8); a weak prior keeps ``s`` near its initial value so that a single loop
    between two robots stays well posed;
  - ``smoothed``: the same plus ``BetweenFactorDouble(s_l, s_m, 0)`` (error ``s_m - s_l``,
    Jacobians -1 and 1, F-Sec. III-C-c) along each cluster of loops whose endpoints are
    fewer than ``cluster_window`` keyframes apart on both robots;
  - ``shared``: one scale variable for all loops.

  Every loop's information is multiplied by its confidence ``p`` (F-Eq. 3), except that its
  translation sigma never falls below ``loop_sigma_trans_floor_ratio`` keyframe spacings
  (which a decentralized run sets to the rotation noise at the scene depth,
  :meth:`~como3r.config_decentralized.DecentralizedConfig.pose_graph_config`). ``p`` is a
  correspondence ratio (F-Eq. 1-2): it tells true loops from failed registrations, not how
  precise a true loop's translation is. The prior registers two pointmaps of the scene, so a
  rotation error ``d_theta`` of the fit turns about the scene (depth ``D``, about 14
  spacings at the default keyframe distance) and moves the camera by ``D d_theta`` whatever
  the baseline: 2 deg is 0.5 spacings there. The closest pairs overlap most and get the
  highest ``p`` (0.73-0.84), hence the stiffest translations, while at a baseline of one
  spacing or less that error turns their direction by 54-127 deg (issue 37's 3-robot scene,
  prior ``v2``; median 9 deg over all accepted loops). With ``loop_scene_depth_ratio > 0``
  a loop's noise is instead a full covariance in which the rotation error turns the camera
  about the scene (:func:`~.factor_noise.loop_covariance`, GTSAM's
  ``Gaussian.Covariance``), off by default: the prior's loops' translation errors do not
  follow their rotation errors.

Odometry (F-Eq. 4) is metric in the paper (F-Sec. III), but a monocular VIO is off in scale
until its estimate converges, at the start of a trajectory (F-Sec. IV-C). With a robot's
start scale uncertainty (``PoseGraphProblem.starts``, which a decentralized run sets for a
robot whose input declares a ``vio`` odometry, :mod:`.odometry_kind`; an undeclared robot's
is ``odom_start_scale_sigma``) a step's noise gains, along the step, that fraction of its
length, decaying with the distance travelled (:func:`~.factor_noise.odometry_noise`), so the
loops to other robots may stretch or shorten a robot's unconverged start; pairwise
consistency counts the same variance (:func:`~.factor_noise.start_variance`).

With ``odom_scale_walk > 0`` each
step ``k`` of a robot's odometry is instead the measurement ``[R_k, lambda_k t_k]`` of
:func:`scaled_loop_factor` with a scale ``lambda_k`` per step: consecutive scales are tied by
a random walk (``odom_scale_walk`` per square root of the keyframe spacings travelled) and
each is held near 1 by ``odom_scale_prior`` (:func:`_add_odometry_scales`). This rescales
dead-reckoning odometry by factors refined by sporadic measurements, as F-[25] does for
pedestrian IMU odometry with UWB ranges (F-Sec. III-C-b), here refined by the loops: a
monocular VIO's scale is off until its estimate converges (F-Sec. IV-C), and the loops to
other robots see it. Off by default: with the prior's loops it helped the scenes it was
tried on and hurt held-out ones (measured in
:class:`~como3r.config_decentralized.PoseGraphConfig`).

Solvers: Levenberg-Marquardt, and graduated non-convexity (Yang et al. 2020, F-[6]) as an
outer loop over LM that re-weights loop factors only: odometry, the gauge prior and scale
factors are known inliers. GTSAM's ``GncLMOptimizer`` clones factors, which a Python
``CustomFactor`` cannot survive, so the weights are applied by rebuilding the loop factors
with scaled noise models.

Jacobians of :func:`scaled_loop_error` (GTSAM's right perturbation ``T <- T Exp(xi)``,
tangent ``(omega, v)``) with ``E = T_hat(s)^-1 T_a^-1 T_b`` and ``e = Log(E)``:

    H_a = -J_r^-1(e) Ad(T_b^-1 T_a),  H_b = J_r^-1(e),  H_s = -J_r^-1(e) Ad(E^-1) [0; R_bar^T t_bar].

At ``e = 0`` they reduce to the paper's ``-Ad(inv(T_a^-1 T_b))``, ``I`` and ``[0, -t_bar]``
(with ``t_bar`` expressed in the loop's second camera).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from como3r.config_decentralized import FORMULATIONS, SOLVERS, PoseGraphConfig
from como3r.decentralized.factor_noise import (
    loop_covariance,
    loop_sigmas,
    odometry_noise,
    pose_noise,
    robot_start,
    step_lengths,
)
from como3r.decentralized.initial_estimate import initial_poses, initial_scales, keyframe_spacing
from como3r.decentralized.pose_graph_problem import (
    PoseGraphProblem,
    PoseGraphSolution,
    from_pose3,
    loop_clusters,
    loop_measurement,
    odometry_scale_key,
    pose_key,
    scale_key,
    to_pose3,
)
from como3r.errors import ConfigError, SolverError

#: Standard deviation of the gauge prior on the anchor's first keyframe (rad, and keyframe
#: spacings for its translation).
ANCHOR_SIGMA = 1e-6
#: Smallest GNC weight kept: keeps a robot whose loops are all rejected weakly attached.
MIN_WEIGHT = 1e-6
#: GNC stops once every weight is this close to 0 or 1 (TLS).
WEIGHT_TOLERANCE = 1e-4
_POSE_DIM = 6


# --------------------------------------------------------------------------- factors


def scaled_loop_error(
    R_bar: np.ndarray, t_bar: np.ndarray, T_a: gtsam.Pose3, T_b: gtsam.Pose3, s: float
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Error of F-Eq. 8 and its exact Jacobians (module docstring).

    Args:
        R_bar: ``(3, 3)`` measured relative rotation (camera b in camera a).
        t_bar: ``(3,)`` measured relative translation, prior units.
        T_a, T_b: current poses of the two keyframes.
        s: current loop scale.

    Returns:
        ``e (6,)`` in GTSAM's ``(omega, v)`` order and ``[H_a (6, 6), H_b (6, 6), H_s (6, 1)]``.
    """
    measured = gtsam.Pose3(gtsam.Rot3(R_bar), s * t_bar)
    relative = T_a.between(T_b)
    E = measured.between(relative)
    J_log = np.zeros((_POSE_DIM, _POSE_DIM), order="F")
    e = gtsam.Pose3.Logmap(E, J_log)
    H_a = -J_log @ relative.inverse().AdjointMap()
    xi_s = np.concatenate([np.zeros(3), R_bar.T @ t_bar])
    H_s = -(J_log @ E.inverse().AdjointMap() @ xi_s)[:, None]
    return e, [H_a, J_log.copy(), H_s]


def scaled_loop_factor(
    keys: tuple[int, int, int], R_bar: np.ndarray, t_bar: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """``CustomFactor`` on ``(T_a, T_b, s)`` with the error of :func:`scaled_loop_error`."""
    key_a, key_b, key_s = keys

    def error(
        factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[np.ndarray] | None
    ) -> np.ndarray:
        e, H = scaled_loop_error(
            R_bar, t_bar, values.atPose3(key_a), values.atPose3(key_b), values.atDouble(key_s)
        )
        if jacobians is not None:
            jacobians[0], jacobians[1], jacobians[2] = H
        return e

    return gtsam.CustomFactor(noise, [key_a, key_b, key_s], error)


def _add_odometry_scales(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    robot: int,
    odometry: np.ndarray,
    noise: gtsam.noiseModel.Base,
    spacing: float,
    config: PoseGraphConfig,
) -> None:
    """Odometry factors of one robot with a scale ``lambda_k`` per step (module docstring).

    Step ``k`` (keyframe ``k-1`` to ``k``) is the measurement ``[R_k, lambda_k t_k]`` of
    :func:`scaled_loop_factor`; consecutive scales are tied by a random walk of
    ``odom_scale_walk`` per square root of the keyframe spacings travelled, and each is held
    near 1 by a prior of ``odom_scale_prior``.

    Args:
        graph, values: the graph and initial values, extended in place.
        robot: the robot's id.
        odometry: ``(K, 8)`` its keyframe odometry ``T_OC``.
        noise: the odometry factor's noise (F-Eq. 4's ``Omega_odom``).
        spacing: the problem's keyframe spacing (odometry units).
        config: ``odom_scale_walk`` and ``odom_scale_prior``.
    """
    prior = gtsam.noiseModel.Isotropic.Sigma(1, config.odom_scale_prior)
    previous_key = None
    for k in range(1, len(odometry)):
        step = to_pose3(odometry[k - 1]).between(to_pose3(odometry[k]))
        key = odometry_scale_key(robot, k)
        values.insert(key, 1.0)
        graph.add(gtsam.PriorFactorDouble(key, 1.0, prior))
        graph.add(
            scaled_loop_factor(
                (pose_key(robot, k - 1), pose_key(robot, k), key),
                step.rotation().matrix(),
                np.asarray(step.translation(), dtype=np.float64),
                noise,
            )
        )
        if previous_key is not None:
            travelled = max(float(np.linalg.norm(step.translation())) / spacing, 1e-3)
            walk = gtsam.noiseModel.Isotropic.Sigma(
                1, config.odom_scale_walk * math.sqrt(travelled)
            )
            graph.add(gtsam.BetweenFactorDouble(previous_key, key, 0.0, walk))
        previous_key = key


# --------------------------------------------------------------------------- graph


@dataclass
class _Graph:
    """A formulation's factors: fixed ones and a builder for weighted loop factors."""

    fixed: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    loop_factor: Callable[[int, float], gtsam.NonlinearFactor]
    loop_scale: Callable[[gtsam.Values, int], float]
    count: int

    def with_weights(self, weights: np.ndarray) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph(self.fixed)
        for index, weight in enumerate(weights):
            graph.add(self.loop_factor(index, float(weight)))
        return graph

    def residuals(self, values: gtsam.Values) -> np.ndarray:
        """Whitened squared residual of every loop factor at weight 1."""
        return np.array([2.0 * self.loop_factor(i, 1.0).error(values) for i in range(self.count)])


def build_graph(problem: PoseGraphProblem, formulation: str, config: PoseGraphConfig) -> _Graph:
    """The factors and initial values of ``formulation`` (module docstring)."""
    if formulation not in FORMULATIONS:
        raise ConfigError(
            f"decentralized.pose_graph.formulation: {formulation!r} is not one of {FORMULATIONS}"
        )
    scales = initial_scales(problem.loops, config.scale_init)
    # Translation noise and the consensus bound follow the scene's scale (keyframe spacing).
    spacing = keyframe_spacing(problem, scales)
    poses = initial_poses(problem, scales, spacing)
    fixed = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    odom_rot = math.radians(config.odom_sigma_rot_deg)
    for robot, odometry in sorted(problem.odometry.items()):
        for k, pose in enumerate(poses[robot]):
            values.insert(pose_key(robot, k), pose)
        noise = pose_noise(odom_rot, config.odom_sigma_trans_ratio * spacing, 1.0)
        if config.odom_scale_walk > 0:
            _add_odometry_scales(fixed, values, robot, odometry, noise, spacing, config)
            continue
        _, middles = step_lengths(odometry, spacing)
        start = robot_start(problem, robot, config)
        for k in range(1, len(odometry)):
            step = to_pose3(odometry[k - 1]).between(to_pose3(odometry[k]))
            fixed.add(
                gtsam.BetweenFactorPose3(
                    pose_key(robot, k - 1),
                    pose_key(robot, k),
                    step,
                    odometry_noise(step, float(middles[k - 1]), spacing, config, start),
                )
            )
    fixed.add(
        gtsam.PriorFactorPose3(
            pose_key(problem.anchor, 0),
            to_pose3(problem.anchor_pose),
            pose_noise(ANCHOR_SIGMA, ANCHOR_SIGMA * spacing, 1.0),
        )
    )

    loops = problem.loops
    keys = [(pose_key(l.robot_a, l.keyframe_a), pose_key(l.robot_b, l.keyframe_b)) for l in loops]

    def noise(index: int, weight: float) -> gtsam.noiseModel.Base:
        loop, weight = loops[index], max(weight, MIN_WEIGHT)
        if config.loop_scene_depth_ratio > 0:
            return gtsam.noiseModel.Gaussian.Covariance(
                loop_covariance(
                    loop.T_ab, float(scales[index]), loop.probability, spacing, config, weight
                )
            )
        return pose_noise(*loop_sigmas(loop.probability, spacing, config, weight), 1.0)

    if formulation == "base":

        def base_factor(index: int, weight: float) -> gtsam.NonlinearFactor:
            return gtsam.BetweenFactorPose3(
                *keys[index], loop_measurement(loops[index], scales[index]), noise(index, weight)
            )

        return _Graph(fixed, values, base_factor, lambda v, i: float(scales[i]), len(loops))

    variable = [0] * len(loops) if formulation == "shared" else list(range(len(loops)))
    for v in sorted(set(variable)):
        members = [i for i in range(len(loops)) if variable[i] == v]
        start = float(np.median(scales[members]))
        values.insert(scale_key(v), start)
        fixed.add(
            gtsam.PriorFactorDouble(
                scale_key(v),
                start,
                gtsam.noiseModel.Isotropic.Sigma(1, config.scale_prior_sigma * abs(start)),
            )
        )
    if formulation == "smoothed":
        smoothing = gtsam.noiseModel.Isotropic.Sigma(1, config.scale_smoothing_sigma)
        for cluster in loop_clusters(loops, config.cluster_window):
            for first, second in zip(cluster, cluster[1:]):
                fixed.add(
                    gtsam.BetweenFactorDouble(scale_key(first), scale_key(second), 0.0, smoothing)
                )
    rotations = [to_pose3(l.T_ab).rotation().matrix() for l in loops]
    translations = [np.asarray(l.T_ab[:3], dtype=np.float64) for l in loops]

    def scaled_factor(index: int, weight: float) -> gtsam.NonlinearFactor:
        return scaled_loop_factor(
            (*keys[index], scale_key(variable[index])),
            rotations[index],
            translations[index],
            noise(index, weight),
        )

    return _Graph(
        fixed, values, scaled_factor, lambda v, i: v.atDouble(scale_key(variable[i])), len(loops)
    )


# --------------------------------------------------------------------------- solvers


def _levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int
) -> tuple[gtsam.Values, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = optimizer.optimize()
    except RuntimeError as exc:
        raise SolverError(f"pose graph optimisation failed: {exc}") from None
    return result, int(optimizer.iterations())


def _gnc_weights(residuals: np.ndarray, mu: float, threshold: float, loss: str) -> np.ndarray:
    """Closed-form GNC weights (Yang et al. 2020) of whitened squared residuals."""
    if loss == "gm":
        return (mu * threshold / (residuals + mu * threshold)) ** 2
    upper = (mu + 1.0) / mu * threshold
    lower = mu / (mu + 1.0) * threshold
    middle = np.sqrt(threshold * mu * (mu + 1.0) / np.maximum(residuals, 1e-300)) - mu
    return np.where(residuals >= upper, 0.0, np.where(residuals <= lower, 1.0, middle))


def _graduated_non_convexity(
    graph: _Graph, config: PoseGraphConfig
) -> tuple[gtsam.Values, np.ndarray, int]:
    """GNC over LM with the loop factors as the only uncertain measurements."""
    weights = np.ones(graph.count)
    values, iterations = _levenberg_marquardt(
        graph.with_weights(weights), graph.initial, config.lm_max_iterations
    )
    if graph.count == 0:
        return values, weights, iterations
    threshold = float(chi2.ppf(config.gnc_inlier_probability, _POSE_DIM))
    residuals = graph.residuals(values)
    largest = float(residuals.max())
    if largest <= threshold:
        return values, weights, iterations
    if config.gnc_loss == "gm":
        mu = 2.0 * largest / threshold
    else:
        mu = threshold / max(2.0 * largest - threshold, 1e-12)
    for _ in range(config.gnc_max_iterations):
        weights = _gnc_weights(residuals, mu, threshold, config.gnc_loss)
        values, used = _levenberg_marquardt(
            graph.with_weights(weights), values, config.lm_max_iterations
        )
        iterations += used
        residuals = graph.residuals(values)
        if config.gnc_loss == "gm":
            if mu <= 1.0:
                break
            mu = max(1.0, mu / config.gnc_mu_step)
        else:
            if np.all(np.minimum(weights, 1.0 - weights) < WEIGHT_TOLERANCE):
                break
            mu *= config.gnc_mu_step
    return values, weights, iterations


def solve_pose_graph(
    problem: PoseGraphProblem, formulation: str, solver: str, config: PoseGraphConfig
) -> PoseGraphSolution:
    """Solve one connected multi-robot pose graph.

    Args:
        problem: odometry, loops, anchor and initial estimates.
        formulation: one of :data:`~como3r.config_decentralized.FORMULATIONS`.
        solver: ``lm`` or ``gnc``.
        config: noise models and solver parameters.

    Raises:
        ConfigError: unknown formulation or solver.
        SolverError: GTSAM failed (e.g. an indeterminate linear system).
    """
    if solver not in SOLVERS:
        raise ConfigError(f"decentralized.pose_graph.solver: {solver!r} is not one of {SOLVERS}")
    graph = build_graph(problem, formulation, config)
    start = time.perf_counter()
    if solver == "lm":
        weights = np.ones(graph.count)
        values, iterations = _levenberg_marquardt(
            graph.with_weights(weights), graph.initial, config.lm_max_iterations
        )
    else:
        values, weights, iterations = _graduated_non_convexity(graph, config)
    seconds = time.perf_counter() - start
    poses = {
        robot: np.stack(
            [from_pose3(values.atPose3(pose_key(robot, k))) for k in range(len(odometry))]
        )
        for robot, odometry in problem.odometry.items()
    }
    return PoseGraphSolution(
        poses=poses,
        loop_scales=np.array([graph.loop_scale(values, i) for i in range(graph.count)]),
        loop_weights=weights,
        loop_residuals=graph.residuals(values),
        seconds=seconds,
        iterations=iterations,
        cost=float(graph.with_weights(weights).error(values)),
    )
