"""The compiled linearization of C-Eq. 17 computes every match in float64, whatever the
inputs' dtype, and its vectorisable logarithm is within 2 ulp of the C library's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from numba import njit

from como3r.geometry.lie import sim3_act, sim3_exp
from como3r.geometry.residuals import calibrated_residual
from como3r.optim import cpu_kernels, cpu_loops

HUBER_K = 1.345


@njit(error_model="numpy")
def _logs(values: np.ndarray) -> np.ndarray:
    out = np.empty_like(values)
    cpu_loops._log(values, out, values.shape[0])
    return out


@pytest.mark.slow
def test_vectorisable_log_is_within_two_ulp_of_the_c_library() -> None:
    rng = np.random.default_rng(0)
    values = np.concatenate(
        [
            np.exp(rng.uniform(-700, 700, 200_000)),  # the whole normal range
            1 + rng.normal(0, 1e-3, 100_000),
            1 + rng.normal(0, 1e-12, 10_000),  # log near 0
            np.sqrt(2) * (1 + rng.normal(0, 1e-13, 10_000)),  # where the mantissa is halved
            2.0 ** np.arange(-1022, 1024).astype(float),
            [1.0, np.nextafter(1.0, 2), 0.5],
        ]
    )
    reference = np.array([math.log(v) for v in values])
    ulp = np.abs(_logs(values) - reference) / np.spacing(np.abs(reference))
    assert ulp.max() <= 2.0


def _calibrated_problem(dtype: torch.dtype, seed: int = 0):
    """Two edges of 5000 matches (some invalid, some behind camera i, a third beyond the
    Huber breakpoint): ``(T_ij, K, X_j, p_i, z_i, q, valid, inv_sigma)``."""
    gen = torch.Generator().manual_seed(seed)
    E, P = 2, 5000
    K = torch.tensor(
        [[[420.0, 0.3, 255.5], [0.0, 410.0, 191.5], [0.0, 0.0, 1.0]]] * E, dtype=torch.float64
    )
    K[1, 0, 0] = 380.0
    T_ij = sim3_exp(0.05 * torch.randn(E, 7, generator=gen, dtype=torch.float64))
    X_j = torch.randn(E, P, 3, generator=gen, dtype=torch.float64)
    X_j[..., 2] = X_j[..., 2].abs() * 2 + 0.5
    X_j[:, :40, 2] = -1.0  # behind camera i
    x = sim3_act(T_ij[:, None, :], X_j)
    p_i = (K[:, None, :2, :] @ x[..., None])[..., 0] / x[..., 2:]
    p_i = p_i + 2.0 * torch.randn(E, P, 2, generator=gen, dtype=torch.float64)
    z_i = x[..., 2].abs() * torch.exp(0.01 * torch.randn(E, P, generator=gen, dtype=torch.float64))
    q = torch.rand(E, P, generator=gen, dtype=torch.float64) + 0.5
    valid = torch.rand(E, P, generator=gen) > 0.1
    q = torch.where(valid, q, torch.zeros_like(q))
    inv_sigma = torch.tensor([[1.0, 1.0, 100.0]] * E, dtype=torch.float64)
    return (T_ij, K, X_j.to(dtype), p_i.to(dtype), z_i.to(dtype), q.to(dtype), valid, inv_sigma)


def _reference(T_ij, K, X_j, p_i, z_i, q, valid, inv_sigma):
    """H, g and the robust cost from the PyTorch residual (geometry.residuals) in float64 of
    the same values: Huber-weighted whitened components (C-Sec. A.1), matches behind camera i
    or nearer it than MIN_DEPTH_RATIO of their observed depth and invalid ones weightless."""
    X_j, p_i, z_i, q = (x.to(torch.float64) for x in (X_j, p_i, z_i, q))
    e, J = calibrated_residual(T_ij, X_j, p_i, z_i, K)
    in_front = sim3_act(T_ij[:, None, :], X_j)[..., 2] > cpu_loops.MIN_DEPTH_RATIO * z_i
    info = q.sqrt()[..., None] * inv_sigma[:, None, :] * (valid & in_front)[..., None]
    whitened = e * info
    w = HUBER_K / whitened.abs().clamp_min(HUBER_K) * info
    H = torch.einsum("epc,epca,epcb->eab", w * info, J, J)
    g = torch.einsum("epc,epca->ea", w * whitened, J)
    a = whitened.abs()
    cost = torch.where(a <= HUBER_K, 0.5 * a * a, HUBER_K * (a - 0.5 * HUBER_K)).sum()
    beyond = (a[info > 0] > HUBER_K).double().mean().item()
    return H, g, cost, beyond


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_calibrated_blocks_are_float64_sums_of_the_inputs(dtype) -> None:
    """float32 inputs (the front-end's pointmaps) are summed in float64: the blocks equal a
    float64 evaluation of the same values to 1e-12 (a float32 square root of the
    confidences made that 1e-9)."""
    args = _calibrated_problem(dtype)
    H, g = cpu_kernels.calibrated_blocks(*args, HUBER_K)
    H_ref, g_ref, cost_ref, beyond = _reference(*args)
    assert 0.1 < beyond < 0.9, "the problem must exercise both Huber regimes"
    torch.testing.assert_close(H, H_ref, rtol=0, atol=1e-12 * H_ref.abs().max().item())
    torch.testing.assert_close(g, g_ref, rtol=0, atol=1e-12 * g_ref.abs().max().item())
    torch.testing.assert_close(
        cpu_kernels.calibrated_costs(*args, HUBER_K).sum(), cost_ref, rtol=1e-12, atol=0
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_factor_batch_preparation_equals_pytorch(dtype) -> None:
    """The compiled validity tests and valid-first order give PyTorch's masks and indices:
    non-finite points, the camera centre, tiny points (whose float32 squares underflow)."""
    gen = torch.Generator().manual_seed(1)
    X = torch.randn(3, 500, 3, generator=gen).to(dtype)
    X[0, :5] = 0.0
    X[0, 5, 1] = float("nan")
    X[1, 7, 2] = float("inf")
    X[1, 8] = torch.tensor([1e-30, 0.0, 0.0], dtype=dtype)  # float32: norm 0
    X[1, 9] = torch.tensor([3e-23, 0.0, 0.0], dtype=dtype)  # float32: a subnormal norm
    X[2, 9] = torch.tensor([0.0, -0.0, 1e-170], dtype=dtype)
    usable = torch.isfinite(X).all(-1) & (torch.linalg.vector_norm(X, dim=-1) > 0)
    assert torch.equal(cpu_kernels.usable_points(X), usable)
    assert cpu_kernels.all_finite(X[2]) and not cpu_kernels.all_finite(X)
    q = X[..., 0].clone()
    q[2, :3] = torch.tensor([float("nan"), 0.0, float("-inf")])
    valid_in = torch.rand(3, 500, generator=gen) < 0.7
    confident = valid_in & torch.isfinite(q) & (q > 0)
    valid_out, q_out = cpu_kernels.confident(valid_in, q)
    assert torch.equal(valid_out, confident)
    assert torch.equal(q_out, torch.where(confident, q, torch.zeros_like(q)))
    z = X[..., 2].abs()
    z[1, :4] = torch.tensor([0.0, float("nan"), float("inf"), -1.0])
    assert torch.equal(
        cpu_kernels.observed(X[..., :2], z),
        torch.isfinite(X[..., :2]).all(-1) & torch.isfinite(z) & (z > 0),
    )
    valid = torch.rand(3, 500, generator=gen) < torch.tensor([[0.2], [0.9], [0.5]])
    order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices
    compiled_order, most = cpu_kernels.valid_first(valid)
    assert torch.equal(compiled_order, order) and most == int(valid.sum(1).max())
    for kept in (500, most, 1):
        for values in (X, valid, X[..., 2]):
            index = (
                order[:, :kept]
                .reshape(3, kept, *(1,) * (values.ndim - 2))
                .expand(3, kept, *values.shape[2:])
            )
            torch.testing.assert_close(
                cpu_kernels.take_matches(values, order, kept),
                torch.gather(values, 1, index),
                rtol=0,
                atol=0,
                equal_nan=True,
            )
