"""Closed-form (weighted) similarity between two point sets (Umeyama 1991; C-Eq. 14).

Used by the gauge synchronisation of C-Sec. A.4 and by the simulated prior. The fit is
computed in float64 whatever the input dtype and returned in the input dtype.
"""

from __future__ import annotations

import torch
from torch import Tensor

from como3r.errors import GeometryError
from como3r.geometry.lie import matrix_to_quat, sim3_act_points

__all__ = ["umeyama_sim3", "umeyama_rmse", "umeyama_sim3_batched"]

# Relative singular-value threshold below which the cross-covariance counts as rank < 2, per
# input precision. Exactly collinear points stored in float32 (float64) deviate from their
# line by rounding, which makes sigma_2 / sigma_1 up to ~1e-6 (~1e-13) for point clouds lying
# far from the origin relative to their extent.
_RANK_RTOL = {torch.float64: 1e-8}
_RANK_RTOL_DEFAULT = 1e-4
# A point set whose RMS spread is below this many ulps of its largest coordinate is coincident.
_SPREAD_ULPS = 100.0


def _validate(src: Tensor, dst: Tensor, weights: Tensor | None) -> None:
    if src.ndim != 2 or src.shape[-1] != 3:
        raise GeometryError(f"umeyama_sim3: src must have shape (N, 3), got {tuple(src.shape)}")
    if dst.shape != src.shape:
        raise GeometryError(
            f"umeyama_sim3: dst must have the shape of src {tuple(src.shape)}, "
            f"got {tuple(dst.shape)}"
        )
    if src.shape[0] < 3:
        raise GeometryError(f"umeyama_sim3: need at least 3 point pairs, got {src.shape[0]}")
    if not (bool(torch.isfinite(src).all()) and bool(torch.isfinite(dst).all())):
        raise GeometryError("umeyama_sim3: src and dst must be finite (found NaN or inf)")
    if weights is None:
        return
    if weights.shape != src.shape[:1]:
        raise GeometryError(
            f"umeyama_sim3: weights must have shape ({src.shape[0]},), got {tuple(weights.shape)}"
        )
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()):
        raise GeometryError("umeyama_sim3: weights must be finite and non-negative")
    positive = int((weights > 0).sum())
    if positive == 0:
        raise GeometryError("umeyama_sim3: all weights are zero")
    if positive < 3:
        raise GeometryError(
            f"umeyama_sim3: need at least 3 point pairs with positive weight, got {positive}"
        )


def _check_spread(points: Tensor, centred: Tensor, w: Tensor, eps: float, name: str) -> Tensor:
    """Weighted mean squared distance to the centroid; raises if the points coincide."""
    variance = (w * (centred * centred).sum(-1)).sum()
    magnitude = points.abs().max()
    if bool(variance.sqrt() <= _SPREAD_ULPS * eps * magnitude):
        raise GeometryError(
            f"umeyama_sim3: degenerate input, the {name} points coincide (zero spread)"
        )
    return variance


def umeyama_sim3(
    src: Tensor,
    dst: Tensor,
    weights: Tensor | None = None,
    with_scale: bool = True,
    rank_rtol: float | None = None,
) -> Tensor:
    """Least-squares similarity ``dst ~= s R src + t`` (C-Eq. 14).

    With normalised weights ``w``, centroids ``mu_src, mu_dst`` and the cross-covariance
    ``Sigma = sum_k w_k (dst_k - mu_dst)(src_k - mu_src)^T = U Lambda V^T``:
    ``R = U D V^T`` with ``D = diag(1, 1, det(U V^T))`` (a proper rotation even when the best
    orthogonal fit is a reflection), ``s = tr(Lambda D) / sum_k w_k ||src_k - mu_src||^2`` and
    ``t = mu_dst - s R mu_src``.

    Args:
        src: ``(N, 3)`` source points (e.g. agent b's world frame), ``N >= 3``.
        dst: ``(N, 3)`` matched destination points (e.g. agent a's world frame).
        weights: optional ``(N,)`` non-negative weights (zero ignores a pair).
        with_scale: estimate ``s``; otherwise ``s = 1`` (a rigid fit).
        rank_rtol: ``Sigma`` counts as rank < 2 when its second singular value is below
            ``rank_rtol`` times its largest; default 1e-8 for float64 and 1e-4 for float32
            input.

    Returns:
        ``(8,)`` Sim(3) element ``T`` with ``sim3_act(T, src) ~= dst``, in ``src``'s dtype.

    Raises:
        GeometryError: fewer than 3 pairs, mismatched shapes, non-finite input, invalid or
            all-zero weights, coincident points, or a collinear configuration (rank < 2).
    """
    src, dst = torch.as_tensor(src), torch.as_tensor(dst)
    weights = None if weights is None else torch.as_tensor(weights, device=src.device)
    _validate(src, dst, weights)
    out_dtype = src.dtype if src.is_floating_point() else torch.float64
    eps = torch.finfo(out_dtype).eps
    rtol = _RANK_RTOL.get(out_dtype, _RANK_RTOL_DEFAULT) if rank_rtol is None else rank_rtol

    x, y = src.double(), dst.double()
    w = torch.ones_like(x[:, 0]) if weights is None else weights.double()
    w = w / w.sum()
    mu_x, mu_y = w @ x, w @ y
    x_c, y_c = x - mu_x, y - mu_y
    var_x = _check_spread(x, x_c, w, eps, "source")
    _check_spread(y, y_c, w, eps, "destination")

    covariance = (y_c * w[:, None]).T @ x_c
    U, singular, Vh = torch.linalg.svd(covariance)
    if bool(singular[1] <= rtol * singular[0]):
        raise GeometryError(
            "umeyama_sim3: degenerate input, the points are collinear "
            f"(covariance singular values {singular.tolist()})"
        )
    d = torch.ones_like(singular)
    d[2] = torch.linalg.det(U @ Vh).sign()
    R = U @ torch.diag(d) @ Vh
    s = (singular * d).sum() / var_x if with_scale else torch.ones_like(var_x)
    t = mu_y - s * (R @ mu_x)
    T = torch.cat([t, matrix_to_quat(R), s[None]])
    return T.to(out_dtype)


def umeyama_rmse(T: Tensor, src: Tensor, dst: Tensor, weights: Tensor | None = None) -> float:
    """(Weighted) root-mean-square distance ``|| T src - dst ||`` of a fit.

    Args:
        T: ``(8,)`` Sim(3) element.
        src, dst: ``(N, 3)``.
        weights: optional ``(N,)`` non-negative weights.
    """
    squared = (sim3_act_points(T, src) - dst).pow(2).sum(-1)
    if weights is None:
        return float(squared.mean().sqrt())
    return float(((weights * squared).sum() / weights.sum()).sqrt())


def umeyama_sim3_batched(src: Tensor, dst: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Closed-form similarities of many small samples at once (RANSAC hypotheses, C-Eq. 14).

    Unlike :func:`umeyama_sim3` it never raises: degenerate samples give arbitrary
    transforms, which simply collect few inliers.

    Args:
        src, dst: ``(B, k, 3)`` point samples (float64 recommended).

    Returns:
        ``R (B, 3, 3)``, ``t (B, 3)``, ``s (B,)`` with ``dst ~= s R src + t``.
    """
    mu_src, mu_dst = src.mean(1, keepdim=True), dst.mean(1, keepdim=True)
    x, y = src - mu_src, dst - mu_dst
    U, singular, Vh = torch.linalg.svd(y.transpose(1, 2) @ x)
    d = torch.ones_like(singular)
    d[:, 2] = torch.linalg.det(U @ Vh).sign()  # proper rotation (reflection handling)
    R = U @ torch.diag_embed(d) @ Vh
    s = (singular * d).sum(-1) / x.square().sum((1, 2)).clamp_min(1e-12)
    t = mu_dst[:, 0] - s[:, None] * (R @ mu_src[:, 0, :, None])[..., 0]
    return R, t, s
