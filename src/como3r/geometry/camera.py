"""Pinhole camera model: intrinsics, pixel grids, unprojection and projection (C-Sec. A.5).

Pixel convention (as in MASt3R-SLAM): ``u`` is the column and ``v`` the row index, and pixel
centres sit at integer coordinates, so pixel ``(row, col)`` has coordinates ``(u, v) = (col,
row)`` and the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. Intrinsics are upper
triangular ``K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]``; camera frames are x right, y down,
z forward.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from como3r.geometry.residuals import psi

__all__ = [
    "intrinsics_matrix",
    "pixel_grid",
    "unproject_depth",
    "project",
    "rays_from_intrinsics",
    "scale_intrinsics",
    "crop_intrinsics",
    "lock_to_rays",
    "estimate_focal",
    "rescale_focal",
    "to_focal",
]

# Depths are clamped to this before dividing; points at or behind the camera project far
# outside the image instead of producing NaNs. Callers test z > 0 themselves.
_MIN_DEPTH = 1e-12


def intrinsics_matrix(
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """``(3, 3)`` pinhole intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def pixel_grid(
    H: int, W: int, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """``(H, W, 2)`` pixel coordinates ``(u, v) = (column, row)`` of every pixel centre."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=dtype, device=device),
        torch.arange(W, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def _unit_depth_rays(H: int, W: int, K: Tensor) -> Tensor:
    """``K^-1 [u, v, 1]^T`` for every pixel: ``(..., H, W, 3)`` rays with ``z = 1``."""
    uv = pixel_grid(H, W, dtype=K.dtype, device=K.device)
    fx, fy = K[..., 0, 0, None, None], K[..., 1, 1, None, None]
    cx, cy = K[..., 0, 2, None, None], K[..., 1, 2, None, None]
    skew = K[..., 0, 1, None, None]
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - skew * y) / fx
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def unproject_depth(depth: Tensor, K: Tensor) -> Tensor:
    """Back-project a z-depth map to camera-frame points ``z K^-1 [u, v, 1]^T`` (C-Eq. 16).

    Args:
        depth: ``(..., H, W)`` depth along the optical axis.
        K: ``(..., 3, 3)`` intrinsics; batch dims broadcast against ``depth``'s.

    Returns:
        ``(..., H, W, 3)`` points in the camera frame.
    """
    H, W = depth.shape[-2:]
    return depth[..., None] * _unit_depth_rays(H, W, K.to(depth.dtype))


def project(x: Tensor, K: Tensor) -> Tensor:
    """Pinhole projection ``Pi_K(x) = (K x)_{1,2} / z`` (C-Sec. A.5).

    Args:
        x: ``(..., 3)`` camera-frame points.
        K: ``(..., 3, 3)``; batch dims broadcast against ``x``'s leading dims (insert
            singleton dims as for ``sim3_act``).

    Returns:
        ``(..., 2)`` pixel coordinates ``(u, v)``.
    """
    z = x[..., 2].clamp_min(_MIN_DEPTH)
    u = (K[..., 0, 0] * x[..., 0] + K[..., 0, 1] * x[..., 1]) / z + K[..., 0, 2]
    v = K[..., 1, 1] * x[..., 1] / z + K[..., 1, 2]
    return torch.stack([u, v], dim=-1)


def rays_from_intrinsics(H: int, W: int, K: Tensor) -> Tensor:
    """``(..., H, W, 3)`` unit rays through every pixel centre for ``K`` ``(..., 3, 3)``."""
    return psi(_unit_depth_rays(H, W, K))


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """Intrinsics of the image resized by ``sx`` (width) and ``sy`` (height).

    With pixel centres at integer coordinates, image borders ``-0.5`` map to ``-0.5``, so
    ``u' = sx (u + 0.5) - 0.5``: ``fx' = sx fx`` and ``cx' = sx (cx + 0.5) - 0.5`` (likewise
    for ``v``). ``K``: ``(..., 3, 3)``.
    """
    S = torch.tensor(
        [[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]],
        dtype=K.dtype,
        device=K.device,
    )
    return S @ K


def crop_intrinsics(K: Tensor, left: float, top: float) -> Tensor:
    """Intrinsics of the image cropped to start at column ``left`` and row ``top``.

    ``cx' = cx - left``, ``cy' = cy - top``. ``K``: ``(..., 3, 3)``.
    """
    K = K.clone()
    K[..., 0, 2] -= left
    K[..., 1, 2] -= top
    return K


def lock_to_rays(X: Tensor, K: Tensor) -> Tensor:
    """Constrain a pointmap to the calibrated rays, keeping its depths (C-Eq. 16).

    Args:
        X: ``(..., H, W, 3)`` pointmap in its own camera frame.
        K: ``(..., 3, 3)`` intrinsics of that camera at the pointmap's resolution.

    Returns:
        ``(..., H, W, 3)`` points ``z_p K^-1 [u_p, v_p, 1]^T`` with ``z_p = [X_p]_3``.
    """
    return unproject_depth(X[..., 2], K)


def estimate_focal(X: Tensor, weights: Tensor | None = None, iterations: int = 10) -> Tensor:
    """Focal length of the pinhole camera a pointmap implies, principal point at the image
    centre (DUSt3R's ``estimate_focal_knowing_depth``, Weiszfeld mode).

    Minimises ``sum_p w_p || (u_p - c) - f (x_p / z_p, y_p / z_p) ||`` over ``f`` by
    iteratively reweighted least squares (the Weiszfeld iteration of a geometric median):
    robust to flying pixels and the prior's outliers, which a plain least-squares fit is not.

    Args:
        X: ``(H, W, 3)`` pointmap in its own camera frame.
        weights: ``(H, W)`` non-negative weights (e.g. confidences); None gives 1.
        iterations: Weiszfeld iterations after the least-squares start.

    Returns:
        ``()`` focal length in pixels (``nan`` when no point lies in front of the camera).
    """
    H, W = X.shape[:2]
    uv = pixel_grid(H, W, dtype=X.dtype, device=X.device)
    centre = torch.tensor([(W - 1) / 2.0, (H - 1) / 2.0], dtype=X.dtype, device=X.device)
    offset = (uv - centre).reshape(-1, 2)
    z = X[..., 2].reshape(-1)
    usable = torch.isfinite(X).all(-1).reshape(-1) & (z > _MIN_DEPTH)
    w = torch.ones_like(z) if weights is None else weights.reshape(-1).to(X.dtype)
    w = torch.where(usable, w, torch.zeros_like(w))
    xy = X[..., :2].reshape(-1, 2) / torch.where(usable, z, torch.ones_like(z))[:, None]
    xy = torch.where(usable[:, None], xy, torch.zeros_like(xy))
    reweight = w
    focal = torch.tensor(float("nan"), dtype=X.dtype, device=X.device)
    for _ in range(iterations + 1):
        numerator = (reweight[:, None] * xy * offset).sum()
        denominator = (reweight[:, None] * xy * xy).sum()
        if float(denominator) <= 0:
            return torch.tensor(float("nan"), dtype=X.dtype, device=X.device)
        focal = numerator / denominator
        distance = (offset - focal * xy).norm(dim=-1)
        reweight = w / distance.clamp_min(1e-8)
    return focal


def rescale_focal(X: Tensor, K: Tensor, log_focal: float) -> tuple[Tensor, Tensor]:
    """A pointmap and intrinsics moved to the focal length ``f exp(log_focal)``.

    Args:
        X: ``(..., H, W, 3)`` pointmap on the rays of ``K`` (C-Eq. 16).
        K: ``(..., 3, 3)`` intrinsics.
        log_focal: ``delta``.

    Returns:
        ``X`` with x and y times ``exp(-delta)`` (depths kept, so every point still
        projects to its pixel) and ``K`` with fx, fy times ``exp(delta)``.
    """
    factor = math.exp(log_focal)
    X = torch.cat([X[..., :2] / factor, X[..., 2:]], dim=-1)
    K = K.clone()
    K[..., 0, 0] *= factor
    K[..., 1, 1] *= factor
    return X, K


def to_focal(X: Tensor, K: Tensor, focal: float) -> tuple[Tensor, Tensor]:
    """:func:`rescale_focal` to the focal length ``focal`` (``fx``, pixels) from ``K``'s."""
    return rescale_focal(X, K, math.log(focal / float(K[..., 0, 0].reshape(-1)[0])))
