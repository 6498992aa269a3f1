"""Tests of como3r.geometry.residuals: residuals and analytic Jacobians (C-Eq. 6-11, 17-18)."""

from __future__ import annotations

import pytest
import torch
from torch.autograd.functional import jacobian

from como3r.geometry.camera import intrinsics_matrix, project
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse, sim3_retract
from como3r.geometry.residuals import (
    calibrated_residual,
    edge_jacobians,
    huber_weight,
    point_jacobian,
    psi,
    ray_range_residual,
)

F64 = torch.float64


def random_sim3(n: int, gen: torch.Generator, rotation: float = 0.3) -> torch.Tensor:
    tau = torch.randn(n, 7, dtype=F64, generator=gen)
    tau[:, :3] *= 0.2
    tau[:, 3:6] *= rotation
    tau[:, 6] *= 0.2
    return sim3_exp(tau)


def random_points(shape: tuple[int, ...], gen: torch.Generator) -> torch.Tensor:
    """Points in front of a camera: x, y in [-1, 1], z in [1, 3]."""
    X = 2.0 * torch.rand(*shape, 3, dtype=F64, generator=gen) - 1.0
    X[..., 2] = 2.0 + X[..., 2]
    return X


def relative_error(J: torch.Tensor, J_ref: torch.Tensor) -> float:
    return float((J - J_ref).norm() / J_ref.norm())


def tangent_jacobian(residual, T: torch.Tensor) -> torch.Tensor:
    """Autograd ``d residual(Exp(tau) T) / d tau`` at ``tau = 0``, shaped ``(..., rows, 7)``."""
    batch = T.shape[:-1]
    J = jacobian(lambda tau: residual(sim3_retract(tau, T)), T.new_zeros(*batch, 7), vectorize=True)
    # jacobian returns (*out_shape, *batch, 7); keep only the diagonal of the batch dims.
    out = J.shape[: J.ndim - len(batch) - 1]
    J = J.reshape(*out, batch.numel(), 7)
    index = torch.arange(batch.numel())
    J = J.movedim(-2, 0)[index, index] if len(batch) else J.squeeze(-2)
    return J


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(7)


def test_psi_is_unit_and_finite_at_origin(dtype, device, gen):
    x = torch.randn(100, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    torch.testing.assert_close(psi(x).norm(dim=-1), torch.ones(100, dtype=dtype, device=device))
    assert bool(torch.isfinite(psi(torch.zeros(3, dtype=dtype, device=device))).all())


def test_point_jacobian_matches_autograd(gen):
    x = torch.randn(20, 3, dtype=F64, generator=gen)
    J_ref = jacobian(lambda tau: sim3_act(sim3_exp(tau), x), torch.zeros(7, dtype=F64))
    assert relative_error(point_jacobian(x), J_ref) < 1e-12


def test_ray_range_residual_value(dtype, device, gen):
    T = random_sim3(1, gen)[0].to(dtype=dtype, device=device)
    X_j = random_points((50,), gen).to(dtype=dtype, device=device)
    X_i = random_points((50,), gen).to(dtype=dtype, device=device)
    e, J = ray_range_residual(T, X_j, X_i)
    x = sim3_act(T, X_j)
    assert e.shape == (50, 4) and J.shape == (50, 4, 7)
    torch.testing.assert_close(
        e[:, :3], x / x.norm(dim=-1, keepdim=True) - X_i / X_i.norm(dim=-1, keepdim=True)
    )
    torch.testing.assert_close(e[:, 3], x.norm(dim=-1) - X_i.norm(dim=-1))
    e_match, _ = ray_range_residual(T, X_j, x)
    assert float(e_match.abs().max()) < (1e-12 if dtype == F64 else 1e-5)


def test_ray_range_jacobian_matches_autograd_batched(gen):
    T = random_sim3(3, gen)
    X_j, X_i = random_points((3, 40), gen), random_points((3, 40), gen)
    e, J = ray_range_residual(T, X_j, X_i)
    J_ref = tangent_jacobian(lambda T_: ray_range_residual(T_, X_j, X_i)[0], T)
    assert J.shape == (3, 40, 4, 7)
    assert relative_error(J, J_ref) < 1e-6
    # Structural zeros of C-Eq. 10: scale moves points along rays, rotation keeps ranges.
    assert float(J[..., :3, 6].abs().max()) < 1e-15
    assert float(J[..., 3, 3:6].abs().max()) < 1e-15


def test_ray_range_jacobian_matches_finite_differences(gen):
    T = random_sim3(1, gen)[0]
    X_j, X_i = random_points((30,), gen), random_points((30,), gen)
    _, J = ray_range_residual(T, X_j, X_i)
    h = 1e-6
    columns = []
    for k in range(7):
        step = torch.zeros(7, dtype=F64)
        step[k] = h
        e_plus, _ = ray_range_residual(sim3_retract(step, T), X_j, X_i)
        e_minus, _ = ray_range_residual(sim3_retract(-step, T), X_j, X_i)
        columns.append((e_plus - e_minus) / (2 * h))
    assert relative_error(J, torch.stack(columns, dim=-1)) < 1e-6


def test_ray_range_residual_broadcasts_pose_over_batches(gen):
    T = random_sim3(1, gen)[0]
    X_j, X_i = random_points((2, 5, 10), gen), random_points((2, 5, 10), gen)
    e, J = ray_range_residual(T, X_j, X_i)
    assert e.shape == (2, 5, 10, 4) and J.shape == (2, 5, 10, 4, 7)
    e_flat, J_flat = ray_range_residual(T, X_j.reshape(-1, 3), X_i.reshape(-1, 3))
    torch.testing.assert_close(e.reshape(-1, 4), e_flat)
    torch.testing.assert_close(J.reshape(-1, 4, 7), J_flat)


def test_ray_range_residual_is_finite_at_origin(dtype):
    T = random_sim3(1, torch.Generator().manual_seed(0))[0].to(dtype)
    X = torch.zeros(4, 3, dtype=dtype)
    X_j = sim3_act(sim3_inverse(T), X)  # maps exactly to the origin of camera i
    e, J = ray_range_residual(T, X_j, X)
    assert bool(torch.isfinite(e).all()) and bool(torch.isfinite(J).all())


def test_calibrated_residual_value_and_zero_at_truth(dtype, device, gen):
    K = intrinsics_matrix(500.0, 480.0, 320.0, 240.0, dtype=dtype, device=device)
    T = random_sim3(1, gen)[0].to(dtype=dtype, device=device)
    X_j = random_points((60,), gen).to(dtype=dtype, device=device)
    x = sim3_act(T, X_j)
    p_i = project(x, K)
    e, J = calibrated_residual(T, X_j, p_i, x[:, 2], K)
    assert e.shape == (60, 3) and J.shape == (60, 3, 7)
    assert float(e.abs().max()) < (1e-9 if dtype == F64 else 1e-3)
    e_shifted, _ = calibrated_residual(T, X_j, p_i + 2.0, 0.5 * x[:, 2], K)
    torch.testing.assert_close(e_shifted[:, :2], torch.full_like(p_i, -2.0), rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(e_shifted[:, 2], torch.full_like(x[:, 2], 0.6931471805599453))


def test_calibrated_jacobian_matches_autograd_batched_intrinsics(gen):
    K = torch.stack(
        [
            intrinsics_matrix(500.0, 480.0, 320.0, 240.0, dtype=F64),
            intrinsics_matrix(300.0, 310.0, 160.0, 120.0, dtype=F64),
        ]
    )
    K[1, 0, 1] = 2.0  # a skew term is handled by the general form of C-Eq. 18
    T = random_sim3(2, gen)
    X_j = random_points((2, 25), gen)
    p_i = 100.0 * torch.rand(2, 25, 2, dtype=F64, generator=gen)
    z_i = 1.0 + torch.rand(2, 25, dtype=F64, generator=gen)
    _, J = calibrated_residual(T, X_j, p_i, z_i, K)
    J_ref = tangent_jacobian(lambda T_: calibrated_residual(T_, X_j, p_i, z_i, K)[0], T)
    assert J.shape == (2, 25, 3, 7)
    assert relative_error(J, J_ref) < 1e-6


def edge_residual(T_i: torch.Tensor, T_j: torch.Tensor, X_j, X_i) -> torch.Tensor:
    T_ij = sim3_compose(sim3_inverse(T_i), T_j)
    return ray_range_residual(T_ij, X_j, X_i)[0].reshape(-1)


def test_edge_jacobians_are_left_perturbation_derivatives(gen):
    T_i, T_j = (random_sim3(1, gen, rotation=1.0)[0] for _ in range(2))
    T_i[7] = 1.7  # a non-unit scale exercises the scale rows of the adjoint
    X_j, X_i = random_points((20,), gen), random_points((20,), gen)
    T_ij = sim3_compose(sim3_inverse(T_i), T_j)
    _, J_rel = ray_range_residual(T_ij, X_j, X_i)
    J_i, J_j = edge_jacobians(T_i, J_rel.reshape(-1, 7))
    zero = torch.zeros(7, dtype=F64)
    J_i_ref = jacobian(
        lambda tau: edge_residual(sim3_retract(tau, T_i), T_j, X_j, X_i), zero, vectorize=True
    )
    J_j_ref = jacobian(
        lambda tau: edge_residual(T_i, sim3_retract(tau, T_j), X_j, X_i), zero, vectorize=True
    )
    assert relative_error(J_i, J_i_ref) < 1e-6
    assert relative_error(J_j, J_j_ref) < 1e-6


def test_edge_jacobians_batched_over_edges(gen):
    T_i = random_sim3(4, gen, rotation=1.0)
    J_rel = torch.randn(4, 12, 7, dtype=F64, generator=gen)
    J_i, J_j = edge_jacobians(T_i, J_rel)
    assert J_i.shape == (4, 12, 7)
    for b in range(4):
        J_i_b, J_j_b = edge_jacobians(T_i[b], J_rel[b])
        torch.testing.assert_close(J_i[b], J_i_b)
        torch.testing.assert_close(J_j[b], J_j_b)
    torch.testing.assert_close(J_i, -J_j)


def test_huber_weight(dtype, device):
    r = torch.tensor([0.0, 0.5, -1.345, 2.69, -13.45], dtype=dtype, device=device)
    expected = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.1], dtype=dtype, device=device)
    torch.testing.assert_close(huber_weight(r, 1.345), expected)
    with pytest.raises(ValueError, match="breakpoint"):
        huber_weight(r, 0.0)
