"""Scale-aware multi-robot pose graphs (decentralized/pose_graph.py, pose_graph_problem.py,
initial_estimate.py; F-Sec. III-C)."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from como3r.config_decentralized import (
    FORMULATIONS,
    DecentralizedConfig,
    PoseGraphConfig,
    check_config,
)
from como3r.decentralized.factor_noise import odometry_noise
from como3r.decentralized.initial_estimate import initial_poses, keyframe_spacing
from como3r.decentralized.odometry_kind import OdometryKind, odometry_start
from como3r.decentralized.pose_graph import (
    build_graph,
    scaled_loop_error,
    scaled_loop_factor,
    solve_pose_graph,
)
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    OdometryStart,
    PoseGraphProblem,
    connected_components,
    from_pose3,
    loop_clusters,
    pose_key,
    to_pose3,
)
from como3r.errors import ConfigError


def _random_pose(rng: np.random.Generator, spread: float = 3.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3)), spread * rng.normal(size=3))


def _numerical_jacobians(R_bar, t_bar, T_a, T_b, s, h=1e-6):
    """Central differences of the error under GTSAM's retraction (what LM linearises)."""

    def error(a, b, scale):
        return scaled_loop_error(R_bar, t_bar, a, b, scale)[0]

    H_a, H_b = np.zeros((6, 6)), np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        H_a[:, k] = (error(T_a.retract(d), T_b, s) - error(T_a.retract(-d), T_b, s)) / (2 * h)
        H_b[:, k] = (error(T_a, T_b.retract(d), s) - error(T_a, T_b.retract(-d), s)) / (2 * h)
    H_s = ((error(T_a, T_b, s + h) - error(T_a, T_b, s - h)) / (2 * h))[:, None]
    return [H_a, H_b, H_s]


@pytest.mark.parametrize("seed", range(5))
def test_scaled_loop_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    R_bar = gtsam.Rot3.Rodrigues(rng.normal(size=3)).matrix()
    t_bar = 2.0 * rng.normal(size=3)
    T_a, T_b = _random_pose(rng), _random_pose(rng)
    s = float(rng.uniform(0.5, 2.0))
    e, analytic = scaled_loop_error(R_bar, t_bar, T_a, T_b, s)
    assert np.linalg.norm(e) > 0.5  # far from zero residual: the exact forms matter
    for H, numeric in zip(analytic, _numerical_jacobians(R_bar, t_bar, T_a, T_b, s)):
        np.testing.assert_allclose(H, numeric, atol=1e-7)


def test_scaled_loop_jacobians_reduce_to_the_paper_at_zero_residual():
    rng = np.random.default_rng(7)
    T_a, T_b = _random_pose(rng), _random_pose(rng)
    relative = T_a.between(T_b)
    s = 1.7
    R_bar, t_bar = relative.rotation().matrix(), relative.translation() / s
    e, (H_a, H_b, H_s) = scaled_loop_error(R_bar, t_bar, T_a, T_b, s)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    # F-Sec. III-C-b: H_Ta = -Adj(inv(T_a^-1 T_b)), H_Tb = I, H_s = [0, -t_bar] (in camera b).
    np.testing.assert_allclose(H_a, -relative.inverse().AdjointMap(), atol=1e-12)
    np.testing.assert_allclose(H_b, np.eye(6), atol=1e-12)
    np.testing.assert_allclose(
        H_s[:, 0], np.concatenate([np.zeros(3), -R_bar.T @ t_bar]), atol=1e-12
    )


def test_custom_factor_linearizes_to_the_analytic_jacobians():
    rng = np.random.default_rng(3)
    R_bar = gtsam.Rot3.Rodrigues(rng.normal(size=3)).matrix()
    t_bar = rng.normal(size=3)
    sigmas = np.array([0.1, 0.1, 0.1, 0.5, 0.5, 0.5])
    factor = scaled_loop_factor((1, 2, 3), R_bar, t_bar, gtsam.noiseModel.Diagonal.Sigmas(sigmas))
    values = gtsam.Values()
    T_a, T_b = _random_pose(rng), _random_pose(rng)
    values.insert(1, T_a)
    values.insert(2, T_b)
    values.insert(3, 0.8)
    e, H = scaled_loop_error(R_bar, t_bar, T_a, T_b, 0.8)
    assert factor.error(values) == pytest.approx(0.5 * np.sum((e / sigmas) ** 2))
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, np.hstack(H) / sigmas[:, None], atol=1e-10)
    np.testing.assert_allclose(b, -e / sigmas, atol=1e-10)


def test_scale_smoothing_factor_jacobians_are_minus_one_and_one():
    """F-Sec. III-C-c: phi = ||s_j - s_i||^2 with H_si = -1 and H_sj = 1."""
    sigma = 0.2
    factor = gtsam.BetweenFactorDouble(1, 2, 0.0, gtsam.noiseModel.Isotropic.Sigma(1, sigma))
    values = gtsam.Values()
    values.insert(1, 0.7)
    values.insert(2, 1.3)
    A, b = factor.linearize(values).jacobian()
    np.testing.assert_allclose(A, [[-1.0 / sigma, 1.0 / sigma]])
    np.testing.assert_allclose(b, [-(1.3 - 0.7) / sigma])


# ----------------------------------------------------------------------------- synthetic graphs


def _circle(robot: int, count: int, radius: float = 6.0) -> list[gtsam.Pose3]:
    """Ground-truth keyframe poses of a robot on a circle, looking along its path."""
    poses = []
    for k in range(count):
        angle = 2 * math.pi * (k / count) + 0.6 * robot
        heading = Rotation.from_euler("z", angle + math.pi / 2).as_matrix()
        position = np.array([radius * math.cos(angle), radius * math.sin(angle), 0.3 * robot])
        poses.append(gtsam.Pose3(gtsam.Rot3(heading), position))
    return poses


#: Keyframe spacing of :func:`_circle` (chord of a 12th of a 6 m circle) [m].
_SPACING = 2 * 6.0 * math.sin(math.pi / 12)


def _config(**overrides) -> PoseGraphConfig:
    """Pose-graph settings whose translation noise is 2 cm (odometry) and 10 cm (loops) at
    :data:`_SPACING`, the noise the synthetic measurements carry: the paper's graph (metric
    odometry, loop translations weighted by p alone, F-Sec. III-C's scale scatter 0.2)
    unless ``overrides`` say otherwise."""
    settings = {
        "odom_sigma_trans_ratio": 0.02 / _SPACING,
        "loop_sigma_trans_ratio": 0.1 / _SPACING,
        "odom_scale_walk": 0.0,
        "loop_sigma_trans_floor_ratio": 0.0,
        "scale_smoothing_sigma": 0.2,
    }
    return PoseGraphConfig(**{**settings, **overrides})


@dataclasses.dataclass
class _Synthetic:
    truth: dict[int, list[gtsam.Pose3]]
    problem: PoseGraphProblem


def _synthetic(
    rng: np.random.Generator,
    loop_scale_sigma: float = 0.0,
    outliers: int = 0,
    robots: int = 3,
    count: int = 12,
) -> _Synthetic:
    """Robots on circles, odometry in their own frames, loops between close keyframes.

    Loop translations are multiplied by ``exp(N(0, loop_scale_sigma))`` (the prior's scale
    inconsistency); the F-Eq. 6 factor is 1, so the base formulation cannot undo it.
    """
    truth = {r: _circle(r, count) for r in range(robots)}
    odometry = {}
    for r, poses in truth.items():
        frame = _random_pose(rng, 10.0)
        odometry[r] = np.stack([from_pose3(frame.compose(p)) for p in poses])
    loops = []
    for a in range(robots):
        for b in range(a + 1, robots):
            for i in range(0, count, 2):
                j = (i + 1) % count
                relative = truth[a][i].between(truth[b][j])
                noisy = relative.compose(
                    gtsam.Pose3.Expmap(
                        np.concatenate([0.005 * rng.normal(size=3), 0.02 * rng.normal(size=3)])
                    )
                )
                scale = math.exp(loop_scale_sigma * rng.normal())
                T_ab = from_pose3(gtsam.Pose3(noisy.rotation(), scale * noisy.translation()))
                loops.append(LoopClosure(a, i, b, j, T_ab, 1.0, 1.0, 0.9, 500))
    for _ in range(outliers):
        i, j = (int(v) for v in rng.integers(0, count, 2))
        wrong = gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3)), 5.0 * rng.normal(size=3))
        loops.append(LoopClosure(0, i, 1, j, from_pose3(wrong), 1.0, 1.2, 0.9, 600))
    anchor_pose = from_pose3(truth[0][0])
    return _Synthetic(truth, PoseGraphProblem(odometry, loops, 0, anchor_pose))


def _position_rmse(truth: dict[int, list[gtsam.Pose3]], poses: dict[int, np.ndarray]) -> float:
    errors = [
        np.linalg.norm(poses[r][k, :3] - p.translation())
        for r, ps in truth.items()
        for k, p in enumerate(ps)
    ]
    return float(np.sqrt(np.mean(np.square(errors))))


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_every_formulation_recovers_a_consistent_graph(formulation):
    data = _synthetic(np.random.default_rng(0))
    solution = solve_pose_graph(data.problem, formulation, "lm", _config())
    assert _position_rmse(data.truth, solution.poses) < 0.05
    np.testing.assert_allclose(solution.loop_scales, 1.0, atol=0.05)
    assert solution.iterations >= 1 and solution.seconds > 0


def test_independent_and_smoothed_scales_beat_the_base_formulation_on_inconsistent_scales():
    """F-Sec. III-C: loops whose prior scale is wrong hurt the base graph, not the
    scale-aware ones."""
    data = _synthetic(np.random.default_rng(1), loop_scale_sigma=0.3)
    errors = {
        f: _position_rmse(data.truth, solve_pose_graph(data.problem, f, "lm", _config()).poses)
        for f in ("base", "independent", "smoothed")
    }
    assert errors["independent"] < 0.5 * errors["base"]
    assert errors["smoothed"] < 0.5 * errors["base"]


def test_independent_scales_absorb_each_loops_scale_error():
    data = _synthetic(np.random.default_rng(2), loop_scale_sigma=0.3)
    solution = solve_pose_graph(data.problem, "independent", "lm", _config())
    true_scales = []
    for loop in data.problem.loops:
        truth = data.truth[loop.robot_a][loop.keyframe_a].between(
            data.truth[loop.robot_b][loop.keyframe_b]
        )
        true_scales.append(np.linalg.norm(truth.translation()) / np.linalg.norm(loop.T_ab[:3]))
    np.testing.assert_allclose(solution.loop_scales, true_scales, rtol=0.05)


@pytest.mark.parametrize("formulation", ["base", "independent", "smoothed"])
@pytest.mark.parametrize("loss", ["tls", "gm"])
def test_gnc_weights_injected_outliers_near_zero(formulation, loss):
    data = _synthetic(np.random.default_rng(4), outliers=3)
    config = _config(gnc_loss=loss)
    solution = solve_pose_graph(data.problem, formulation, "gnc", config)
    inliers, outliers = solution.loop_weights[:-3], solution.loop_weights[-3:]
    assert np.all(outliers < 0.05), outliers
    assert np.all(inliers > 0.9), inliers
    lm = solve_pose_graph(data.problem, formulation, "lm", config)
    assert _position_rmse(data.truth, solution.poses) < 0.05
    assert _position_rmse(data.truth, solution.poses) < _position_rmse(data.truth, lm.poses)


def test_initialisation_follows_the_loops_most_others_agree_with():
    data = _synthetic(np.random.default_rng(5), outliers=2, robots=2)
    scales = np.ones(len(data.problem.loops))
    poses = initial_poses(data.problem, scales, keyframe_spacing(data.problem, scales))
    error = np.linalg.norm(poses[1][0].translation() - data.truth[1][0].translation())
    assert error < 0.2


def test_connected_components_and_clusters():
    T = from_pose3(gtsam.Pose3())
    loops = [LoopClosure(0, k, 1, k + 1, T, 1.0, 1.0, 0.5, 10) for k in (0, 5, 30)]
    loops.append(LoopClosure(3, 2, 2, 0, T, 1.0, 1.0, 0.5, 10))
    assert connected_components([0, 1, 2, 3, 4], loops) == [[0, 1], [2, 3], [4]]
    # Loops 0 and 1 are 5 keyframes apart on both robots, loop 2 is 25 further.
    assert loop_clusters(loops, window=10) == [[0, 1], [2], [3]]
    assert loop_clusters(loops, window=5) == [[0], [1], [2], [3]]


def test_a_single_loop_between_two_robots_is_well_posed_with_scale_variables():
    data = _synthetic(np.random.default_rng(6), robots=2)
    data.problem.loops = data.problem.loops[:1]
    for formulation in ("independent", "smoothed", "shared"):
        solution = solve_pose_graph(data.problem, formulation, "lm", _config())
        assert np.all(np.isfinite(solution.poses[1]))
        assert solution.loop_scales[0] == pytest.approx(1.0, abs=0.05)


def test_pose_conversions_round_trip():
    rng = np.random.default_rng(8)
    pose = _random_pose(rng)
    T = from_pose3(pose)
    assert T.shape == (8,) and T[6] >= 0 and T[7] == 1.0
    assert to_pose3(T).equals(pose, 1e-12)


def _stretched(odometry: np.ndarray, start_error: float, convergence: float) -> np.ndarray:
    """``odometry (K, 8)`` re-integrated with step ``k`` scaled by
    ``1 + start_error exp(-k / convergence)``: a VIO whose scale has not converged yet."""
    out = odometry.copy()
    for k in range(1, len(odometry)):
        factor = 1.0 + start_error * math.exp(-k / convergence)
        out[k, :3] = out[k - 1, :3] + factor * (odometry[k, :3] - odometry[k - 1, :3])
    return out


def test_odometry_scales_undo_an_unconverged_vio_start():
    """One robot's odometry starts 40 % long; per-step odometry scales tied by a random walk
    let the loops to the other robots shorten it, and change little where it is right."""
    data = _synthetic(np.random.default_rng(9), loop_scale_sigma=0.05)
    truth = _position_rmse(
        data.truth, solve_pose_graph(data.problem, "smoothed", "lm", _config()).poses
    )
    data.problem.odometry[1] = _stretched(data.problem.odometry[1], 0.4, 3.0)
    fixed = solve_pose_graph(data.problem, "smoothed", "lm", _config(odom_scale_walk=0.0)).poses
    walk = solve_pose_graph(data.problem, "smoothed", "lm", _config(odom_scale_walk=0.1)).poses
    assert _position_rmse(data.truth, walk) < 0.5 * _position_rmse(data.truth, fixed)
    solved = np.linalg.norm(np.diff(walk[1][:, :3], axis=0), axis=1)
    measured = np.linalg.norm(np.diff(data.problem.odometry[1][:, :3], axis=0), axis=1)
    assert solved[0] / measured[0] < 0.85  # the first step shortened toward 1 / 1.4
    assert truth < 0.05


def test_odometry_noise_widens_an_unconverged_start_along_the_motion():
    """At the start, a step's translation variance along its direction (in its end frame)
    gains ``(scale_sigma x length)^2``; across it, and far from the start, the odometry
    keeps ``odom_sigma_trans_ratio`` spacings."""
    config = PoseGraphConfig(odom_sigma_trans_ratio=0.04)
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.3), np.array([2.0, 0.0, 0.0]))
    along = step.rotation().matrix().T @ np.array([1.0, 0.0, 0.0])
    across = np.cross(along, [0.0, 0.0, 1.0])
    for travelled, stretch in ((0.0, 0.3 * 2.0), (2.0, 0.3 * 2.0 * math.exp(-1.0)), (40.0, 0.0)):
        noise = odometry_noise(step, travelled, 1.0, config, OdometryStart(0.3, 2.0))
        covariance = np.linalg.inv(noise.information())
        assert along @ covariance[3:, 3:] @ along == pytest.approx(0.04**2 + stretch**2, rel=1e-6)
        assert across @ covariance[3:, 3:] @ across == pytest.approx(0.04**2, rel=1e-6)
        assert np.diag(covariance[:3, :3]) == pytest.approx([math.radians(0.5) ** 2] * 3)


def test_a_discounted_odometry_start_lets_loops_shorten_an_unconverged_vio_start():
    """One robot's odometry starts 40 % long; with its start discounted the loops to the
    other robots shorten it (here: 0.42 -> 0.26 m RMSE; on right odometry the discount
    costs, 0.02 -> 0.11 m, as it does a ``lio`` odometry)."""
    data = _synthetic(np.random.default_rng(9), loop_scale_sigma=0.05)
    data.problem.odometry[1] = _stretched(data.problem.odometry[1], 0.4, 3.0)
    metric = solve_pose_graph(data.problem, "smoothed", "lm", _config()).poses
    discounted = solve_pose_graph(
        data.problem,
        "smoothed",
        "lm",
        _config(odom_start_scale_sigma=0.4, odom_start_spacings=3.0),
    ).poses
    assert _position_rmse(data.truth, discounted) < 0.7 * _position_rmse(data.truth, metric)


def test_the_vio_start_is_set_in_keyframe_spacings_from_scene_depths():
    """A declared ``vio`` robot's start: ``vio_start_scale_error`` (0.3 by default) over
    ``vio_start_depths / keyframe_distance_ratio`` spacings, or the declaration's own; a
    ``metric`` one has none; undeclared: None (the pose graph's own key then)."""
    settings = DecentralizedConfig(keyframe_distance_ratio=0.1)
    assert odometry_start(OdometryKind("vio"), settings) == OdometryStart(0.3, pytest.approx(3.0))
    own = odometry_start(OdometryKind("vio", start_scale_error=0.1, start_depths=0.5), settings)
    assert own == OdometryStart(0.1, pytest.approx(5.0))
    assert odometry_start(OdometryKind("metric"), settings) == OdometryStart(0.0, 0.0)
    assert odometry_start(None, settings) is None
    # the team-wide graph settings carry no start: it is per robot
    assert settings.pose_graph_config().odom_start_scale_sigma == 0.0
    assert PoseGraphConfig().odom_start_scale_sigma == 0.0  # the paper's metric odometry


def _odometry_stretch_sigmas(graph, problem: PoseGraphProblem, robot: int) -> np.ndarray:
    """``(K - 1,)``: the translation sigma along each odometry step of ``robot`` in the
    built graph (the step's direction in its end frame)."""
    sigmas = []
    for k in range(1, len(problem.odometry[robot])):
        step = to_pose3(problem.odometry[robot][k - 1]).between(
            to_pose3(problem.odometry[robot][k])
        )
        along = step.rotation().matrix().T @ np.asarray(step.translation())
        along /= np.linalg.norm(along)
        factor = next(
            f
            for f in (graph.fixed.at(i) for i in range(graph.fixed.size()))
            if isinstance(f, gtsam.BetweenFactorPose3)
            and list(f.keys()) == [pose_key(robot, k - 1), pose_key(robot, k)]
        )
        covariance = np.linalg.inv(factor.noiseModel().information())
        sigmas.append(math.sqrt(along @ covariance[3:, 3:] @ along))
    return np.array(sigmas)


def test_a_declared_vio_robots_start_is_discounted_and_a_metric_ones_is_not():
    """One team, robot 0 declared ``vio`` and robot 1 ``metric``, robot 2 undeclared: only
    robot 0's first steps gain the start's stretch along the motion; robot 1's and robot
    2's keep the odometry's sigma everywhere (the configuration's undeclared start is 0)."""
    data = _synthetic(np.random.default_rng(3))
    settings = DecentralizedConfig(keyframe_distance_ratio=0.1)
    problem = dataclasses.replace(
        data.problem,
        starts={
            0: odometry_start(OdometryKind("vio"), settings),
            1: odometry_start(OdometryKind("metric"), settings),
        },
    )
    config = _config()
    graph = build_graph(problem, "smoothed", config)
    plain = config.odom_sigma_trans_ratio * keyframe_spacing(problem, np.ones(len(problem.loops)))
    vio, metric, undeclared = (_odometry_stretch_sigmas(graph, problem, r) for r in range(3))
    assert vio[0] > 3 * plain  # 0.3 of a step's length, about a spacing, against 0.02 m
    assert vio[-1] < 2 * plain < vio[0] / 2  # decayed over 3 spacings, 11 steps
    assert np.all(np.diff(vio) < 0)
    assert metric == pytest.approx(plain, rel=1e-6)
    assert undeclared == pytest.approx(plain, rel=1e-6)
    # the undeclared robot takes the configuration's start: here the same as robot 0's
    legacy = build_graph(
        problem, "smoothed", _config(odom_start_scale_sigma=0.3, odom_start_spacings=3.0)
    )
    assert _odometry_stretch_sigmas(legacy, problem, 2)[0] > 3 * plain
    assert _odometry_stretch_sigmas(legacy, problem, 1) == pytest.approx(plain, rel=1e-6)


def test_loop_translation_sigma_has_a_floor_confidence_cannot_lower():
    data = _synthetic(np.random.default_rng(10), robots=2)
    spacing = keyframe_spacing(data.problem, np.ones(len(data.problem.loops)))
    for floor, expected in ((0.0, 0.1), (1.0, spacing)):
        graph = build_graph(data.problem, "smoothed", _config(loop_sigma_trans_floor_ratio=floor))
        sigmas = graph.loop_factor(0, 1.0).noiseModel().sigmas()
        # p = 0.9: without the floor 0.1 m / sqrt(0.9); the rotation keeps F-Eq. 3's 1/sqrt(p).
        assert sigmas[3:] == pytest.approx([max(expected, 0.1 / math.sqrt(0.9))] * 3, rel=1e-6)
        assert sigmas[:3] == pytest.approx([math.radians(2.0) / math.sqrt(0.9)] * 3, rel=1e-6)


def test_odometry_scale_and_loop_floor_settings_are_validated():
    for key, value in (
        ("odom_scale_walk", -0.1),
        ("odom_scale_prior", 0.0),
        ("loop_sigma_trans_floor_ratio", -1.0),
        ("odom_start_scale_sigma", -0.1),
        ("odom_start_spacings", -1.0),
    ):
        with pytest.raises(ConfigError, match=key):
            check_config(DecentralizedConfig(pose_graph=PoseGraphConfig(**{key: value})))
    for key in ("vio_start_scale_error", "vio_start_depths"):
        with pytest.raises(ConfigError, match=key):
            check_config(DecentralizedConfig(**{key: -0.1}))


def test_the_loop_floor_is_the_rotation_noise_at_the_scene_depth_in_keyframe_spacings():
    """``radians(loop_sigma_rot_deg) x loop_lever_arm_depths / keyframe_distance_ratio``
    spacings, or the explicit ``pose_graph`` floor where that is larger; 0: the paper's."""
    graph = DecentralizedConfig(keyframe_distance_ratio=0.1).pose_graph_config()
    assert graph.loop_sigma_trans_floor_ratio == pytest.approx(math.radians(2.0) / 0.1)
    explicit = DecentralizedConfig(pose_graph=PoseGraphConfig(loop_sigma_trans_floor_ratio=3.0))
    assert explicit.pose_graph_config().loop_sigma_trans_floor_ratio == 3.0
    off = DecentralizedConfig(loop_lever_arm_depths=0.0).pose_graph_config()
    assert off.loop_sigma_trans_floor_ratio == 0.0
