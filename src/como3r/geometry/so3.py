"""The rotation group SO(3) on torch tensors: skew matrices, unit quaternions and the
exponential and logarithm maps (C-Sec. 3.2). Part of :mod:`como3r.geometry.lie`, which
re-exports every public name; import from there.

Every function is pure, batched over arbitrary leading dimensions, differentiable and works in
float32 and float64 on any device. A unit quaternion is ``(..., 4)`` = ``(x, y, z, w)``,
Hamilton product.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "skew",
    "quat_identity",
    "quat_multiply",
    "quat_conjugate",
    "quat_rotate",
    "quat_to_matrix",
    "matrix_to_quat",
    "so3_exp",
    "so3_log",
]

# Below this rotation angle so3_exp / so3_log switch to Taylor series; the truncation error
# there is below 1e-17 and the closed forms above it are accurate to a few ulps.
_SO3_SERIES_ANGLE = 1e-2


def check_last_dim(x: Tensor, size: int, name: str) -> None:
    if x.shape[-1:] != (size,):
        raise ValueError(f"{name} must have shape (..., {size}), got {tuple(x.shape)}")


#: the components (y, z, x) and (z, x, y) of a vector: ``a x b = a_yzx b_zxy - a_zxy b_yzx``
_YZX, _ZXY = torch.tensor([1, 2, 0]), torch.tensor([2, 0, 1])


def cross3(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over the last dim with full broadcasting (``linalg.cross`` needs equal
    ranks, and its compiled loop rounds differently). Component k is ``a_k+1 b_k+2 -
    a_k+2 b_k+1`` (indices mod 3), as three products written out, in 7 tensor operations
    instead of 12 (a solver's 2-10 poses: the dispatch is the cost)."""
    yzx, zxy = (_YZX, _ZXY) if a.device.type == "cpu" else (_YZX.to(a.device), _ZXY.to(a.device))
    return a.index_select(-1, yzx) * b.index_select(-1, zxy) - a.index_select(
        -1, zxy
    ) * b.index_select(-1, yzx)


# --------------------------------------------------------------------------------------------
# SO(3): skew matrices and quaternions
# --------------------------------------------------------------------------------------------


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix: ``skew(v) @ x == cross(v, x)``.

    Args:
        v: ``(..., 3)``.

    Returns:
        ``(..., 3, 3)``.
    """
    check_last_dim(v, 3, "v")
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).unflatten(-1, (3, 3))


def quat_identity(
    *batch_shape: int, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Identity quaternions ``(*batch_shape, 4)`` = ``(0, 0, 0, 1)``."""
    q = torch.zeros(*batch_shape, 4, dtype=dtype, device=device)
    q[..., 3] = 1.0
    return q


def quat_multiply(q1: Tensor, q2: Tensor) -> Tensor:
    """Hamilton product ``q1 * q2`` (rotate by ``q2`` first, then ``q1``).

    Args:
        q1, q2: ``(..., 4)`` quaternions ``(x, y, z, w)``; batch dims broadcast.

    Returns:
        ``(..., 4)``.
    """
    check_last_dim(q1, 4, "q1")
    check_last_dim(q2, 4, "q2")
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + cross3(v1, v2)
    w = w1 * w2 - (v1 * v2).sum(-1, keepdim=True)
    return torch.cat([v, w], dim=-1)


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate (the inverse of a unit quaternion). ``q``: ``(..., 4)``."""
    check_last_dim(q, 4, "q")
    return torch.cat([-q[..., :3], q[..., 3:]], dim=-1)


def quat_rotate(q: Tensor, x: Tensor) -> Tensor:
    """Rotate points by unit quaternions: ``R(q) x``.

    Args:
        q: ``(..., 4)`` unit quaternions.
        x: ``(..., 3)`` points; batch dims broadcast against ``q``'s.

    Returns:
        ``(..., 3)``.
    """
    check_last_dim(q, 4, "q")
    check_last_dim(x, 3, "x")
    qv, w = q[..., :3], q[..., 3:]
    # R x = x + 2 w (qv x x) + 2 qv x (qv x x): two cross products, no 3x3 matrix.
    uv = 2.0 * cross3(qv, x)
    return x + w * uv + cross3(qv, uv)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices of unit quaternions. ``q``: ``(..., 4)`` -> ``(..., 3, 3)``."""
    check_last_dim(q, 4, "q")
    x, y, z, w = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz),
        2 * (xy - wz),
        2 * (xz + wy),
        2 * (xy + wz),
        1 - 2 * (xx + zz),
        2 * (yz - wx),
        2 * (xz - wy),
        2 * (yz + wx),
        1 - 2 * (xx + yy),
    ]
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def matrix_to_quat(R: Tensor) -> Tensor:
    """Unit quaternions of rotation matrices (Shepperd's method, all four branches).

    Each candidate quaternion is computed from one of ``4w^2, 4x^2, 4y^2, 4z^2`` (read off the
    diagonal); the largest is at least 1, so dividing by its root is always well conditioned,
    including at 180-degree rotations where ``w = 0``. The result is normalised and has
    ``w >= 0``.

    Args:
        R: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 4)`` quaternions ``(x, y, z, w)``.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    m = R.flatten(-2).unbind(-1)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    four_sq = torch.stack(
        [
            1 + m00 - m11 - m22,  # 4 x^2
            1 - m00 + m11 - m22,  # 4 y^2
            1 - m00 - m11 + m22,  # 4 z^2
            1 + m00 + m11 + m22,  # 4 w^2
        ],
        dim=-1,
    )
    # Off-diagonal sums and differences: 4xy, 4xz, 4yz and 4wx, 4wy, 4wz.
    xy, xz, yz = m01 + m10, m02 + m20, m12 + m21
    wx, wy, wz = m21 - m12, m02 - m20, m10 - m01
    candidates = torch.stack(
        [
            torch.stack([four_sq[..., 0], xy, xz, wx], dim=-1),
            torch.stack([xy, four_sq[..., 1], yz, wy], dim=-1),
            torch.stack([xz, yz, four_sq[..., 2], wz], dim=-1),
            torch.stack([wx, wy, wz, four_sq[..., 3]], dim=-1),
        ],
        dim=-2,
    )
    # Only the candidate with the largest entry (>= 1 since the four sum to 4) is kept; the
    # clamp merely keeps the discarded ones finite.
    candidates = candidates / (2.0 * four_sq.clamp_min(0.1).sqrt()[..., None])
    best = four_sq.argmax(dim=-1)
    index = best[..., None, None].expand(*best.shape, 1, 4)
    q = candidates.gather(-2, index).squeeze(-2)
    q = torch.where(q[..., 3:] < 0, -q, q)
    return q / q.norm(dim=-1, keepdim=True)


def so3_exp(phi: Tensor) -> Tensor:
    """Exponential map of so(3): rotation vector -> unit quaternion.

    ``q = (sin(theta/2) phi / theta, cos(theta/2))``; Taylor series below a small angle so that
    values and gradients are exact at ``phi = 0``.

    Args:
        phi: ``(..., 3)`` rotation vectors (axis * angle, radians).

    Returns:
        ``(..., 4)`` unit quaternions.
    """
    check_last_dim(phi, 3, "phi")
    theta_sq = (phi * phi).sum(-1, keepdim=True)
    small = theta_sq < _SO3_SERIES_ANGLE**2
    theta = torch.where(small, torch.ones_like(theta_sq), theta_sq).sqrt()
    half = 0.5 * theta
    t2, t4 = theta_sq, theta_sq * theta_sq
    sin_half_over_theta = torch.where(small, 0.5 - t2 / 48.0 + t4 / 3840.0, half.sin() / theta)
    cos_half = torch.where(small, 1.0 - t2 / 8.0 + t4 / 384.0, half.cos())
    return torch.cat([sin_half_over_theta * phi, cos_half], dim=-1)


def so3_log(q: Tensor) -> Tensor:
    """Logarithm of SO(3): unit quaternion -> rotation vector with angle in ``[0, pi]``.

    ``q`` and ``-q`` give the same result (the sign is chosen so that ``w >= 0``). The angle is
    ``2 atan2(|qv|, w)``, which stays well conditioned near ``pi``; below a small ``|qv|`` the
    ratio ``angle / |qv|`` is a Taylor series in ``(|qv| / w)^2`` so that values and gradients
    are exact at the identity. Non-unit quaternions give the log of their normalisation.

    Args:
        q: ``(..., 4)`` quaternions ``(x, y, z, w)``.

    Returns:
        ``(..., 3)`` rotation vectors.
    """
    check_last_dim(q, 4, "q")
    q = torch.where(q[..., 3:] < 0, -q, q)
    qv, w = q[..., :3], q[..., 3:]
    n_sq = (qv * qv).sum(-1, keepdim=True)
    small = n_sq < (_SO3_SERIES_ANGLE * w) ** 2
    n = torch.where(small, torch.ones_like(n_sq), n_sq).sqrt()
    w_safe = torch.where(small, w, torch.ones_like(w))
    u2 = n_sq / (w_safe * w_safe)
    # atan(u) / u = 1 - u^2/3 + u^4/5 - u^6/7 + u^8/9, u = |qv| / w < 1e-2.
    atan_series = 1.0 + u2 * (-1.0 / 3 + u2 * (1.0 / 5 + u2 * (-1.0 / 7 + u2 / 9)))
    scale = torch.where(small, 2.0 * atan_series / w_safe, 2.0 * torch.atan2(n, w) / n)
    return scale * qv
