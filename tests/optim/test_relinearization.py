"""Tests of como3r.optim.relinearization: dense edges linearized again past a threshold."""

from __future__ import annotations

import pytest
import torch

from como3r.config import GlobalBAConfig
from como3r.errors import InputError
from como3r.geometry.lie import sim3_compose, sim3_exp
from como3r.optim.match_factors import RayRangeFactors
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.relinearization import KEEP_DENSE_BYTES, EdgeModels, ThresholdRelinearized
from como3r.optim.synthetic import chain_poses, random_sim3, synthetic_graph
from como3r.optim.values import PoseValues

SCENE = 12.5  # the synthetic points are 5-20 units in front of their cameras


def _problem(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
    """A 6-pose chain with a loop and a chord; noisy initial poses, the first pinned."""
    generator = torch.Generator().manual_seed(11)
    truth = chain_poses(6, generator)
    i = torch.tensor([0, 1, 2, 3, 4, 5, 1])
    j = torch.tensor([1, 2, 3, 4, 5, 0, 4])
    graph = synthetic_graph(truth, i, j, 300, generator)
    # a little noise on the points of j, so the solution has residuals and Huber weights < 1
    X_j = graph.X_j + 0.05 * torch.randn(graph.X_j.shape, generator=generator, dtype=torch.float64)
    factors = RayRangeFactors(
        graph.i.to(device),
        graph.j.to(device),
        graph.X_i.to(device, dtype),
        X_j.to(device, dtype),
        graph.q.to(device, dtype),
        graph.valid.to(device),
    )
    initial = sim3_compose(random_sim3(6, 3.0, 0.3, 0.05, generator), truth)
    initial[0] = truth[0]
    return truth, factors, PoseValues.from_poses(initial.to(device), num_pinned=1)


def _lazy(
    factors: RayRangeFactors,
    tol: float,
    models: EdgeModels | None = None,
    stamps: list | None = None,
    keep_bytes: int = KEEP_DENSE_BYTES,
) -> ThresholdRelinearized:
    """The batch's edges through a relinearization threshold, built from ``factors``
    (edge positions = their rows), keyed by position."""
    E = factors.num_edges
    built = []

    def build(positions):
        built.append(list(positions))
        return [(factors, list(range(E)))]

    lazy = ThresholdRelinearized(
        factors.i,
        factors.j,
        list(range(E)),
        stamps or [0] * E,
        EdgeModels() if models is None else models,
        build,
        tol,
        SCENE,
        keep_bytes,
    )
    lazy.built = built
    return lazy


def _moved(poses: torch.Tensor, rows: list[int], size: float) -> torch.Tensor:
    """``poses`` with ``rows`` moved by a rotation of ``size`` radians."""
    moved = poses.clone()
    tau = torch.tensor([0.0, 0.0, 0.0, size, 0.0, 0.0, 0.0], dtype=poses.dtype)
    moved[rows] = sim3_compose(sim3_exp(tau).expand(len(rows), 8), poses[rows])
    return moved


def test_without_a_threshold_the_blocks_are_the_dense_ones() -> None:
    _, factors, values = _problem(torch.float64)
    lazy = _lazy(factors, 0.0)
    for poses in (values.poses, _moved(values.poses, [2], 1e-6), _moved(values.poses, [3], 0.1)):
        blocks, dense = lazy.linearize(poses), factors.linearize(poses)
        for name in ("H_ii", "H_jj", "H_ij", "g_i", "g_j"):
            assert torch.equal(getattr(blocks, name), getattr(dense, name))
    assert lazy.linearized == 3 * factors.num_edges


def test_only_edges_that_moved_past_the_threshold_are_linearized_again() -> None:
    _, factors, values = _problem()
    lazy = _lazy(factors, 1e-3)
    lazy.linearize(values.poses)
    assert lazy.linearized == factors.num_edges
    # pose 3 turned by 1e-4 rad: its edges' relative poses stay within the threshold
    lazy.linearize(_moved(values.poses, [3], 1e-4))
    assert lazy.linearized == factors.num_edges
    # by 1e-2 rad: its two chain edges (2-3, 3-4) are linearized again, the others not
    moved = _moved(values.poses, [3], 1e-2)
    blocks, dense = lazy.linearize(moved), factors.linearize(moved)
    assert lazy.linearized == factors.num_edges + 2
    torch.testing.assert_close(blocks.H_jj, dense.H_jj, rtol=0, atol=0)
    # the others' blocks come from their models: near the dense ones, not equal to them
    assert not torch.equal(blocks.g_j, dense.g_j)
    torch.testing.assert_close(blocks.g_j, dense.g_j, rtol=1e-2, atol=1e-3)


def test_the_energy_is_the_dense_one() -> None:
    _, factors, values = _problem()
    lazy = _lazy(factors, 1e-3)
    lazy.linearize(values.poses)
    moved = _moved(values.poses, [4], 1e-4)
    assert torch.equal(lazy.cost(moved), factors.cost(moved))


def test_a_solve_with_the_threshold_ends_where_the_dense_one_does() -> None:
    truth, factors, values = _problem()
    dense, dense_report = gauss_newton_irls([factors], values, GlobalBAConfig(), length_scale=SCENE)
    lazy = _lazy(factors, GlobalBAConfig().relinearize_tol)
    solved, report = gauss_newton_irls([lazy], values, GlobalBAConfig(), length_scale=SCENE)
    assert report.converged and dense_report.converged
    # 21 edge linearizations over the matches where the dense solve made 7 x 7
    assert lazy.linearized <= 0.6 * factors.num_edges * dense_report.iterations
    # 6e-4 of the scene from the dense solve's poses, 1.1e-3 from the truth (dense: 9e-4)
    assert float((solved.poses[:, :3] - dense.poses[:, :3]).norm(dim=-1).max()) < 1.2e-3 * SCENE
    assert float((solved.poses[:, :3] - truth[:, :3]).norm(dim=-1).max()) < 2.2e-3 * SCENE


def test_models_are_kept_between_solves_while_their_stamps_hold(device) -> None:
    _, factors, values = _problem(device=device)
    models = EdgeModels()
    first = _lazy(factors, 1e-3, models)
    first.linearize(values.poses)
    assert len(models) == factors.num_edges and first.built == [list(range(7))]
    # a later solve at the same poses: every edge from its model, no dense factors built
    again = _lazy(factors, 1e-3, models)
    blocks = again.linearize(values.poses)
    assert again.reused == factors.num_edges and again.linearized == 0 and again.built == []
    assert torch.equal(blocks.H_jj, factors.linearize(values.poses).H_jj)
    # edge 2's pointmaps changed (its stamp): only it is built and linearized again
    stamps = [0, 0, 1, 0, 0, 0, 0]
    changed = _lazy(factors, 1e-3, models, stamps)
    changed.linearize(values.poses)
    assert changed.reused == 6 and changed.linearized == 1 and changed.built == [[2]]


def test_factors_past_the_kept_bytes_are_built_again_with_the_same_result() -> None:
    """A solve that may keep no dense factors (``keep_bytes`` 0: a large map's) builds an
    edge's again each time it is linearized again, and ends where the keeping one does."""
    _, factors, values = _problem()
    config = GlobalBAConfig()
    keeping = _lazy(factors, config.relinearize_tol)
    thrifty = _lazy(factors, config.relinearize_tol, keep_bytes=0)
    kept, kept_report = gauss_newton_irls([keeping], values, config, length_scale=SCENE)
    solved, report = gauss_newton_irls([thrifty], values, config, length_scale=SCENE)
    assert torch.equal(solved.poses, kept.poses) and report.iterations == kept_report.iterations
    assert thrifty.linearized == keeping.linearized
    assert len(keeping.built) == 1  # built once, kept to the end
    # each edge built again for each of its linearizations over the matches, none kept
    assert sum(len(b) for b in thrifty.built) == thrifty.linearized > factors.num_edges
    assert thrifty._dense == {}
    assert torch.equal(thrifty.cost(solved.poses), keeping.cost(solved.poses))


@pytest.mark.parametrize("tol, length", [(-1e-3, 1.0), (1e-3, 0.0)])
def test_a_bad_threshold_is_refused(tol: float, length: float) -> None:
    _, factors, _ = _problem()
    with pytest.raises(InputError, match="ThresholdRelinearized"):
        ThresholdRelinearized(
            factors.i, factors.j, [0] * 7, [0] * 7, EdgeModels(), lambda p: [], tol, length
        )


def test_edges_without_a_key_or_stamp_each_are_refused() -> None:
    _, factors, _ = _problem()
    with pytest.raises(InputError, match="one entry per edge"):
        ThresholdRelinearized(
            factors.i, factors.j, [0] * 6, [0] * 7, EdgeModels(), lambda p: [], 1e-3, 1.0
        )
