"""Noise models of the decentralized pose graph's factors (F-Eq. 3-4; :mod:`.pose_graph`
builds the factors, :mod:`.consistency` weighs loop cycles with the same noise).

A loop's noise: its sigmas, F-Eq. 3 with a translation floor the confidence does not lower
(:func:`loop_sigmas`), or a full covariance in which its rotation error turns the camera
about the scene (:func:`loop_covariance`). An odometry step's (F-Eq. 4), with the stretch of
a monocular VIO's unconverged start along the step (:func:`odometry_noise`,
:func:`start_variance`). Tangents in GTSAM's ``(omega, v)`` order, right perturbation; lengths
in odometry units unless a name says keyframe spacings.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from como3r.config_decentralized import PoseGraphConfig
from como3r.decentralized.pose_graph_problem import OdometryStart, PoseGraphProblem, to_pose3

_POSE_DIM = 6


def pose_noise(sigma_rot_rad: float, sigma_trans: float, weight: float) -> gtsam.noiseModel.Base:
    """Diagonal noise in GTSAM's (rotation, translation) order, information times ``weight``;
    ``sigma_trans`` in odometry units."""
    sigmas = np.array([sigma_rot_rad] * 3 + [sigma_trans] * 3) / math.sqrt(weight)
    return gtsam.noiseModel.Diagonal.Sigmas(sigmas)


def loop_sigmas(
    probability: float, spacing: float, config: PoseGraphConfig, weight: float = 1.0
) -> tuple[float, float]:
    """A loop's noise: ``(rotation sigma [rad], translation sigma [odometry units])``.

    F-Eq. 3 multiplies the loop's information by its confidence ``p`` (and GNC's
    ``weight``); the translation's sigma never falls below ``loop_sigma_trans_floor_ratio``
    keyframe spacings, which ``p`` does not lower (module docstring). The solve's loop
    factors and the pairwise consistency test
    (:func:`~como3r.decentralized.pairwise_consistency.pair_chi2`) both take a loop's noise from here.

    Args:
        probability: the loop's confidence ``p`` (F-Eq. 2).
        spacing: the keyframe spacing, in odometry units.
        config: ``loop_sigma_rot_deg``, ``loop_sigma_trans_ratio`` and
            ``loop_sigma_trans_floor_ratio``.
        weight: GNC weight of the loop (1 outside GNC).
    """
    information = weight * probability
    sigma_trans = max(
        config.loop_sigma_trans_ratio * spacing / math.sqrt(information),
        config.loop_sigma_trans_floor_ratio * spacing / math.sqrt(weight),
    )
    return math.radians(config.loop_sigma_rot_deg) / math.sqrt(information), sigma_trans


def loop_covariance(
    T_ab: np.ndarray,
    scale: float,
    probability: float,
    spacing: float,
    config: PoseGraphConfig,
    weight: float = 1.0,
) -> np.ndarray:
    """A loop's ``(6, 6)`` covariance with its rotation error turning about the scene.

    The prior registers two pointmaps of the scene, so the fit's rotation error ``delta``
    turns camera b about the scene's centre ``c`` (``loop_scene_depth_ratio`` keyframe
    spacings in front of camera a) and moves it by ``delta x (b - c)``. In the error's
    frame (GTSAM's ``Log(Z^-1 T_a^-1 T_b)``: tangent ``(omega, v)`` at camera b,
    right perturbation) that is ``omega = R^T delta`` and ``v = [c_b]x omega`` with
    ``c_b = R^T (c - t)`` the scene's centre in camera b: the covariance is
    ``J Sigma_rot J^T + diag(0, sigma_t^2 I)``, ``J = [I; [c_b]x]``, with both sigmas of
    :func:`loop_sigmas` (F-Eq. 3; ``sigma_rot^2 D^2`` takes the place of the isotropic
    floor). A rotation about the scene's centre costs the rotation's Mahalanobis distance
    alone; the same camera displacement without that rotation is weighed by the isotropic
    ``sigma_t`` alone. Off by default (``decentralized.loop_covariance``): the prior's loops
    do not turn about the scene (measured there).

    Args:
        T_ab: ``(8,)`` the loop's relative pose (camera b in camera a, prior units;
            :class:`~.pose_graph_problem.LoopClosure`).
        scale: the factor taking its translation to odometry units (F-Eq. 6).
        probability: its confidence ``p`` (F-Eq. 2).
        spacing: the keyframe spacing, in odometry units.
        config: ``loop_scene_depth_ratio`` and the sigmas of :func:`loop_sigmas`.
        weight: GNC weight of the loop (1 outside GNC).

    Returns:
        ``(6, 6)`` covariance of the loop factor's error, ``(omega, v)`` order, odometry
        units.
    """
    sigma_rot, sigma_trans = loop_sigmas(probability, spacing, config, weight)
    pose = to_pose3(T_ab)
    R = pose.rotation().matrix()
    centre = np.array([0.0, 0.0, config.loop_scene_depth_ratio * spacing])
    c_b = R.T @ (centre - scale * np.asarray(pose.translation(), dtype=np.float64))
    J = np.vstack([np.eye(3), _skew(c_b)])
    covariance = sigma_rot**2 * J @ J.T
    covariance[3:, 3:] += np.eye(3) * sigma_trans**2
    return covariance


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def robot_start(problem: PoseGraphProblem, robot: int, config: PoseGraphConfig) -> OdometryStart:
    """Robot ``robot``'s odometry start: the problem's (its declared kind), else the
    configuration's ``odom_start_scale_sigma`` over ``odom_start_spacings``."""
    default = OdometryStart(config.odom_start_scale_sigma, config.odom_start_spacings)
    return problem.starts.get(robot, default)


def start_scale_sigma(travelled: float, start: OdometryStart) -> float:
    """The odometry's scale uncertainty ``scale_sigma x exp(-travelled / spacings)`` after
    ``travelled`` keyframe spacings (:func:`odometry_noise`)."""
    if start.scale_sigma <= 0 or start.spacings <= 0:
        return 0.0
    return start.scale_sigma * math.exp(-travelled / start.spacings)


def step_lengths(odometry: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """``(K - 1,)`` each: the lengths of one robot's ``(K, 8)`` odometry steps (odometry
    units) and the distance travelled from its first keyframe to each step's middle (keyframe
    spacings), where :func:`start_scale_sigma` is taken."""
    lengths = np.linalg.norm(np.diff(odometry[:, :3], axis=0), axis=1)
    return lengths, (np.cumsum(lengths) - lengths / 2) / spacing


def start_variance(odometry: np.ndarray, spacing: float, start: OdometryStart) -> np.ndarray:
    """``(K,)``: the summed variance of the odometry's step lengths from keyframe 0 to each
    keyframe of one robot's ``(K, 8)`` odometry, from its unconverged scale ``start``
    (:func:`start_scale_sigma`; odometry units squared)."""
    lengths, middles = step_lengths(odometry, spacing)
    sigmas = np.array([start_scale_sigma(float(d), start) for d in middles])
    return np.concatenate([[0.0], np.cumsum((sigmas * lengths) ** 2)])


def odometry_noise(
    step: gtsam.Pose3,
    travelled: float,
    spacing: float,
    config: PoseGraphConfig,
    start: OdometryStart,
) -> gtsam.noiseModel.Base:
    """Noise of one odometry step (F-Eq. 4's ``Omega_odom``).

    ``odom_sigma_rot_deg`` and ``odom_sigma_trans_ratio`` keyframe spacings, plus, along the
    step's direction, ``start.scale_sigma x exp(-travelled / start.spacings)`` of its
    length: a monocular VIO's scale is off until its estimate converges, at the start of a
    trajectory (F-Sec. IV-C), and a scale error stretches a step along itself.

    Args:
        step: the step's relative pose (keyframe ``k-1`` to ``k``, odometry units).
        travelled: odometry distance from the robot's first keyframe to the step's middle,
            in keyframe spacings.
        spacing: the keyframe spacing, in odometry units.
        config: the odometry noise parameters.
        start: the robot's odometry start (:func:`robot_start`).
    """
    sigma_rot = math.radians(config.odom_sigma_rot_deg)
    sigma_trans = config.odom_sigma_trans_ratio * spacing
    stretch = start_scale_sigma(travelled, start)
    if stretch == 0.0:
        return pose_noise(sigma_rot, sigma_trans, 1.0)
    # GTSAM's error is Log(Z^-1 T_a^-1 T_b): a stretch d of the step's translation t appears
    # as d R^T t in the step's end frame.
    along = step.rotation().matrix().T @ np.asarray(step.translation(), dtype=np.float64)
    covariance = np.zeros((_POSE_DIM, _POSE_DIM))
    covariance[:3, :3] = np.eye(3) * sigma_rot**2
    covariance[3:, 3:] = np.eye(3) * sigma_trans**2 + stretch**2 * np.outer(along, along)
    return gtsam.noiseModel.Gaussian.Covariance(covariance)
