"""Tests of como3r.geometry.umeyama: closed-form weighted Sim(3) fit (C-Eq. 14)."""

from __future__ import annotations

import math

import pytest
import torch

from como3r.errors import GeometryError
from como3r.geometry.lie import quat_to_matrix, sim3_act, sim3_exp, sim3_retract, sim3_to_matrix
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3

F64 = torch.float64


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(99)


def random_sim3(gen: torch.Generator) -> torch.Tensor:
    tau = torch.randn(7, dtype=F64, generator=gen)
    tau[3:6] *= 2.5 / tau[3:6].norm()  # a large rotation
    return sim3_exp(tau)


def test_recovers_random_sim3_exactly(dtype, device, gen):
    for _ in range(5):
        T = random_sim3(gen)
        src = 3.0 * torch.randn(100, 3, dtype=F64, generator=gen)
        dst = sim3_act(T, src)
        T_fit = umeyama_sim3(src.to(dtype=dtype, device=device), dst.to(dtype=dtype, device=device))
        assert T_fit.shape == (8,) and T_fit.dtype == dtype and T_fit.device.type == device.type
        atol = 1e-10 if dtype == F64 else 1e-4
        torch.testing.assert_close(
            sim3_to_matrix(T_fit.double().cpu()), sim3_to_matrix(T), rtol=0.0, atol=atol
        )


def test_rigid_fit_keeps_unit_scale(gen):
    T = random_sim3(gen)
    T[7] = 1.0
    src = torch.randn(50, 3, dtype=F64, generator=gen)
    T_fit = umeyama_sim3(src, 2.0 * sim3_act(T, src), with_scale=False)
    assert float(T_fit[7]) == 1.0
    T_scaled = umeyama_sim3(src, 2.0 * sim3_act(T, src))
    assert abs(float(T_scaled[7]) - 2.0) < 1e-10


def test_planar_points_are_not_degenerate(gen):
    T = random_sim3(gen)
    src = torch.randn(40, 3, dtype=F64, generator=gen)
    src[:, 2] = 0.0
    T_fit = umeyama_sim3(src, sim3_act(T, src))
    torch.testing.assert_close(sim3_to_matrix(T_fit), sim3_to_matrix(T), rtol=0.0, atol=1e-10)


def test_reflection_gives_best_proper_rotation(gen):
    src = torch.randn(60, 3, dtype=F64, generator=gen) * torch.tensor([3.0, 2.0, 1.0], dtype=F64)
    dst = src * torch.tensor([1.0, 1.0, -1.0], dtype=F64)  # a mirror image
    T_fit = umeyama_sim3(src, dst)
    R = quat_to_matrix(T_fit[3:7])
    assert abs(float(torch.linalg.det(R)) - 1.0) < 1e-12
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=F64))
    # Locally optimal among similarities: any small perturbation fits worse.
    best = umeyama_rmse(T_fit, src, dst)
    for _ in range(20):
        tau = 1e-3 * torch.randn(7, dtype=F64, generator=gen)
        assert umeyama_rmse(sim3_retract(tau, T_fit), src, dst) > best


def test_zero_weight_outliers_are_ignored(dtype, gen):
    T = random_sim3(gen)
    src = torch.randn(80, 3, dtype=F64, generator=gen)
    dst = sim3_act(T, src)
    dst[:20] += 5.0 * torch.randn(20, 3, dtype=F64, generator=gen)
    weights = torch.ones(80, dtype=F64)
    weights[:20] = 0.0
    T_fit = umeyama_sim3(src.to(dtype), dst.to(dtype), weights.to(dtype))
    atol = 1e-10 if dtype == F64 else 1e-4
    torch.testing.assert_close(
        sim3_to_matrix(T_fit.double()), sim3_to_matrix(T), rtol=0.0, atol=atol
    )
    assert umeyama_rmse(T_fit, src.to(dtype), dst.to(dtype), weights.to(dtype)) < 10 * atol
    assert umeyama_rmse(T_fit, src.to(dtype), dst.to(dtype)) > 1.0


def test_integer_weights_equal_repeated_points(gen):
    src = torch.randn(30, 3, dtype=F64, generator=gen)
    dst = sim3_act(random_sim3(gen), src) + 0.1 * torch.randn(30, 3, dtype=F64, generator=gen)
    counts = torch.randint(1, 4, (30,), generator=gen)
    weighted = umeyama_sim3(src, dst, counts.to(F64))
    repeated = umeyama_sim3(src.repeat_interleave(counts, 0), dst.repeat_interleave(counts, 0))
    torch.testing.assert_close(sim3_to_matrix(weighted), sim3_to_matrix(repeated))


def test_noisy_fit_has_expected_residual(gen):
    src = torch.randn(2000, 3, dtype=F64, generator=gen)
    noise = 0.01 * torch.randn(2000, 3, dtype=F64, generator=gen)
    dst = sim3_act(random_sim3(gen), src) + noise
    rmse = umeyama_rmse(umeyama_sim3(src, dst), src, dst)
    assert rmse <= float(noise.pow(2).sum(-1).mean().sqrt())
    assert rmse > 0.9 * 0.01 * math.sqrt(3)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("two_points", "at least 3"),
        ("collinear", "collinear"),
        ("collinear_far_from_origin", "collinear"),
        ("all_equal", "coincide"),
        ("dst_all_equal", "coincide"),
        ("nan", "finite"),
        ("inf", "finite"),
        ("shape_mismatch", "shape of src"),
        ("not_3d", r"shape \(N, 3\)"),
        ("zero_weights", "all weights are zero"),
        ("negative_weight", "non-negative"),
        ("two_positive_weights", "positive weight"),
        ("weight_shape", "weights must have shape"),
    ],
)
def test_rejects_degenerate_input(case, message, dtype, gen):
    src = torch.randn(10, 3, dtype=F64, generator=gen)
    dst = sim3_act(random_sim3(gen), src)
    weights = None
    direction = torch.tensor([0.3, -0.4, 0.5], dtype=F64)
    line = torch.linspace(-2, 2, 10, dtype=F64)[:, None] * direction
    if case == "two_points":
        src, dst = src[:2], dst[:2]
    elif case == "collinear":
        src = line
        dst = sim3_act(random_sim3(gen), src) + 0.01 * torch.randn(10, 3, dtype=F64, generator=gen)
    elif case == "collinear_far_from_origin":
        src = line + torch.tensor([100.0, 50.0, -70.0], dtype=F64)
        dst = sim3_act(random_sim3(gen), src)
    elif case == "all_equal":
        src = torch.full((10, 3), 0.1, dtype=F64)
    elif case == "dst_all_equal":
        dst = torch.full((10, 3), -0.7, dtype=F64)
    elif case == "nan":
        src[3, 1] = float("nan")
    elif case == "inf":
        dst[0, 0] = float("inf")
    elif case == "shape_mismatch":
        dst = dst[:9]
    elif case == "not_3d":
        src, dst = src[:, :2], dst[:, :2]
    elif case == "zero_weights":
        weights = torch.zeros(10, dtype=F64)
    elif case == "negative_weight":
        weights = torch.ones(10, dtype=F64)
        weights[4] = -1.0
    elif case == "two_positive_weights":
        weights = torch.zeros(10, dtype=F64)
        weights[:2] = 1.0
    elif case == "weight_shape":
        weights = torch.ones(9, dtype=F64)
    with pytest.raises(GeometryError, match=message):
        umeyama_sim3(src.to(dtype), dst.to(dtype), None if weights is None else weights.to(dtype))


def test_rmse_of_known_offset():
    src = torch.randn(10, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    T = sim3_exp(torch.zeros(7, dtype=F64))
    assert umeyama_rmse(T, src, src) == 0.0
    assert abs(umeyama_rmse(T, src, src + torch.tensor([0.0, 3.0, 4.0], dtype=F64)) - 5.0) < 1e-12


def test_batched_umeyama_matches_the_single_solver() -> None:
    from como3r.geometry.lie import quat_to_matrix, sim3_exp
    from como3r.geometry.umeyama import umeyama_sim3_batched

    g = torch.Generator().manual_seed(3)
    T = sim3_exp(torch.randn(4, 7, generator=g, dtype=torch.float64) * 0.5)
    src = torch.randn(4, 5, 3, generator=g, dtype=torch.float64)
    R_true = quat_to_matrix(T[:, 3:7])
    dst = T[:, 7, None, None] * (src @ R_true.transpose(1, 2)) + T[:, None, :3]
    R, t, s = umeyama_sim3_batched(src, dst)
    assert torch.allclose(R, R_true, atol=1e-10)
    assert torch.allclose(t, T[:, :3], atol=1e-10)
    assert torch.allclose(s, T[:, 7], atol=1e-10)
