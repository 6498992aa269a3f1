"""A loop's covariance whose rotation error turns about the scene
(``decentralized.loop_covariance: scene``; decentralized/factor_noise.py ``loop_covariance``,
pose_graph.py, pairwise_consistency.py ``pair_chi2``)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from como3r.config_decentralized import DecentralizedConfig, PoseGraphConfig, check_config
from como3r.decentralized.factor_noise import loop_covariance
from como3r.decentralized.pairwise_consistency import (
    oriented_covariance,
    oriented_loop,
    pair_chi2,
)
from como3r.decentralized.pose_graph import build_graph, scaled_loop_error
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    PoseGraphProblem,
    from_pose3,
)
from como3r.errors import ConfigError

#: Scene depth in keyframe spacings (the default's 1 / 0.07) and the keyframe spacing [m].
DEPTH = 1 / 0.07
SPACING = 0.5
#: A 99 % chi-square bound (6 dof).
BOUND = chi2.ppf(0.99, 6)


def _config(**overrides) -> PoseGraphConfig:
    return PoseGraphConfig(loop_scene_depth_ratio=DEPTH, **overrides)


def _about_scene(relative: gtsam.Pose3, rotvec: np.ndarray) -> gtsam.Pose3:
    """``relative`` (camera b in camera a) with camera b turned by ``rotvec`` about the
    scene point ``DEPTH`` spacings in front of camera a."""
    centre = np.array([0.0, 0.0, DEPTH * SPACING])
    turn = gtsam.Rot3.Expmap(rotvec)
    return gtsam.Pose3(turn, centre - turn.matrix() @ centre).compose(relative)


def _loop(T_ab: np.ndarray, a: int = 0, b: int = 1, ka: int = 0, kb: int = 0) -> LoopClosure:
    return LoopClosure(a, ka, b, kb, T_ab, 1.0, 1.0, 0.8, 500)


def _mahalanobis(truth: gtsam.Pose3, measured: gtsam.Pose3, covariance: np.ndarray) -> float:
    """The loop factor's whitened squared error at the true poses (F-Eq. 8, scale 1)."""
    e, _ = scaled_loop_error(
        measured.rotation().matrix(),
        np.asarray(measured.translation()),
        gtsam.Pose3(),
        truth,
        1.0,
    )
    return float(e @ np.linalg.solve(covariance, e))


@pytest.mark.parametrize("baseline", [0.3, 1.0, 3.0])
def test_a_rotation_about_the_scene_is_cheap_the_same_displacement_without_it_is_not(baseline):
    """A 5 deg turn about the scene moves camera b by 1.25 spacings whatever the baseline:
    under the scene covariance that costs the rotation's distance alone (5 deg against 2 deg
    / sqrt(0.8)); the same displacement with the true rotation is beyond the bound (against
    0.2 spacings / sqrt(0.8))."""
    truth = gtsam.Pose3(gtsam.Rot3.Ypr(0.2, 0.05, -0.1), np.array([baseline, 0.1, 0.2]) * SPACING)
    turned = _about_scene(truth, np.radians([0.0, 5.0, 0.0]))
    shifted = gtsam.Pose3(truth.rotation(), turned.translation())
    moved = np.linalg.norm(turned.translation() - truth.translation()) / SPACING
    assert moved == pytest.approx(math.radians(5.0) * DEPTH, rel=0.05)
    covariance = loop_covariance(from_pose3(turned), 1.0, 0.8, SPACING, _config())
    assert _mahalanobis(truth, turned, covariance) < 6.0
    assert _mahalanobis(truth, shifted, covariance) > BOUND
    # The isotropic model (no scene depth) cannot tell them apart that way.
    diagonal = loop_covariance(from_pose3(turned), 1.0, 0.8, SPACING, PoseGraphConfig())
    assert _mahalanobis(truth, turned, diagonal) > BOUND


def test_the_scene_covariance_is_the_solves_noise_model_and_its_config():
    truth = gtsam.Pose3(gtsam.Rot3.Ypr(0.1, 0.0, 0.0), np.array([1.0, 0.0, 0.0]))
    odometry = {r: np.stack([from_pose3(gtsam.Pose3()), from_pose3(truth)]) for r in (0, 1)}
    loop = _loop(from_pose3(truth), ka=1, kb=1)
    problem = PoseGraphProblem(odometry, [loop], 0, from_pose3(gtsam.Pose3()))
    graph = build_graph(problem, "smoothed", _config())
    noise = graph.loop_factor(0, 0.5).noiseModel()
    expected = loop_covariance(loop.T_ab, 1.0, 0.8, 1.0, _config(), 0.5)
    assert np.linalg.inv(noise.R().T @ noise.R()) == pytest.approx(expected, rel=1e-6)
    scene = DecentralizedConfig(loop_covariance="scene").pose_graph_config()
    assert scene.loop_scene_depth_ratio == pytest.approx(DEPTH)
    assert scene.loop_sigma_trans_floor_ratio == 0.0  # the scene's lever arm replaces it
    default = DecentralizedConfig().pose_graph_config()
    assert default.loop_scene_depth_ratio == 0.0 < default.loop_sigma_trans_floor_ratio
    with pytest.raises(ConfigError, match="loop_covariance"):
        check_config(DecentralizedConfig(loop_covariance="full"))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="loop_scene_depth_ratio"):
        check_config(DecentralizedConfig(pose_graph=PoseGraphConfig(loop_scene_depth_ratio=-1)))


@pytest.mark.parametrize("flipped", [False, True])
@pytest.mark.parametrize("which", [0, 1])
def test_pairwise_consistency_weighs_a_turn_about_the_scene_with_the_solves_covariance(
    which, flipped
):
    """Two loops of robots 0 and 1 (cameras 46 deg apart), at keyframes 0 and 5 of tracks
    that pan by 72 deg; one of them registered 7 deg turned about the scene in front of its
    registering camera (1.75 spacings off): consistent under the scene covariance, and the
    same displacement without the turn is not. ``which``: the turned loop (the first one's
    covariance reaches the cycle through its adjoint); ``flipped``: the second loop
    registered by robot 1 (the inverse pose, its covariance through ``Ad``)."""
    steps = [
        gtsam.Pose3(gtsam.Rot3.Ry(0.25 * k), np.array([k * SPACING, 0.0, 0.1 * k * SPACING]))
        for k in range(6)
    ]
    odometry = {r: np.stack([from_pose3(p) for p in steps]) for r in (0, 1)}
    relative = gtsam.Pose3(gtsam.Rot3.Ypr(0.8, 0.3, 0.0), np.array([0.6, 0.0, 0.1]) * SPACING)
    # Camera b in camera a at keyframes 0 and 5 (O_a(0 -> 5)^-1 relative O_b(0 -> 5)), the
    # second as its registering robot measures it.
    true = [relative, steps[5].inverse().compose(relative).compose(steps[5])]
    if flipped:
        true[1] = true[1].inverse()
    turned = _about_scene(true[which], np.radians([0.0, 7.0, 0.0]))
    shifted = gtsam.Pose3(true[which].rotation(), turned.translation())
    # A precise odometry (its rotation drift, free of a lever arm, would let a turn about
    # the scene through) and loops whose isotropic translation noise is 0.1 spacings.
    config = _config(scale_smoothing_sigma=0.01, odom_sigma_rot_deg=0.1, loop_sigma_trans_ratio=0.1)
    statistics = []
    for measured in (turned, shifted):
        poses = list(true)
        poses[which] = measured
        first = _loop(from_pose3(poses[0]))
        robots = (1, 0) if flipped else (0, 1)
        second = _loop(from_pose3(poses[1]), *robots, ka=5, kb=5)
        statistics.append(
            pair_chi2(
                oriented_loop(first, 1.0),
                oriented_loop(second, 1.0),
                0.8,
                0.8,
                odometry,
                SPACING,
                config,
                covariances=(
                    oriented_covariance(first, 1.0, SPACING, config),
                    oriented_covariance(second, 1.0, SPACING, config),
                ),
            )
        )
    assert statistics[0] < BOUND < statistics[1]
