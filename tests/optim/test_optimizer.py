"""Tests of como3r.optim.optimizer: tracking by LM-IRLS, local/global BA by GN-IRLS."""

from __future__ import annotations

import logging
import math

import pytest
import torch

from como3r.config import GlobalBAConfig, LocalSolveConfig, TrackingConfig
from como3r.errors import InputError
from como3r.geometry.lie import (
    sim3_act,
    sim3_compose,
    sim3_exp,
    sim3_identity,
    sim3_inverse,
    sim3_log,
)
from como3r.optim.match_factors import CalibratedFactors, RayRangeFactors
from como3r.optim.optimizer import gauss_newton_irls, levenberg_marquardt_irls
from como3r.optim.synthetic import chain_poses, random_sim3, synthetic_graph
from como3r.optim.system import EdgeBlocks
from como3r.optim.values import PoseValues

NUM_MATCHES = 2000
MEAN_DEPTH = 12.5  # points are 5-20 m in front of the keyframe


def _tracking_problem(seed: int, dtype: torch.dtype):
    """A keyframe at the identity and a frame displaced by up to 10 deg, 20 % of the depth
    and +-20 % scale, with P = 2000 noise-free correspondences."""
    generator = torch.Generator().manual_seed(seed)
    T_kf = random_sim3(1, 10.0, 0.2 * MEAN_DEPTH, math.log(1.2), generator)
    truth = torch.cat([sim3_identity(1, dtype=torch.float64), T_kf])
    graph = synthetic_graph(truth, torch.tensor([0]), torch.tensor([1]), NUM_MATCHES, generator)
    return T_kf[0], graph, generator


def _errors(T_est: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float, float]:
    """Relative translation error, rotation error (rad), relative scale error."""
    T_est, T_true = T_est.to(torch.float64), T_true.to(torch.float64)
    translation = float((T_est[:3] - T_true[:3]).norm() / T_true[:3].norm())
    rotation = float(sim3_log(sim3_compose(T_est, sim3_inverse(T_true)))[3:6].norm())
    scale = float(abs(T_est[7] / T_true[7] - 1))
    return translation, rotation, scale


def _track(graph, dtype, X_j=None, config=None):
    factors = RayRangeFactors(
        graph.i,
        graph.j,
        graph.X_i.to(dtype),
        (graph.X_j if X_j is None else X_j).to(dtype),
        graph.q.to(dtype),
        graph.valid,
    )
    values = PoseValues.from_poses(sim3_identity(2, dtype=dtype), num_pinned=1)
    return levenberg_marquardt_irls(factors, values, config)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tracking_recovers_the_relative_pose(seed, dtype):
    T_true, graph, _ = _tracking_problem(seed, dtype)
    values, report = _track(graph, dtype)
    assert report.converged, report.reason
    assert all(error < 1e-3 for error in _errors(values.poses[1], T_true))
    assert torch.equal(values.poses[0], sim3_identity(dtype=dtype))  # the keyframe is pinned
    history = report.cost_history
    assert len(history) >= 2 and all(b < a for a, b in zip(history, history[1:]))
    assert report.initial_cost == history[0] and report.final_cost == history[-1]
    assert report.failed_solves == 0 and report.seconds > 0


def _rotate_about_centre(X: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Rotate points about the camera centre by 5-30 deg: a wrong pixel at the same range."""
    axis = torch.randn(*X.shape, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = math.radians(5) + math.radians(25) * torch.rand(
        *X.shape[:-1], 1, generator=generator, dtype=torch.float64
    )
    rotation = torch.cat([torch.zeros_like(axis), axis * angle, torch.zeros_like(angle)], -1)
    return sim3_act(sim3_exp(rotation), X)


@pytest.mark.parametrize("seed", [3, 4])
def test_tracking_with_20_percent_gross_ray_outliers(seed):
    """Outliers whose rays are off by 5-30 deg (whitened ray residuals of 30-170) are
    bounded by the Huber kernel; the estimate stays within 1e-2."""
    T_true, graph, generator = _tracking_problem(seed, torch.float64)
    outlier = torch.rand(graph.q.shape, generator=generator) < 0.2
    X_j = torch.where(outlier[..., None], _rotate_about_centre(graph.X_j, generator), graph.X_j)
    values, report = _track(graph, torch.float64, X_j)
    assert report.converged, report.reason
    assert all(error < 1e-2 for error in _errors(values.poses[1], T_true))


def test_tracking_rotation_survives_arbitrary_wrong_matches():
    """Outliers matched to random other points (wrong ray and range): the ray term keeps the
    rotation. (Their range residuals, below sigma_dist = 10 m, are not in the Huber tail,
    so the scale is not protected the same way; see the module report.)"""
    T_true, graph, generator = _tracking_problem(5, torch.float64)
    outlier = torch.rand(graph.q.shape, generator=generator) < 0.2
    shuffled = graph.X_i[:, torch.randperm(NUM_MATCHES, generator=generator)]
    values, report = _track(
        graph, torch.float64, torch.where(outlier[..., None], shuffled, graph.X_j)
    )
    assert report.converged, report.reason
    assert _errors(values.poses[1], T_true)[1] < 5e-3


def test_calibrated_tracking_recovers_the_relative_pose():
    T_true, graph, _ = _tracking_problem(6, torch.float64)
    K = torch.tensor([[400.0, 0, 256], [0, 400, 192], [0, 0, 1]], dtype=torch.float64)
    pixels = (K @ graph.X_i[..., None])[..., 0]
    factors = CalibratedFactors(
        graph.i,
        graph.j,
        graph.X_j,
        pixels[..., :2] / pixels[..., 2:],
        graph.X_i[..., 2],
        K,
        graph.q,
        graph.valid,
    )
    values = PoseValues.from_poses(sim3_identity(2, dtype=torch.float64))
    values, report = levenberg_marquardt_irls(factors, values)
    assert report.converged, report.reason
    assert all(error < 1e-3 for error in _errors(values.poses[1], T_true))


def _loop_graph(num_matches: int = 100):
    """6 poses: a chain 0-1-2-3-4-5, the loop 5-0 and a chord 1-4; noisy initial poses."""
    generator = torch.Generator().manual_seed(11)
    truth = chain_poses(6, generator)
    i = torch.tensor([0, 1, 2, 3, 4, 5, 1])
    j = torch.tensor([1, 2, 3, 4, 5, 0, 4])
    graph = synthetic_graph(truth, i, j, num_matches, generator)
    initial = sim3_compose(random_sim3(6, 3.0, 0.3, 0.05, generator), truth)
    initial[0] = truth[0]
    return truth, graph, PoseValues.from_poses(initial, num_pinned=1)


@pytest.mark.parametrize("backend", ["dense", "sparse", "pcg"])
def test_global_ba_converges_to_the_truth(backend):
    truth, graph, values = _loop_graph()
    # Two factor batches (e.g. intra- and inter-agent edges) assembled into one system.
    factors = [
        RayRangeFactors(
            graph.i[s], graph.j[s], graph.X_i[s], graph.X_j[s], graph.q[s], graph.valid[s]
        )
        for s in (slice(0, 5), slice(5, 7))
    ]
    result, report = gauss_newton_irls(factors, values, GlobalBAConfig(), backend=backend)
    assert report.converged and report.reason == "step_tol"
    assert report.cost_history == [] and not report.diverged and report.failed_solves == 0
    for k in range(6):
        assert all(error < 1e-7 for error in _errors(result.poses[k], truth[k])[1:])
        assert (result.poses[k, :3] - truth[k, :3]).norm() < 1e-7
    assert torch.equal(result.poses[0], values.poses[0])


def test_global_ba_backends_agree_iterate_by_iterate():
    _, graph, values = _loop_graph()
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i, graph.X_j, graph.q, graph.valid)
    dense, _ = gauss_newton_irls(factors, values, max_iters=2, backend="dense")
    sparse, _ = gauss_newton_irls(factors, values, max_iters=2, backend="sparse")
    torch.testing.assert_close(dense.poses, sparse.poses, rtol=0, atol=1e-9)


def test_gauss_newton_takes_its_limits_from_the_config():
    _, graph, values = _loop_graph()
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i, graph.X_j, graph.q, graph.valid)
    _, report = gauss_newton_irls(factors, values, LocalSolveConfig(max_iters=2))
    assert report.iterations == 2 and report.reason == "max_iters" and not report.converged
    _, report = gauss_newton_irls(factors, values, GlobalBAConfig(max_iters_stream=3))
    assert report.iterations == 3
    _, report = gauss_newton_irls(factors, values, GlobalBAConfig(), max_iters=1)
    assert report.iterations == 1


class _FixedLinearization:
    """A factor whose linearization and cost are given: drives the loops into corners."""

    def __init__(self, H_jj: torch.Tensor, g_j: torch.Tensor, cost=lambda poses: 1.0):
        self.H_jj, self.g_j, self._cost = H_jj, g_j, cost
        self.max_pose_index = 1

    def linearize(self, poses):
        zero_block = torch.zeros(1, 7, 7, dtype=torch.float64)
        return EdgeBlocks(
            torch.tensor([0]),
            torch.tensor([1]),
            zero_block,
            self.H_jj[None],
            zero_block,
            torch.zeros(1, 7, dtype=torch.float64),
            self.g_j[None],
        )

    def cost(self, poses):
        return torch.tensor(self._cost(poses), dtype=torch.float64)


def test_divergence_guard_keeps_the_previous_poses(caplog):
    step_too_large = torch.tensor([0.0, 0, 0, 4.0, 0, 0, 0], dtype=torch.float64)  # 4 rad
    factor = _FixedLinearization(torch.eye(7, dtype=torch.float64), -step_too_large)
    values = PoseValues.from_poses(sim3_identity(2, dtype=torch.float64))
    with caplog.at_level(logging.WARNING, logger="como3r.optim.optimizer"):
        result, report = gauss_newton_irls(factor, values)
    assert report.diverged and report.reason == "diverged" and not report.converged
    assert torch.equal(result.poses, values.poses)
    assert "refused" in caplog.text


def test_failed_linear_solve_is_reported_and_leaves_the_poses():
    H = torch.eye(7, dtype=torch.float64)
    H[2, 2] = float("nan")
    factor = _FixedLinearization(H, torch.ones(7, dtype=torch.float64))
    values = PoseValues.from_poses(sim3_identity(2, dtype=torch.float64))
    result, report = gauss_newton_irls(factor, values)
    assert report.reason == "solve_failed" and report.failed_solves == 1
    assert report.tikhonov_retries == LocalSolveConfig().tikhonov_retries
    assert not report.converged and torch.equal(result.poses, values.poses)


def test_levenberg_marquardt_gives_up_when_lambda_exceeds_its_maximum():
    """A linearization that points uphill: every step is rejected, lambda grows x10 each
    time from 1e-6 until it passes 1e3, and the initial poses are returned."""
    uphill = torch.ones(7, dtype=torch.float64)  # the true gradient of the cost is -uphill

    def cost(poses):
        return 10.0 - float(poses[1, :3].sum() + poses[1, 7])

    factor = _FixedLinearization(torch.eye(7, dtype=torch.float64), uphill, cost)
    values = PoseValues.from_poses(sim3_identity(2, dtype=torch.float64))
    result, report = levenberg_marquardt_irls(factor, values, step_tol=0.0)
    assert report.reason == "lambda_max" and not report.converged
    assert report.iterations == 10  # 1e-6 * 10^10 = 1e4 > 1e3
    assert report.final_lambda == pytest.approx(1e4)
    assert report.cost_history == [10.0 - 1.0]
    assert torch.equal(result.poses, values.poses)


def test_levenberg_marquardt_takes_its_defaults_from_the_tracking_config():
    _, graph, _ = _tracking_problem(0, torch.float64)
    _, report = _track(graph, torch.float64, config=TrackingConfig(max_iters=1))
    assert report.iterations == 1 and report.reason == "max_iters"


def test_optimizers_validate_the_problem():
    _, graph, values = _loop_graph()
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i, graph.X_j, graph.q, graph.valid)
    too_few = PoseValues.from_poses(values.poses[:4])
    with pytest.raises(InputError, match="refers to pose 5"):
        gauss_newton_irls(factors, too_few)
    with pytest.raises(InputError, match="no factors"):
        levenberg_marquardt_irls([], values)
    with pytest.raises(InputError, match="max_iters"):
        gauss_newton_irls(factors, values, max_iters=0)
    with pytest.raises(InputError, match="pinned"):
        PoseValues(values.poses, torch.zeros(3, dtype=torch.bool))


def test_pinned_poses_only_gives_an_immediate_result():
    _, graph, values = _loop_graph()
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i, graph.X_j, graph.q, graph.valid)
    all_pinned = PoseValues.from_poses(values.poses, num_pinned=6)
    result, report = gauss_newton_irls(factors, all_pinned)
    assert report.converged and report.reason == "no_free_poses"
    assert torch.equal(result.poses, values.poses)


def test_levenberg_marquardt_refuses_non_finite_initial_poses():
    _, graph, _ = _tracking_problem(0, torch.float64)
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i, graph.X_j, graph.q, graph.valid)
    poses = sim3_identity(2, dtype=torch.float64)
    poses[1, 0] = float("nan")
    result, report = levenberg_marquardt_irls(factors, PoseValues.from_poses(poses))
    assert report.reason == "non_finite_cost" and not report.converged
    assert report.iterations == 0 and torch.equal(result.poses[0], poses[0])


def _scaled_chain_problem(scale: float):
    """The loop graph of :func:`_loop_graph` with every length times ``scale``, as
    calibrated factors (pixels and log-depths do not change with the scale), and its noisy
    initial poses with their translations scaled too."""
    truth, graph, values = _loop_graph()
    K = torch.tensor([[400.0, 0, 256], [0, 400, 192], [0, 0, 1]], dtype=torch.float64)
    pixels = (K @ graph.X_i[..., None])[..., 0]
    factors = CalibratedFactors(
        graph.i,
        graph.j,
        scale * graph.X_j,
        pixels[..., :2] / pixels[..., 2:],
        scale * graph.X_i[..., 2],
        K,
        graph.q,
        graph.valid,
    )
    poses = values.poses.clone()
    poses[:, :3] *= scale
    return factors, PoseValues.from_poses(poses, num_pinned=1)


def test_step_tolerance_is_relative_to_the_scene_length() -> None:
    """The same problem at 100x the scale stops after as many iterations when the step's
    translation is measured in units of the scene length."""
    reports = []
    for scale in (1.0, 100.0):
        factor, values = _scaled_chain_problem(scale)
        _, report = gauss_newton_irls(
            factor, values, GlobalBAConfig(), max_iters=50, step_tol=1e-6, length_scale=scale
        )
        reports.append(report)
    assert reports[0].converged and reports[1].converged
    assert reports[0].iterations == reports[1].iterations
    factor, values = _scaled_chain_problem(100.0)
    _, absolute = gauss_newton_irls(factor, values, GlobalBAConfig(), max_iters=50, step_tol=1e-6)
    assert absolute.iterations > reports[1].iterations


def test_length_scale_must_be_positive() -> None:
    factor, values = _scaled_chain_problem(1.0)
    with pytest.raises(InputError, match="length_scale"):
        gauss_newton_irls(factor, values, length_scale=0.0)
    with pytest.raises(InputError, match="length_scale"):
        levenberg_marquardt_irls(factor, values, length_scale=-1.0)
