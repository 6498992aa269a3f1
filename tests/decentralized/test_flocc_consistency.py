"""Wrong loops cannot bend the map (decentralized/consistency.py): pairwise consistency and
the scale-collapse alarm."""

from __future__ import annotations

import dataclasses
import logging
import math

import gtsam
import numpy as np
import pytest
from scipy.stats import chi2

from como3r.config_decentralized import DecentralizedConfig, PoseGraphConfig, check_config
from como3r.decentralized import pairwise_consistency
from como3r.decentralized.consistency import check_solution, solve_checked, solve_shares
from como3r.decentralized.factor_noise import start_variance
from como3r.decentralized.messages import PoseGraphShare
from como3r.decentralized.pairwise_consistency import consistent_loops, oriented_loop, pair_chi2
from como3r.decentralized.pose_graph import solve_pose_graph
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    OdometryStart,
    PoseGraphProblem,
    PoseGraphSolution,
    from_pose3,
)
from como3r.errors import ConfigError

COUNT = 24
RADIUS = 6.0
SPACING = 2 * RADIUS * math.sin(math.pi / COUNT)


def _circle(robot: int) -> list[gtsam.Pose3]:
    poses = []
    for k in range(COUNT):
        angle = 2 * math.pi * k / COUNT + 0.4 * robot
        t = np.array([RADIUS * math.cos(angle), RADIUS * math.sin(angle), 0.3 * robot])
        poses.append(gtsam.Pose3(gtsam.Rot3.Ypr(angle + math.pi / 2, 0.0, 0.0), t))
    return poses


def _config(**overrides) -> PoseGraphConfig:
    """Noise models matching the measurements: 2 cm odometry, 10 cm loops."""
    return PoseGraphConfig(
        odom_sigma_trans_ratio=0.02 / SPACING, loop_sigma_trans_ratio=0.1 / SPACING, **overrides
    )


@dataclasses.dataclass
class _Data:
    truth: dict[int, list[gtsam.Pose3]]
    problem: PoseGraphProblem
    true_loops: int


def _data(seed: int, look_alike: int = 0, wrong_scale: int = 0) -> _Data:
    """Three robots on circles; true loops between close keyframes (scale 1, F-Eq. 6
    factor 1), then ``look_alike`` loops between far keyframes registered to a plausible
    close pose and ``wrong_scale`` true loops whose translation is 2.5x too long."""
    rng = np.random.default_rng(seed)
    truth = {r: _circle(r) for r in range(3)}
    odometry = {}
    for r, poses in truth.items():
        frame = gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3)), 5 * rng.normal(size=3))
        odometry[r] = np.stack([from_pose3(frame.compose(p)) for p in poses])
    loops = []
    for a in range(3):
        for b in range(a + 1, 3):
            for i in range(0, COUNT, 3):
                relative = truth[a][i].between(truth[b][i])
                noisy = relative.compose(
                    gtsam.Pose3.Expmap(
                        np.concatenate([0.005 * rng.normal(size=3), 0.02 * rng.normal(size=3)])
                    )
                )
                loops.append(LoopClosure(a, i, b, i, from_pose3(noisy), 1.0, 1.0, 0.9, 500))
    true_loops = len(loops)
    for n in range(look_alike):
        a, b = (0, 1) if n % 2 == 0 else (1, 2)
        i = int(rng.integers(COUNT))
        j = (i + COUNT // 2 + int(rng.integers(-3, 4))) % COUNT
        claimed = gtsam.Pose3(
            gtsam.Rot3.Ypr(*rng.uniform(-0.2, 0.2, 3)), rng.uniform(-0.5, 0.5, 3) * SPACING
        )
        loops.append(LoopClosure(a, i, b, j, from_pose3(claimed), 1.0, 1.0, 0.9, 500))
    for n in range(wrong_scale):
        loop = loops[(5 * n + 1) % true_loops]
        T = loop.T_ab.copy()
        T[:3] *= 2.5
        loops.append(dataclasses.replace(loop, T_ab=T))
    problem = PoseGraphProblem(odometry, loops, 0, from_pose3(truth[0][0]))
    return _Data(truth, problem, true_loops)


def _rmse(truth: dict[int, list[gtsam.Pose3]], poses: dict[int, np.ndarray]) -> float:
    errors = [
        np.linalg.norm(poses[r][k, :3] - p.translation())
        for r, ps in truth.items()
        for k, p in enumerate(ps)
    ]
    return float(np.sqrt(np.mean(np.square(errors))))


def test_pairwise_consistency_keeps_true_loops_and_holds_back_wrong_ones():
    data = _data(0, look_alike=4, wrong_scale=4)
    keep = consistent_loops(data.problem, _config())
    assert keep[: data.true_loops].all()
    assert not keep[data.true_loops :].any(), keep[data.true_loops :]


def test_pairwise_consistency_weighs_a_loop_with_the_solves_translation_floor():
    """Two loops of robots 0 and 1, the second's translation one keyframe spacing off: at
    p = 0.9 without a floor their cycle is inconsistent; with the floor the solve gives a
    loop (0.5 spacings, :func:`~como3r.decentralized.factor_noise.loop_sigmas`) it is not."""
    data = _data(0)
    first, second = data.problem.loops[0], data.problem.loops[1]
    assert (first.robot_a, first.robot_b, second.robot_a, second.robot_b) == (0, 1, 0, 1)
    moved = second.T_ab.copy()
    moved[0] += SPACING
    threshold = chi2.ppf(0.99, 6)
    statistics = [
        pair_chi2(
            oriented_loop(first, 1.0),
            oriented_loop(dataclasses.replace(second, T_ab=moved), 1.0),
            0.9,
            0.9,
            data.problem.odometry,
            SPACING,
            _config(loop_sigma_trans_floor_ratio=floor, scale_smoothing_sigma=0.01),
        )
        for floor in (0.0, 0.5)
    ]
    assert statistics[0] > threshold > statistics[1]


def test_pairwise_consistency_counts_the_odometrys_unconverged_start():
    """Robot 1's odometry starts 40 % long (a VIO's scale before it converges): the cycle of
    two true loops at its keyframes 0 and 6 is inconsistent for a metric odometry and
    consistent once the solve's start discount (:func:`~.factor_noise.start_variance`) is
    counted."""
    data = _data(0)
    first, second = data.problem.loops[0], data.problem.loops[2]
    assert (first.keyframe_b, second.keyframe_b, second.robot_b) == (0, 6, 1)
    odometry = dict(data.problem.odometry)
    steps = np.diff(odometry[1][:, :3], axis=0)
    stretch = 1 + 0.4 * np.exp(-np.arange(1, COUNT) / 3)[:, None]
    odometry[1] = odometry[1].copy()
    odometry[1][1:, :3] = odometry[1][0, :3] + np.cumsum(stretch * steps, axis=0)
    statistics = []
    for start_sigma in (0.0, 0.4):
        config = _config(
            scale_smoothing_sigma=0.01, odom_start_scale_sigma=start_sigma, odom_start_spacings=3.0
        )
        begin = OdometryStart(config.odom_start_scale_sigma, config.odom_start_spacings)
        start = {r: start_variance(o, SPACING, begin) for r, o in odometry.items()}
        statistics.append(
            pair_chi2(
                oriented_loop(first, 1.0),
                oriented_loop(second, 1.0),
                0.9,
                0.9,
                odometry,
                SPACING,
                config,
                start,
            )
        )
    assert statistics[0] > chi2.ppf(0.99, 6) > statistics[1]


def test_the_greedy_clique_of_many_loops_holds_back_the_wrong_ones(monkeypatch):
    monkeypatch.setattr(pairwise_consistency, "MAX_EXACT_LOOPS", 2)
    data = _data(0, look_alike=4, wrong_scale=4)
    keep = consistent_loops(data.problem, _config())
    assert keep[: data.true_loops].all()
    assert not keep[data.true_loops :].any(), keep[data.true_loops :]


def test_a_graph_with_injected_wrong_loops_keeps_its_true_solution():
    """About 25 % wrong loops: the default solve behind pairwise consistency lands on the
    clean solution, the same solve without it is bent."""
    data = _data(1, look_alike=3, wrong_scale=3)
    clean = PoseGraphProblem(
        data.problem.odometry, data.problem.loops[: data.true_loops], 0, data.problem.anchor_pose
    )
    reference = _rmse(data.truth, solve_pose_graph(clean, "smoothed", "lm", _config()).poses)
    solution, check = solve_checked(data.problem, "smoothed", "lm", _config())
    assert not check.alarm
    assert _rmse(data.truth, solution.poses) < 1.2 * reference + 0.005
    bent, _ = solve_checked(data.problem, "smoothed", "lm", _config(consistency="none"))
    assert _rmse(data.truth, bent.poses) > 3 * _rmse(data.truth, solution.poses)


def test_the_scale_alarm_reports_a_loop_set_that_changes_a_robots_scale(caplog):
    data = _data(2)
    problem, config = data.problem, _config()
    # A solution in which robot 1's trajectory is 1.5x longer than its metric odometry.
    poses = {r: np.stack([from_pose3(p) for p in ps]) for r, ps in data.truth.items()}
    poses[1][:, :3] = 1.5 * poses[1][:, :3]
    count = len(problem.loops)
    stretched = PoseGraphSolution(
        poses, np.ones(count), np.ones(count), np.zeros(count), 0.0, 1, 0.0
    )
    with caplog.at_level(logging.WARNING):
        check = check_solution(problem, stretched, np.ones(count, dtype=bool), [0, 1, 2], config)
    assert check.alarm
    assert check.robot_scale_log[1] == pytest.approx(math.log(1.5), abs=1e-6)
    assert "scale-collapse alarm" in caplog.text
    assert check.to_json()["scale_alarm"] is True
    # The true solution raises nothing.
    truth = dataclasses.replace(
        stretched, poses={r: np.stack([from_pose3(p) for p in ps]) for r, ps in data.truth.items()}
    )
    calm = check_solution(problem, truth, np.ones(count, dtype=bool), [0, 1, 2], config)
    assert not calm.alarm and math.isnan(calm.merged_scale_log)


def test_the_scale_alarm_compares_the_merged_map_with_the_previous_one():
    data = _data(4)
    config = _config()
    truth = {r: np.stack([from_pose3(p) for p in ps]) for r, ps in data.truth.items()}
    problem = data.problem
    count = len(problem.loops)
    # The merged map 1.5x larger than before (about its centre).
    centre = np.concatenate([poses[:, :3] for poses in truth.values()]).mean(0)
    moved = {r: poses.copy() for r, poses in truth.items()}
    for poses in moved.values():
        poses[:, :3] = centre + 1.5 * (poses[:, :3] - centre)
    solution = PoseGraphSolution(
        moved, np.ones(count), np.ones(count), np.zeros(count), 0.0, 1, 0.0
    )
    check = check_solution(
        problem, solution, np.ones(count, dtype=bool), [0, 1, 2], config, reference=truth
    )
    assert check.merged_scale_log == pytest.approx(math.log(1.5), abs=1e-9)
    assert check.alarm
    same = dataclasses.replace(solution, poses=truth)
    calm = check_solution(
        problem, same, np.ones(count, dtype=bool), [0, 1, 2], config, reference=truth
    )
    assert abs(calm.merged_scale_log) < 1e-9 and not calm.alarm


def _shares(problem: PoseGraphProblem) -> dict[int, PoseGraphShare]:
    return {
        r: PoseGraphShare(
            sender=r,
            recipient=0,
            round=0,
            time_s=0.0,
            odometry=odometry,
            estimate=np.zeros((0, 8)),
            frame=r,
            loops=[l for l in problem.loops if l.robot_a == r],
        )
        for r, odometry in problem.odometry.items()
    }


def test_a_group_whose_solve_raises_the_alarm_keeps_its_estimates():
    data = _data(3)
    shares = _shares(data.problem)
    settings = DecentralizedConfig(pose_graph=_config())
    checks: list = []
    assert set(solve_shares(shares, settings, checks=checks)) == {0, 1, 2}
    assert len(checks) == 1 and not checks[0].alarm
    # A threshold no solve can meet: the update is held back and reported.
    strict = DecentralizedConfig(pose_graph=_config(scale_alarm_log=1e-9))
    checks = []
    assert solve_shares(shares, strict, checks=checks) == {}
    assert checks[0].alarm


def test_consistency_settings_are_validated():
    with pytest.raises(ConfigError, match="consistency_probability"):
        check_config(DecentralizedConfig(pose_graph=PoseGraphConfig(consistency_probability=1.0)))
    with pytest.raises(ConfigError, match="scale_alarm_log"):
        check_config(DecentralizedConfig(pose_graph=PoseGraphConfig(scale_alarm_log=0.0)))
