"""Union-find gauge components and the gauge transforms of C-Sec. A.4."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from como3r.coordination.gauge import (
    GaugeComponents,
    edge_log_scale,
    residual_ratio,
    solve_gauge_transform,
    transport,
)
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse, sim3_log

EDGES = [(2, 3), (0, 1), (1, 3), (4, 5)]


@pytest.mark.parametrize("order", list(itertools.permutations(EDGES)))
def test_union_find_merges_in_any_order(order) -> None:
    gauges = GaugeComponents()
    for agent in range(7):
        gauges.add(agent)
    for a, b in order:
        anchor, moved = gauges.union(b, a)
        assert anchor < moved or anchor == moved
        assert gauges.find(a) == gauges.find(b) == anchor
    assert gauges.components() == [[0, 1, 2, 3], [4, 5], [6]]
    assert gauges.find(3) == 0 and gauges.find(5) == 4
    assert gauges.members(2) == [0, 1, 2, 3]


def test_union_keeps_the_component_with_the_lower_root() -> None:
    gauges = GaugeComponents()
    assert gauges.union(3, 2) == (2, 3)  # agents 2 and 3 meet first
    assert gauges.union(1, 0) == (0, 1)
    # agent 3 meets agent 1: the whole component {2, 3} joins agent 0's
    assert gauges.union(3, 1) == (0, 2)
    assert gauges.union(2, 0) == (0, 0)
    assert gauges.components() == [[0, 1, 2, 3]]
    assert not GaugeComponents().same(0, 1)


def _points(n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 3, generator=g) * torch.tensor([3.0, 1.0, 5.0]) + 4.0).to(dtype)


def test_umeyama_transport_recovers_a_known_sim3(dtype) -> None:
    T_true = sim3_exp(torch.tensor([1.0, -2.0, 0.5, 0.3, -0.2, 0.9, 0.4], dtype=dtype))
    x_moving = _points(500, dtype)
    x_anchor = sim3_act(T_true, x_moving)
    x_anchor = x_anchor + 0.01 * torch.randn(
        x_anchor.shape, generator=torch.Generator().manual_seed(1)
    ).to(dtype)
    x_anchor[:40] += 5.0  # occluded / mismatched pixels
    weights = torch.ones(500, dtype=dtype)
    identity = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1], dtype=dtype)
    transform = solve_gauge_transform(x_moving, x_anchor, weights, identity, identity, 64)
    assert transform.method == "umeyama"
    assert transform.correspondences < 500  # the outliers were dropped before the refit
    error = sim3_log(sim3_compose(transform.T, sim3_inverse(T_true)).double())
    assert float(error[3:6].norm()) < 2e-3
    assert abs(float(error[6])) < 2e-3
    assert float((transform.T[:3] - T_true[:3]).norm()) < 0.02
    assert transform.rmse < 0.05


def test_rigid_snap_below_the_minimum_correspondences(dtype) -> None:
    T_anchor = sim3_exp(torch.tensor([0.5, 0.1, 2.0, 0.0, 0.3, 0.0, 0.2], dtype=dtype))
    T_moving = sim3_exp(torch.tensor([-1.0, 0.0, 0.3, 0.1, 0.0, -0.4, -0.1], dtype=dtype))
    x = _points(63, dtype)
    transform = solve_gauge_transform(
        x, x + 1.0, torch.ones(63, dtype=dtype), T_moving, T_anchor, min_correspondences=64
    )
    assert transform.method == "rigid_snap"
    assert math.isnan(transform.rmse)
    # the moving endpoint lands exactly on the anchor endpoint (C-Sec. A.4)
    snapped = sim3_compose(transform.T, T_moving)
    assert torch.allclose(snapped, T_anchor, atol=1e-5)


def test_degenerate_points_fall_back_to_the_rigid_snap() -> None:
    line = torch.linspace(0, 1, 100)[:, None] * torch.tensor([1.0, 2.0, 3.0])
    identity = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1.0])
    transform = solve_gauge_transform(line, line, torch.ones(100), identity, identity, 64)
    assert transform.method == "rigid_snap"


def test_transport_left_multiplies_every_pose(dtype) -> None:
    T = sim3_exp(torch.tensor([0.2, 0.0, -0.1, 0.1, 0.2, 0.3, 0.5], dtype=dtype))
    poses = sim3_exp(torch.randn(5, 7, generator=torch.Generator().manual_seed(2)).to(dtype))
    moved = transport(T, poses)
    point = torch.tensor([0.3, -0.2, 1.0], dtype=dtype)
    for pose, new in zip(poses, moved):
        assert torch.allclose(sim3_act(new, point), sim3_act(T, sim3_act(pose, point)), atol=1e-5)


def test_residual_ratio_measures_relative_disagreement(dtype) -> None:
    x = _points(300, dtype)
    centre = torch.zeros(3, dtype=dtype)
    assert residual_ratio(x, x, centre) == 0.0
    rotation = sim3_exp(torch.tensor([0, 0, 0, 0, 0.1, 0, 0], dtype=dtype))  # 0.1 rad
    ratio = residual_ratio(x, sim3_act(rotation, x), centre)
    assert 0.05 < ratio < 0.1001
    assert math.isinf(residual_ratio(x[:0], x[:0], centre))


def test_edge_log_scale_measures_how_much_a_link_would_rescale_the_map() -> None:
    generator = torch.Generator().manual_seed(5)
    x = torch.randn(200, 3, generator=generator, dtype=torch.float64) * 2.0
    weights = torch.ones(200, dtype=torch.float64)
    T = sim3_exp(torch.tensor([0.5, -1.0, 2.0, 0.1, 0.2, -0.3, math.log(1.3)], dtype=torch.float64))
    assert edge_log_scale(x, sim3_act(T[None], x), weights, 64) == pytest.approx(
        math.log(1.3), abs=1e-6
    )
    assert edge_log_scale(x, x + 0.5, weights, 64) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(edge_log_scale(x[:10], x[:10], weights[:10], 64))
