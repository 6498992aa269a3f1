"""Per-match residuals with analytic Jacobians on Sim(3) (C-Sec. A.1, A.2, A.5).

All Jacobians are with respect to the left perturbation ``T <- Exp(tau) T`` with
``tau = (v, omega, zeta)`` (C-Sec. 3.2). Degenerate inputs (points at the camera centre, points
with non-positive depth in the calibrated residual) give finite but meaningless values from a
clamped norm / depth; callers mask them out (their IRLS weight is set to zero), which would be
impossible with NaNs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from como3r.geometry.lie import quat_to_matrix, sim3_adjoint, sim3_inverse, skew

__all__ = [
    "psi",
    "point_jacobian",
    "ray_range_error",
    "ray_range_terms",
    "ray_range_residual",
    "calibrated_residual",
    "edge_jacobians",
    "huber_weight",
]

# Norms and depths are clamped to this before dividing (finite in float32: 1 / 1e-12 = 1e12).
_MIN_NORM = 1e-12


def _norm(x: Tensor) -> Tensor:
    return x.norm(dim=-1).clamp_min(_MIN_NORM)


def psi(x: Tensor) -> Tensor:
    """Unit ray ``psi(x) = x / ||x||`` (C-Eq. 1). ``x``: ``(..., 3)`` -> ``(..., 3)``."""
    return x / _norm(x)[..., None]


def point_jacobian(x: Tensor) -> Tensor:
    """``D(Exp(tau) x) / D tau`` at ``tau = 0``: ``[I, -[x]_x, x]`` (C-Eq. 9).

    Args:
        x: ``(..., 3)`` transformed points ``x = T X``.

    Returns:
        ``(..., 3, 7)``.
    """
    eye = torch.eye(3, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], 3, 3)
    return torch.cat([eye, -skew(x), x[..., None]], dim=-1)


def _transform_matches(T_ij: Tensor, X_j: Tensor) -> Tensor:
    """``T_ij X_j`` with ``T_ij``'s batch dims broadcast against ``X_j``'s dims before N.

    One ``s R`` matrix per pose and a matrix product over the N points: the same
    ``s R x + t`` as :func:`~como3r.geometry.lie.sim3_act`, a few times faster for the many
    points of a dense edge than rotating each point by the quaternion.
    """
    dtype = torch.promote_types(T_ij.dtype, X_j.dtype)  # as sim3_act's broadcasting
    T = T_ij.to(dtype)
    sR = T[..., 7:, None] * quat_to_matrix(T[..., 3:7])
    return X_j.to(dtype) @ sR.transpose(-1, -2) + T[..., None, :3]


def _jacobian_buffer(like: Tensor, components: int) -> Tensor:
    """An uninitialised Jacobian ``(..., N, components, 7)`` for the matches of ``like``
    ``(..., N, 3)``, stored component-major: a view of a contiguous
    ``(..., 7, components, N)`` buffer.

    Every entry ``J[..., c, k]`` is written for all N matches at once, which in this layout
    is one contiguous row instead of a stride-``7 * components`` scatter, and the factors'
    ``J^T W J`` reads it as a ``(7, components * N)`` matrix without a copy
    (:meth:`como3r.optim.factors.RelativePoseFactors.linearize`). 512x384 local solve: the
    strided writes were 31 % of its time.
    """
    *batch, n, _ = like.shape
    buffer = like.new_empty(*batch, 7, components, n)
    nb = len(batch)
    return buffer.permute(*range(nb), nb + 2, nb + 1, nb)


def ray_range_error(T_ij: Tensor, X_j: Tensor, X_i: Tensor) -> Tensor:
    """Ray-and-range residual of C-Eq. 6 without its Jacobian (for cost evaluations).

    Args:
        T_ij, X_j, X_i: as in :func:`ray_range_residual`.

    Returns:
        ``e``: ``(..., N, 4)`` = ``[psi(T X_j) - psi(X_i); ||T X_j|| - ||X_i||]``.
    """
    return ray_range_terms(T_ij, X_j, X_i)[2]


def ray_range_terms(T_ij: Tensor, X_j: Tensor, X_i: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The pieces of C-Eq. 6 its Jacobian is made of (see :func:`ray_range_residual`).

    Args:
        T_ij, X_j, X_i: as in :func:`ray_range_residual`.

    Returns:
        ``d = ||T X_j||`` ``(..., N)``, ``r = T X_j / d`` ``(..., N, 3)`` and the residual
        ``e`` ``(..., N, 4)``.
    """
    x = _transform_matches(T_ij, X_j)
    d = _norm(x)
    r = x / d[..., None]
    d_i = _norm(X_i)
    e = torch.cat([r - X_i / d_i[..., None], (d - d_i)[..., None]], dim=-1)
    return d, r, e


def ray_range_residual(T_ij: Tensor, X_j: Tensor, X_i: Tensor) -> tuple[Tensor, Tensor]:
    """Ray-and-range residual of C-Eq. 6 and its Jacobian (C-Eq. 9-10).

    ``e = [psi(T X_j) - psi(X_i); ||T X_j|| - ||X_i||]``. With ``x = T X_j``, ``d = ||x||`` and
    ``r = x / d`` the chain rule of C-Eq. 10 through C-Eq. 9 simplifies, because
    ``(I - r r^T) x = 0`` and ``r^T [x]_x = 0``, to

        d e_psi / d tau = [(I - r r^T) / d,  -[r]_x,  0],
        d e_d   / d tau = [r^T,              0,       d]:

    a scale change moves points along their rays and a rotation keeps their range.

    Args:
        T_ij: ``(..., 8)`` pose of camera j in camera i.
        X_j: ``(..., N, 3)`` points in camera j.
        X_i: ``(..., N, 3)`` matched points in camera i. All batch dims broadcast.

    Returns:
        ``e``: ``(..., N, 4)``; ``J``: ``(..., N, 4, 7)`` = ``d e / d tau`` for
        ``T_ij <- Exp(tau) T_ij``.
    """
    d, r, e = ray_range_terms(T_ij, X_j, X_i)

    # Written block by block into one buffer: the global BA linearises millions of matches,
    # and concatenating per-match blocks cost more than the arithmetic.
    J = _jacobian_buffer(r, 4).zero_()
    r_over_d = r / d[..., None]
    J[..., :3, :3] = -r_over_d[..., :, None] * r[..., None, :]
    for k in range(3):
        J[..., k, k] += 1.0 / d
    r0, r1, r2 = r.unbind(-1)
    J[..., 0, 4], J[..., 0, 5] = r2, -r1  # -[r]_x
    J[..., 1, 3], J[..., 1, 5] = -r2, r0
    J[..., 2, 3], J[..., 2, 4] = r1, -r0
    J[..., 3, :3] = r
    J[..., 3, 6] = d
    return e, J.expand(*e.shape, 7)


def calibrated_residual(
    T_ij: Tensor, X_j: Tensor, p_i: Tensor, z_i: Tensor, K: Tensor
) -> tuple[Tensor, Tensor]:
    """Pixel-and-log-depth residual of the known-calibration variant (C-Eq. 17-18).

    ``e = [Pi_K(T X_j) - p_i; log z(T X_j) - log z_i]`` with ``Pi_K(x) = (K x)_{1,2} / z``.
    For ``x = (x, y, z)`` the pixel Jacobian ``(K_{1:2} - Pi_K(x) e_3^T) / z`` equals C-Eq. 18
    (and also covers a skew term); the log-depth row is ``(0, 0, 1 / z)``. Both are composed with
    C-Eq. 9.

    Args:
        T_ij: ``(..., 8)`` pose of camera j in camera i.
        X_j: ``(..., N, 3)`` points in camera j.
        p_i: ``(..., N, 2)`` observed pixels ``(u, v)`` in image i.
        z_i: ``(..., N)`` observed depths (z) in camera i, positive.
        K: ``(..., 3, 3)`` intrinsics of camera i (last row ``(0, 0, 1)``). All batch dims
            broadcast.

    Returns:
        ``e``: ``(..., N, 3)``; ``J``: ``(..., N, 3, 7)`` = ``d e / d tau`` for
        ``T_ij <- Exp(tau) T_ij``.
    """
    x = _transform_matches(T_ij, X_j)
    z = x[..., 2].clamp_min(_MIN_NORM)
    inv_z = 1.0 / z
    K = K.to(x.dtype)[..., None, :2, :]  # (..., 1, 2, 3): broadcasts over the N matches;
    # float64 poses promote x (global BA)
    fx, k_skew, cx = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2]
    fy, cy = K[..., 1, 1], K[..., 1, 2]
    x0, x1 = x[..., 0] * inv_z, x[..., 1] * inv_z  # normalised image coordinates
    u = fx * x0 + k_skew * x1 + cx
    v = fy * x1 + cy
    e = torch.stack(
        [u - p_i[..., 0], v - p_i[..., 1], z.log() - z_i.clamp_min(_MIN_NORM).log()], dim=-1
    )

    # Rows j_c of d e_c / d x, composed with C-Eq. 9's [I, -[x]_x, x] into
    # [j_c, x cross j_c, j_c . x], written block by block into one buffer (the global BA
    # linearises millions of matches; small per-match matrix products and concatenations
    # cost more than the arithmetic). j_u = (fx, skew, cx - u) / z, j_v = (0, fy, cy - v) / z,
    # j_log_z = (0, 0, 1) / z. j_u . x = j_v . x = 0 (a scale change moves a point along its
    # ray, its pixel stays) and j_log_z . x = 1, exactly for x in front of the camera.
    J = _jacobian_buffer(e, 3)  # every entry is written below (zeroing costs a pass)
    ju0, ju1, ju2 = fx * inv_z, k_skew * inv_z, (cx - u) * inv_z
    jv1, jv2 = fy * inv_z, (cy - v) * inv_z
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = ju0, ju1, ju2
    J[..., 1, 1], J[..., 1, 2] = jv1, jv2
    J[..., 2, 2] = inv_z
    J[..., 0, 6] = J[..., 1, 0] = J[..., 1, 6] = J[..., 2, 0] = J[..., 2, 1] = J[..., 2, 5] = 0.0
    X, Y, Z = x.unbind(-1)
    J[..., 0, 3], J[..., 0, 4], J[..., 0, 5] = (
        Y * ju2 - Z * ju1,
        Z * ju0 - X * ju2,
        X * ju1 - Y * ju0,
    )
    J[..., 1, 3], J[..., 1, 4], J[..., 1, 5] = Y * jv2 - Z * jv1, -X * jv2, X * jv1
    J[..., 2, 3], J[..., 2, 4] = x1, -x0
    J[..., 2, 6] = x[..., 2] * inv_z
    return e, J.expand(*e.shape, 7)


def edge_jacobians(T_WC_i: Tensor, J_rel: Tensor) -> tuple[Tensor, Tensor]:
    """Jacobians of an edge residual with respect to both endpoint poses (C-Eq. 11).

    For ``T_ij = T_WC_i^-1 T_WC_j``, a left perturbation of ``T_WC_j`` moves ``T_ij`` by
    ``Exp(Ad_{T_WC_i^-1} delta)`` and one of ``T_WC_i`` by ``Exp(-Ad_{T_WC_i^-1} delta)``, so

        J_i = -J_rel Ad_{T_WC_i^-1},    J_j = +J_rel Ad_{T_WC_i^-1}.

    Args:
        T_WC_i: ``(..., 8)`` world pose of camera i.
        J_rel: ``(..., M, 7)`` Jacobian rows with respect to ``T_ij`` (e.g. ``(..., N*4, 7)``
            from :func:`ray_range_residual`); its ``...`` broadcast against ``T_WC_i``'s.

    Returns:
        ``(J_i, J_j)``, each ``(..., M, 7)``.
    """
    J_j = J_rel @ sim3_adjoint(sim3_inverse(T_WC_i))
    return -J_j, J_j


def huber_weight(r: Tensor, k: float) -> Tensor:
    """IRLS weight of the Huber kernel, ``min(1, k / |r|)`` (C-Sec. A.1).

    Args:
        r: ``(...)`` whitened residual components.
        k: Huber breakpoint (1.345 in Table 3), positive.

    Returns:
        ``(...)`` weights in ``(0, 1]``.
    """
    if not k > 0:
        raise ValueError(f"huber_weight: breakpoint k must be positive, got {k}")
    return k / r.abs().clamp_min(k)
