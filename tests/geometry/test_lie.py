"""Tests of como3r.geometry.lie: SO(3), SE(3), Sim(3) maps and group operations."""

from __future__ import annotations

import math

import pytest
import torch

from como3r.errors import GeometryError
from como3r.geometry.lie import (
    matrix_to_quat,
    quat_conjugate,
    quat_identity,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    se3_act,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_identity,
    se3_inverse,
    se3_log,
    se3_to_matrix,
    sim3_act,
    sim3_act_points,
    sim3_adjoint,
    sim3_compose,
    sim3_exp,
    sim3_from_matrix,
    sim3_from_se3,
    sim3_identity,
    sim3_inverse,
    sim3_log,
    sim3_normalize,
    sim3_retract,
    sim3_to_matrix,
    skew,
    so3_exp,
    so3_log,
)

F64 = torch.float64
# Angles and log-scales that exercise every branch of the closed forms: exact zero, deep in the
# series regimes, around the switch-over thresholds, generic and near pi.
TINY_MAGNITUDES = [1e-9, 1e-7, 1e-6, 1e-5, 1e-4]
ANGLES = [0.0, *TINY_MAGNITUDES, 3e-3, 1e-2, 0.3, 2.0, math.pi - 1e-3, math.pi - 1e-6]
ZETAS = [0.0, *TINY_MAGNITUDES, 0.05, 0.1, 0.7, -2.0]


def tol(dtype: torch.dtype) -> dict[str, float]:
    """Comparison tolerances for quantities of order one."""
    return {"rtol": 1e-10, "atol": 1e-12} if dtype == F64 else {"rtol": 1e-4, "atol": 2e-5}


def random_unit(n: int, gen: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, dtype=F64, generator=gen)
    return v / v.norm(dim=-1, keepdim=True)


def random_quat(n: int, gen: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, dtype=F64, generator=gen)
    return q / q.norm(dim=-1, keepdim=True)


def random_tau(n: int, gen: torch.Generator, max_angle: float = 3.0) -> torch.Tensor:
    """Random sim(3) vectors with rotation angles below ``max_angle`` and |zeta| < 1."""
    v = torch.randn(n, 3, dtype=F64, generator=gen)
    angle = max_angle * torch.rand(n, 1, dtype=F64, generator=gen)
    zeta = 2.0 * torch.rand(n, 1, dtype=F64, generator=gen) - 1.0
    return torch.cat([v, random_unit(n, gen) * angle, zeta], dim=-1)


def random_sim3(n: int, gen: torch.Generator) -> torch.Tensor:
    t = torch.randn(n, 3, dtype=F64, generator=gen)
    s = torch.exp(torch.randn(n, 1, dtype=F64, generator=gen))
    return torch.cat([t, random_quat(n, gen), s], dim=-1)


def regime_tau(gen: torch.Generator) -> torch.Tensor:
    """One random sim(3) vector per (angle, zeta) pair of the regime grid, ``(len*len, 7)``."""
    angle = torch.tensor(ANGLES, dtype=F64).repeat_interleave(len(ZETAS))[:, None]
    zeta = torch.tensor(ZETAS, dtype=F64).repeat(len(ANGLES))[:, None]
    n = angle.shape[0]
    sign = torch.where(torch.rand(n, 1, generator=gen) < 0.5, -1.0, 1.0).to(F64)
    v = torch.randn(n, 3, dtype=F64, generator=gen)
    return torch.cat([v, random_unit(n, gen) * angle, sign * zeta], dim=-1)


def algebra_matrix(tau: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` matrix ``[[zeta I + [omega]_x, v], [0, 0]]`` of a sim(3) vector."""
    M = tau.new_zeros(*tau.shape[:-1], 4, 4)
    M[..., :3, :3] = tau[..., 6, None, None] * torch.eye(3, dtype=tau.dtype) + skew(tau[..., 3:6])
    M[..., :3, 3] = tau[..., :3]
    return M


def same_rotation(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """``1 - |<q1, q2>|``: zero iff the quaternions encode the same rotation."""
    return 1.0 - (q1 * q2).sum(-1).abs()


@pytest.fixture
def gen() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


# ------------------------------------------------------------------------------------------
# SO(3)
# ------------------------------------------------------------------------------------------


def test_skew_is_cross_product(dtype, device, gen):
    a, b = torch.randn(2, 50, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    expected = torch.linalg.cross(a, b, dim=-1)
    torch.testing.assert_close((skew(a) @ b[..., None])[..., 0], expected, **tol(dtype))


def test_quaternion_algebra_matches_matrices(dtype, device, gen):
    q1, q2 = (random_quat(100, gen).to(dtype=dtype, device=device) for _ in range(2))
    x = torch.randn(100, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    R1, R2 = quat_to_matrix(q1), quat_to_matrix(q2)
    eye = torch.eye(3, dtype=dtype, device=device).expand(100, 3, 3)
    torch.testing.assert_close(R1 @ R1.transpose(-1, -2), eye, **tol(dtype))
    torch.testing.assert_close(
        torch.linalg.det(R1), torch.ones(100, dtype=dtype, device=device), **tol(dtype)
    )
    torch.testing.assert_close(quat_to_matrix(quat_multiply(q1, q2)), R1 @ R2, **tol(dtype))
    torch.testing.assert_close(quat_rotate(q1, x), (R1 @ x[..., None])[..., 0], **tol(dtype))
    torch.testing.assert_close(
        quat_multiply(q1, quat_conjugate(q1)),
        quat_identity(100, dtype=dtype, device=device),
        **tol(dtype),
    )


def test_matrix_to_quat_round_trip(dtype, device, gen):
    q = random_quat(500, gen).to(dtype=dtype, device=device)
    q_back = matrix_to_quat(quat_to_matrix(q))
    assert bool((q_back[..., 3] >= 0).all())
    assert float(same_rotation(q, q_back).abs().max()) < (1e-12 if dtype == F64 else 1e-6)


@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 1)])
def test_matrix_to_quat_half_turns(axis, dtype, device):
    n = torch.tensor(axis, dtype=dtype, device=device)
    n = n / n.norm()
    R = 2.0 * torch.outer(n, n) - torch.eye(3, dtype=dtype, device=device)  # 180 deg about n
    q = matrix_to_quat(R)
    torch.testing.assert_close(quat_to_matrix(q), R, **tol(dtype))
    assert float(q[3].abs()) < 1e-6
    assert float(same_rotation(q, torch.cat([n, n.new_zeros(1)]))) < 1e-6


def test_so3_exp_matches_matrix_exponential(gen):
    phi = random_unit(200, gen) * (math.pi * torch.rand(200, 1, dtype=F64, generator=gen))
    torch.testing.assert_close(
        quat_to_matrix(so3_exp(phi)), torch.linalg.matrix_exp(skew(phi)), rtol=1e-12, atol=1e-13
    )


@pytest.mark.parametrize("angle", [0.0, *TINY_MAGNITUDES, 0.5, 2.0, math.pi - 1e-6, math.pi - 1e-9])
def test_so3_log_exp_round_trip(angle, dtype, device, gen):
    phi = (random_unit(64, gen) * angle).to(dtype=dtype, device=device)
    if dtype == F64:
        torch.testing.assert_close(so3_log(so3_exp(phi)), phi, rtol=1e-9, atol=1e-15)
    elif angle < 3.0:
        torch.testing.assert_close(so3_log(so3_exp(phi)), phi, rtol=1e-5, atol=1e-6)
    else:
        # float32 rounds pi - 1e-9 to just above pi, where log rightly returns the other side.
        torch.testing.assert_close(
            quat_to_matrix(so3_exp(so3_log(so3_exp(phi)))),
            quat_to_matrix(so3_exp(phi)),
            rtol=1e-5,
            atol=1e-5,
        )


def test_so3_log_is_sign_invariant_with_angle_in_zero_pi(dtype, device, gen):
    q = random_quat(500, gen).to(dtype=dtype, device=device)
    phi = so3_log(q)
    torch.testing.assert_close(so3_log(-q), phi, **tol(dtype))
    angle = phi.norm(dim=-1)
    assert bool((angle >= 0).all()) and bool((angle <= math.pi + 1e-6).all())
    assert float(same_rotation(so3_exp(phi), q).abs().max()) < (1e-12 if dtype == F64 else 1e-6)


def test_so3_exp_log_at_exactly_pi(dtype, device):
    phi = torch.tensor(
        [[math.pi, 0, 0], [0, math.pi, 0], [0, 0, -math.pi]], dtype=dtype, device=device
    )
    phi_back = so3_log(so3_exp(phi))
    torch.testing.assert_close(phi_back.norm(dim=-1), phi.norm(dim=-1), **tol(dtype))
    torch.testing.assert_close(
        quat_to_matrix(so3_exp(phi_back)), quat_to_matrix(so3_exp(phi)), **tol(dtype)
    )


def test_so3_maps_have_exact_gradients_at_identity():
    phi = torch.zeros(3, dtype=F64)
    J_exp = torch.autograd.functional.jacobian(so3_exp, phi)
    torch.testing.assert_close(
        J_exp, torch.cat([0.5 * torch.eye(3, dtype=F64), torch.zeros(1, 3, dtype=F64)])
    )
    J_log = torch.autograd.functional.jacobian(so3_log, quat_identity(dtype=F64))
    torch.testing.assert_close(J_log[:, :3], 2.0 * torch.eye(3, dtype=F64))


# ------------------------------------------------------------------------------------------
# SE(3)
# ------------------------------------------------------------------------------------------


def test_se3_exp_matches_matrix_exponential(gen):
    xi = regime_tau(gen)[:, :6]
    reference = torch.linalg.matrix_exp(algebra_matrix(torch.cat([xi, xi[:, :1] * 0], -1)))
    torch.testing.assert_close(se3_to_matrix(se3_exp(xi)), reference, rtol=1e-12, atol=1e-12)


def test_se3_log_exp_round_trip(dtype, device, gen):
    xi = torch.cat([regime_tau(gen)[:, :6], random_tau(300, gen)[:, :6]])
    xi = xi.to(dtype=dtype, device=device)
    rtol, atol = (1e-9, 1e-12) if dtype == F64 else (1e-4, 1e-5)
    torch.testing.assert_close(se3_log(se3_exp(xi)), xi, rtol=rtol, atol=atol)


def test_se3_group_operations(dtype, device, gen):
    A, B = (se3_exp(random_tau(50, gen)[:, :6]).to(dtype=dtype, device=device) for _ in range(2))
    x = torch.randn(50, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    M_A, M_B = se3_to_matrix(A), se3_to_matrix(B)
    torch.testing.assert_close(se3_to_matrix(se3_compose(A, B)), M_A @ M_B, **tol(dtype))
    torch.testing.assert_close(se3_to_matrix(se3_inverse(A)), torch.linalg.inv(M_A), **tol(dtype))
    torch.testing.assert_close(
        se3_act(A, x), (M_A[:, :3, :3] @ x[..., None])[..., 0] + A[:, :3], **tol(dtype)
    )
    identity = se3_to_matrix(se3_identity(50, dtype=dtype, device=device))
    torch.testing.assert_close(
        se3_to_matrix(se3_compose(A, se3_inverse(A))), identity, **tol(dtype)
    )


def test_se3_adjoint_identity(gen):
    T = se3_exp(random_tau(50, gen)[:, :6])
    xi = 0.3 * torch.randn(50, 6, dtype=F64, generator=gen)
    lhs = se3_compose(se3_compose(T, se3_exp(xi)), se3_inverse(T))
    rhs = se3_exp((se3_adjoint(T) @ xi[..., None])[..., 0])
    torch.testing.assert_close(se3_to_matrix(lhs), se3_to_matrix(rhs), rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------
# Sim(3)
# ------------------------------------------------------------------------------------------


def test_sim3_exp_matches_matrix_exponential_in_every_regime(gen):
    tau = torch.cat([regime_tau(gen), random_tau(200, gen)])
    reference = torch.linalg.matrix_exp(algebra_matrix(tau))
    torch.testing.assert_close(sim3_to_matrix(sim3_exp(tau)), reference, rtol=1e-12, atol=1e-12)


def test_sim3_exp_float32_matches_float64(device, gen):
    tau = torch.cat([regime_tau(gen), random_tau(200, gen)])
    T32 = sim3_exp(tau.to(torch.float32).to(device)).double().cpu()
    T64 = sim3_exp(tau.to(torch.float32).double())
    torch.testing.assert_close(sim3_to_matrix(T32), sim3_to_matrix(T64), rtol=1e-5, atol=1e-6)


def test_sim3_log_exp_round_trip_in_every_regime(dtype, device, gen):
    tau = torch.cat([regime_tau(gen), random_tau(300, gen)]).to(dtype=dtype, device=device)
    # float64 scale is stored as s = e^zeta, so zeta carries an absolute error of one ulp of 1.
    rtol, atol = (1e-9, 1e-13) if dtype == F64 else (1e-4, 2e-5)
    torch.testing.assert_close(sim3_log(sim3_exp(tau)), tau, rtol=rtol, atol=atol)


@pytest.mark.parametrize("magnitude", TINY_MAGNITUDES)
def test_sim3_log_exp_round_trip_near_zero_is_relative(magnitude, dtype, device, gen):
    """Tiny tangent vectors come back with small *relative* error (no absolute noise floor)."""
    tau = magnitude * torch.randn(64, 7, dtype=F64, generator=gen)
    tau = tau.to(dtype=dtype, device=device)
    back = sim3_log(sim3_exp(tau))
    rtol = 1e-9 if dtype == F64 else 1e-4
    torch.testing.assert_close(back[:, :6], tau[:, :6], rtol=rtol, atol=magnitude * rtol)
    # zeta goes through s = exp(zeta), whose resolution is one ulp of 1.
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(back[:, 6], tau[:, 6], rtol=0.0, atol=4 * eps)


@pytest.mark.parametrize("gap", [1e-3, 1e-6, 1e-9])
def test_sim3_log_exp_round_trip_near_pi(gap, dtype, device, gen):
    tau = random_tau(64, gen)
    tau[:, 3:6] = random_unit(64, gen) * (math.pi - gap)
    tau = tau.to(dtype=dtype, device=device)
    if dtype == F64:
        torch.testing.assert_close(sim3_log(sim3_exp(tau)), tau, rtol=1e-8, atol=1e-9)
    else:
        # In float32 the angle is resolved to ~1e-7 near pi, so compare as group elements.
        torch.testing.assert_close(
            sim3_to_matrix(sim3_exp(sim3_log(sim3_exp(tau)))),
            sim3_to_matrix(sim3_exp(tau)),
            rtol=1e-4,
            atol=1e-4,
        )


def test_sim3_exp_log_round_trip(dtype, device, gen):
    T = random_sim3(300, gen)
    T[:5, 3:7] = torch.tensor(
        [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, -1], [0.6, 0, 0.8, 0]], dtype=F64
    )  # half turns and -identity
    T = T.to(dtype=dtype, device=device)
    back = sim3_exp(sim3_log(T))
    torch.testing.assert_close(sim3_to_matrix(back), sim3_to_matrix(T), **tol(dtype))
    angle = sim3_log(T)[:, 3:6].norm(dim=-1)
    assert bool((angle <= math.pi + 1e-6).all())


def test_sim3_exp_has_exact_gradient_at_zero():
    J = torch.autograd.functional.jacobian(sim3_exp, torch.zeros(7, dtype=F64))
    expected = torch.zeros(8, 7, dtype=F64)
    expected[:3, :3] = torch.eye(3, dtype=F64)
    expected[3:6, 3:6] = 0.5 * torch.eye(3, dtype=F64)
    expected[7, 6] = 1.0
    torch.testing.assert_close(J, expected)


def test_sim3_adjoint_identity(dtype, device, gen):
    T = random_sim3(100, gen).to(dtype=dtype, device=device)
    xi = (0.3 * torch.randn(100, 7, dtype=F64, generator=gen)).to(dtype=dtype, device=device)
    lhs = sim3_compose(sim3_compose(T, sim3_exp(xi)), sim3_inverse(T))
    rhs = sim3_exp((sim3_adjoint(T) @ xi[..., None])[..., 0])
    torch.testing.assert_close(sim3_to_matrix(lhs), sim3_to_matrix(rhs), **tol(dtype))


def test_sim3_compose_inverse_identities(dtype, device, gen):
    A, B, C = (random_sim3(100, gen).to(dtype=dtype, device=device) for _ in range(3))
    identity = sim3_identity(100, dtype=dtype, device=device)
    M = sim3_to_matrix
    torch.testing.assert_close(M(sim3_compose(A, sim3_inverse(A))), M(identity), **tol(dtype))
    torch.testing.assert_close(M(sim3_compose(sim3_inverse(A), A)), M(identity), **tol(dtype))
    torch.testing.assert_close(M(sim3_compose(A, identity)), M(A), **tol(dtype))
    torch.testing.assert_close(
        M(sim3_compose(sim3_compose(A, B), C)), M(sim3_compose(A, sim3_compose(B, C))), **tol(dtype)
    )
    torch.testing.assert_close(
        M(sim3_inverse(sim3_compose(A, B))),
        M(sim3_compose(sim3_inverse(B), sim3_inverse(A))),
        **tol(dtype),
    )
    torch.testing.assert_close(M(sim3_compose(A, B)), M(A) @ M(B), **tol(dtype))
    torch.testing.assert_close(M(sim3_inverse(A)), torch.linalg.inv(M(A)), **tol(dtype))


def test_sim3_act_matches_homogeneous_matrices_and_broadcasts(dtype, device, gen):
    T = random_sim3(4, gen).to(dtype=dtype, device=device)
    X = torch.randn(4, 25, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    M = sim3_to_matrix(T)
    expected = (M[:, None, :3, :3] @ X[..., None])[..., 0] + M[:, None, :3, 3]
    torch.testing.assert_close(sim3_act(T[:, None, :], X), expected, **tol(dtype))
    A, B = T[0], T[1]
    torch.testing.assert_close(
        sim3_act(sim3_compose(A, B), X), sim3_act(A, sim3_act(B, X)), **tol(dtype)
    )


def test_sim3_act_points_agrees_with_sim3_act(dtype, device, gen):
    T = random_sim3(1, gen)[0].to(dtype=dtype, device=device)
    X = torch.randn(1000, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    out = sim3_act_points(T.double(), X)  # T's dtype follows the points'
    assert out.dtype == dtype and out.shape == (1000, 3)
    torch.testing.assert_close(out, sim3_act(T, X), **tol(dtype))


def test_sim3_matrix_round_trip(dtype, device, gen):
    T = random_sim3(100, gen).to(dtype=dtype, device=device)
    T_back = sim3_from_matrix(sim3_to_matrix(T))
    torch.testing.assert_close(sim3_to_matrix(T_back), sim3_to_matrix(T), **tol(dtype))
    torch.testing.assert_close(T_back[:, 7], T[:, 7], **tol(dtype))


def test_sim3_from_matrix_rejects_reflections():
    M = torch.eye(4, dtype=F64)
    M[2, 2] = -1.0
    with pytest.raises(GeometryError, match="positive determinant"):
        sim3_from_matrix(M)


def test_sim3_retract_is_left_multiplication(gen):
    T = random_sim3(20, gen)
    tau = 0.2 * torch.randn(20, 7, dtype=F64, generator=gen)
    expected = sim3_to_matrix(sim3_exp(tau)) @ sim3_to_matrix(T)
    torch.testing.assert_close(sim3_to_matrix(sim3_retract(tau, T)), expected)


def test_sim3_from_se3_and_normalize(dtype, device, gen):
    T7 = se3_exp(random_tau(10, gen)[:, :6]).to(dtype=dtype, device=device)
    x = torch.randn(10, 3, dtype=F64, generator=gen).to(dtype=dtype, device=device)
    torch.testing.assert_close(sim3_act(sim3_from_se3(T7), x), se3_act(T7, x), **tol(dtype))
    scale = torch.full((10,), 2.5, dtype=dtype, device=device)
    torch.testing.assert_close(
        sim3_act(sim3_from_se3(T7, scale), x),
        2.5 * quat_rotate(T7[:, 3:], x) + T7[:, :3],
        **tol(dtype),
    )
    assert bool((sim3_from_se3(T7, 3.0)[:, 7] == 3.0).all())
    drifted = sim3_from_se3(T7).clone()
    drifted[:, 3:7] *= 1.01
    normalized = sim3_normalize(drifted)
    torch.testing.assert_close(
        normalized[:, 3:7].norm(dim=-1), torch.ones(10, dtype=dtype, device=device), **tol(dtype)
    )
    torch.testing.assert_close(normalized, sim3_from_se3(T7), **tol(dtype))


def test_identities_have_expected_layout(dtype, device):
    identity = sim3_identity(2, 3, dtype=dtype, device=device)
    assert identity.shape == (2, 3, 8) and identity.dtype == dtype
    torch.testing.assert_close(sim3_log(identity), identity.new_zeros(2, 3, 7))
    torch.testing.assert_close(
        se3_log(se3_identity(5, dtype=dtype, device=device)),
        torch.zeros(5, 6, dtype=dtype, device=device),
    )


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match="tau must have shape"):
        sim3_exp(torch.zeros(6))
    with pytest.raises(ValueError, match="T must have shape"):
        sim3_act(torch.zeros(7), torch.zeros(3))


def test_sim3_exp_and_log_of_a_row_do_not_depend_on_the_regimes_of_the_others(gen):
    # the left Jacobian skips a side of a torch.where that no row of the batch takes: a row
    # must come out bit for bit the same in a batch of its own regime as among all regimes
    tau = torch.cat([regime_tau(gen), torch.zeros(2, 7, dtype=F64)])
    together, logs = sim3_exp(tau), sim3_log(sim3_exp(tau))
    for k in range(tau.shape[0]):
        assert torch.equal(sim3_exp(tau[k : k + 1])[0], together[k])
        assert torch.equal(sim3_log(together[k : k + 1])[0], logs[k])
