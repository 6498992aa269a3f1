"""Dense projective matching of two pointmaps (C-Eq. 1, C-Sec. 3.3).

For every query point ``x`` (a pixel of one view, expressed in the frame of the other
view) we look for the pixel ``p`` of the other view's own pointmap whose ray is closest:

    p* = argmin_p || psi([X]_p) - psi(x) ||^2                               (C-Eq. 1)

solved per pixel by damped Gauss-Newton on the continuous pixel position over the ray
image and its spatial gradients, warm-started from the previous frame's matches. The
match is then refined by descriptor similarity in a dilated window (MASt3R-SLAM's
coarse-to-fine search, dilation 5 -> 1), and rejected as occluded when the 3-D points at
the two ends are further apart than ``occlusion_ratio`` times the query's range. Validity
is decided on the final, refined match; only matches that can be valid (the projection
converged on a finite query point) are refined, the others keep their projected pixel.

Everything is vectorised PyTorch over a batch of pairs and runs on CPU and GPU; on CPU the
per-pixel work (ray image, projection, window search, validity) runs as compiled loops
(:mod:`como3r.frontend.cpu_kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import MatchingConfig
from como3r.frontend import cpu_kernels, cpu_window_search
from como3r.frontend.match_consensus import consensus_window, displacement_consensus
from como3r.geometry.residuals import psi
from como3r.geometry.units import pixels_at

#: query pixels refined at once: small enough that the gathered (chunk, 49, d) float32
#: candidate descriptors (2.4 MB at 512) stay in cache, large enough to amortise the
#: per-chunk overhead. Whole matching call on a 512x384 pair, one thread, AMD EPYC: chunk
#: 1024 0.99 s, 512 0.91 s, 256 0.92 s (16k was 2x slower than 1024)
_REFINE_CHUNK = 512
#: the same on a GPU, where a chunk's cost is its kernel launches (about 25 per chunk), not
#: its cache: 512 took 224 ms a matching call on an H200 (384 chunks, 10k launches,
#: benchmarks/cuda_speed.py); 65536 matches gather a 308 MB (chunk, 49, 24) float32 buffer
_REFINE_CHUNK_CUDA = 1 << 16

#: dtype of the descriptor scores of the window search. MASt3R-SLAM's refine_matches kernel
#: scores in half precision (``D.half()``) on the GPU; on CPU, float32 with a fused dot
#: product (torch.linalg.vecdot) is faster than a half-precision bmm on CPUs without native
#: fp16 arithmetic: 512x384, radius 3, dilations 5..1, one thread, AMD EPYC (AVX512-BF16,
#: no AVX512-FP16), busy machine: half-precision bmm 3.1 s, half vecdot 1.9 s, float32 vecdot
#: 1.0 s (benchmarks/matching_kernel.py; AMX CPUs may differ). float32 changes the choice
#: only between candidates whose scores agree to fp16 rounding (0.3 % of the refined pixels
#: of random unit descriptors)
_SCORE_DTYPE = torch.float32


@dataclass(frozen=True)
class Matches:
    """Dense matches from query pixels to pixels of the searched view.

    Attributes:
        idx: ``(B, P)`` int64 linear pixel index ``v * W + u`` in the searched view.
        pixel: ``(B, P, 2)`` int64 pixel ``(u, v)`` in the searched view.
        valid: ``(B, P)`` bool: converged, inside the image and not occluded.
    """

    idx: Tensor
    pixel: Tensor
    valid: Tensor


def ray_image_with_gradients(X: Tensor) -> Tensor:
    """Unit-ray image and its spatial derivatives.

    Args:
        X: ``(B, H, W, 3)`` pointmap in its own camera frame.

    Returns:
        ``(B, H, W, 9)``: ray ``psi(X)``, ``d ray / du``, ``d ray / dv`` (central
        differences, one-sided at the border).
    """
    if X.device.type == "cpu" and not X.requires_grad:  # one compiled pass
        return cpu_kernels.ray_image_with_gradients(X)
    rays = psi(X)
    grad_u = torch.gradient(rays, dim=2)[0]
    grad_v = torch.gradient(rays, dim=1)[0]
    return torch.cat([rays, grad_u, grad_v], dim=-1)


def _bilinear(table: Tensor, H: int, W: int, base: Tensor, p: Tensor) -> Tensor:
    """Bilinear samples of a flattened image batch at continuous pixels.

    Args:
        table: ``(B * H * W, C)`` image rows, image b starting at row ``b * H * W``.
        H, W: image size.
        base: ``(M,)`` first row of each sample's image (``b * H * W``).
        p: ``(M, 2)`` pixels ``(u, v)`` inside the image.

    Returns:
        ``(M, C)`` samples.
    """
    u = p[:, 0].clamp(0, W - 1)
    v = p[:, 1].clamp(0, H - 1)
    u0 = u.floor().clamp(max=max(W - 2, 0)).long()
    v0 = v.floor().clamp(max=max(H - 2, 0)).long()
    u1 = (u0 + 1).clamp(max=W - 1)
    v1 = (v0 + 1).clamp(max=H - 1)
    a = (u - u0)[:, None]
    b = (v - v0)[:, None]
    top_row, bottom_row = base + v0 * W, base + v1 * W
    # the four corners in one gather (index_select is several times faster than indexing)
    corners = torch.cat([top_row + u0, top_row + u1, bottom_row + u0, bottom_row + u1])
    t00, t01, t10, t11 = table.index_select(0, corners).view(4, -1, table.shape[1]).unbind(0)
    top = t00 * (1 - a) + t01 * a
    bottom = t10 * (1 - a) + t11 * a
    return top * (1 - b) + bottom * b


def _ray_cost(
    table: Tensor, H: int, W: int, base: Tensor, p: Tensor, target: Tensor
) -> tuple[Tensor, Tensor]:
    """Squared ray error ``(M,)`` at ``p`` and the linearization ``(M, 9)`` there: the
    residual (3) and its derivatives w.r.t. u (3) and v (3), kept in one tensor."""
    sample = _bilinear(table, H, W, base, p)
    err = psi(sample[:, 0:3]) - target
    return (err * err).sum(-1), torch.cat([err, sample[:, 3:9]], dim=-1)


def _damped_step(lin: Tensor, lam: Tensor) -> Tensor:
    """Solve the 2x2 system ``(J^T J + lam I) step = -J^T err`` in closed form -> ``(M, 2)``,
    with ``lin = [err, J_u, J_v]`` ``(M, 9)`` from :func:`_ray_cost`."""
    err, J_u, J_v = lin[:, 0:3], lin[:, 3:6], lin[:, 6:9]
    a11 = (J_u * J_u).sum(-1) + lam
    a12 = (J_u * J_v).sum(-1)
    a22 = (J_v * J_v).sum(-1) + lam
    b1 = -(J_u * err).sum(-1)
    b2 = -(J_v * err).sum(-1)
    det = a11 * a22 - a12 * a12
    return torch.stack([a22 * b1 - a12 * b2, a11 * b2 - a12 * b1], dim=-1) / det[:, None]


def project_iteratively(
    rays_grad: Tensor,
    target_rays: Tensor,
    p_init: Tensor,
    max_iters: int,
    lambda_init: float,
    convergence_tol: float,
) -> tuple[Tensor, Tensor]:
    """Damped Gauss-Newton on pixel positions minimising the ray error (C-Eq. 1).

    Each pixel runs its own Levenberg-Marquardt: a step is taken only if it lowers the
    pixel's ray error (damping / 10), else the damping grows (x 10). Converged pixels
    leave the active set, so later iterations only touch the pixels still moving. So do
    pixels whose step left the image and, clamped to its border, did not lower the error:
    their ray lies outside the searched view (a third to a half of the pixels of a
    keyframe link), and they used to spend every remaining iteration pushing against the
    border. On four pairs of a 512x384 run this removed 40-60 % of the ray evaluations and
    changed no valid match.

    Args:
        rays_grad: ``(B, H, W, 9)`` from :func:`ray_image_with_gradients`.
        target_rays: ``(B, P, 3)`` unit query rays.
        p_init: ``(B, P, 2)`` float initial pixels ``(u, v)``.
        max_iters: Gauss-Newton iterations.
        lambda_init: initial damping of the 2x2 normal equations.
        convergence_tol: a pixel has converged when its squared ray error is below this.

    Returns:
        ``(p (B, P, 2) float, converged (B, P) bool)``.
    """
    if rays_grad.device.type == "cpu":
        p, _, converged = cpu_kernels.project_rays(
            rays_grad, target_rays, p_init, max_iters, lambda_init, convergence_tol
        )
        return p, converged
    return _project_vectorised(
        rays_grad, target_rays, p_init, max_iters, lambda_init, convergence_tol
    )


def project_to_pixels(
    rays_grad: Tensor,
    target_rays: Tensor,
    p_init: Tensor,
    max_iters: int,
    lambda_init: float,
    convergence_tol: float,
) -> tuple[Tensor, Tensor]:
    """:func:`project_iteratively`, then the pixel centre whose ray is nearest the target
    (:func:`_nearest_ray_pixel`): ``(pixel (B, P, 2) int64, converged (B, P) bool)``.

    On CPU one compiled loop does both per pixel (:mod:`como3r.frontend.cpu_kernels`).
    """
    if rays_grad.device.type == "cpu":
        _, pixel, converged = cpu_kernels.project_rays(
            rays_grad, target_rays, p_init, max_iters, lambda_init, convergence_tol
        )
        return pixel, converged
    p, converged = _project_vectorised(
        rays_grad, target_rays, p_init, max_iters, lambda_init, convergence_tol
    )
    return _nearest_ray_pixel(rays_grad[..., :3], p, target_rays), converged


def _project_vectorised(
    rays_grad: Tensor,
    target_rays: Tensor,
    p_init: Tensor,
    max_iters: int,
    lambda_init: float,
    convergence_tol: float,
) -> tuple[Tensor, Tensor]:
    """:func:`project_iteratively` as batched PyTorch over the pixels still moving (any
    device; on CPU the compiled loop of :mod:`como3r.frontend.cpu_kernels` is faster)."""
    B, H, W, C = rays_grad.shape
    P = target_rays.shape[1]
    table = rays_grad.reshape(B * H * W, C)
    upper = torch.tensor([W - 1, H - 1], dtype=p_init.dtype, device=p_init.device)
    p = p_init.reshape(B * P, 2).clone()
    target = target_rays.reshape(B * P, 3)
    base = torch.arange(B, device=p.device).repeat_interleave(P) * (H * W)
    cost, lin = _ray_cost(table, H, W, base, p, target)
    keep = ~(cost < convergence_tol)
    active, lin = keep.nonzero().squeeze(-1), lin[keep]
    lam = torch.full_like(active, lambda_init, dtype=p.dtype)
    for _ in range(max_iters):
        if active.numel() == 0:
            break
        step_end = p[active] + _damped_step(lin, lam)
        candidate = step_end.clamp(min=0).minimum(upper)
        new_cost, new_lin = _ray_cost(table, H, W, base[active], candidate, target[active])
        better = (new_cost < cost[active]) & torch.isfinite(new_cost)
        moved = active[better]
        p[moved], cost[moved] = candidate[better], new_cost[better]
        lin = torch.where(better[:, None], new_lin, lin)
        lam = torch.where(better, lam * 0.1, lam * 10.0)
        pushed_out = (candidate != step_end).any(-1) & ~better
        keep = ~(cost[active] < convergence_tol) & ~pushed_out
        active, lin, lam = active[keep], lin[keep], lam[keep]
    return p.reshape(B, P, 2), (cost < convergence_tol).reshape(B, P)


def _nearest_ray_pixel(rays: Tensor, p: Tensor, target_rays: Tensor) -> Tensor:
    """Of the four pixel centres around ``p``, the one whose ray is closest to the target.

    Rounding the continuous optimum is not enough: the ray field is not linear in the
    pixel position, so near half-pixel ties rounding can pick the farther ray.

    Args:
        rays: ``(B, H, W, 3)`` unit rays at pixel centres.
        p: ``(B, P, 2)`` continuous pixels.
        target_rays: ``(B, P, 3)`` unit query rays.

    Returns:
        ``(B, P, 2)`` int64 pixels ``(u, v)``.
    """
    B, H, W, _ = rays.shape
    flat = rays.reshape(B, H * W, 3)
    base = p.floor().long()
    corners = torch.tensor([[0, 0], [1, 0], [0, 1], [1, 1]], device=p.device)
    upper = torch.tensor([W - 1, H - 1], device=p.device)
    cand = (base[:, :, None, :] + corners).clamp(min=0).minimum(upper)  # (B, P, 4, 2)
    lin = (cand[..., 1] * W + cand[..., 0]).reshape(B, -1)
    cand_rays = torch.gather(flat, 1, lin[..., None].expand(-1, -1, 3)).reshape(*cand.shape[:3], 3)
    err = ((cand_rays - target_rays[:, :, None, :]) ** 2).sum(-1)
    best = err.argmin(dim=-1, keepdim=True)
    return torch.gather(cand, 2, best[..., None].expand(-1, -1, 1, 2)).squeeze(2)


def refine_with_descriptors(
    D_search: Tensor,
    D_query: Tensor,
    pixel: Tensor,
    radius: int,
    dilation_max: int,
    active: Tensor | None = None,
) -> Tensor:
    """Move each match to the best descriptor match in shrinking dilated windows.

    At each dilation d (from ``dilation_max`` down to 1) the match moves to the best of
    the ``(2r+1)^2`` pixels ``p + d * (i, j)``, ``|i|, |j| <= r``, by descriptor dot
    product (in :data:`_SCORE_DTYPE`); window pixels outside the image count as the nearest
    border pixel.

    Args:
        D_search: ``(B, H, W, d)`` descriptors of the searched view.
        D_query: ``(B, P, d)`` descriptors of the query pixels.
        pixel: ``(B, P, 2)`` int64 current matches ``(u, v)``.
        radius: window radius in samples.
        dilation_max: first dilation; it decreases to 1.
        active: ``(B, P)`` bool, the matches to refine (default all); the others keep
            ``pixel``.

    Returns:
        ``(B, P, 2)`` int64 refined pixels.
    """
    if D_search.device.type == "cpu":
        return cpu_window_search.refine_windows(
            D_search, D_query, pixel, radius, dilation_max, active
        )
    return _refine_vectorised(D_search, D_query, pixel, radius, dilation_max, active)


def _refine_vectorised(
    D_search: Tensor,
    D_query: Tensor,
    pixel: Tensor,
    radius: int,
    dilation_max: int,
    active: Tensor | None,
    chunk: int | None = None,
) -> Tensor:
    """:func:`refine_with_descriptors` as batched PyTorch (any device; on CPU the compiled
    loop of :mod:`como3r.frontend.cpu_window_search` is 9x faster), ``chunk`` matches at a
    time (default: :data:`_REFINE_CHUNK` on a CPU, :data:`_REFINE_CHUNK_CUDA` elsewhere;
    the result does not depend on it)."""
    if chunk is None:
        chunk = _REFINE_CHUNK if D_search.device.type == "cpu" else _REFINE_CHUNK_CUDA
    B, H, W, d = D_search.shape
    P = pixel.shape[1]
    margin = radius * dilation_max
    # Border-replicated descriptor images, so every window pixel is one flat row index
    # ``centre + offset`` with no per-candidate clamping (the hot loop is memory bound).
    padded = torch.nn.functional.pad(D_search.permute(0, 3, 1, 2), (margin,) * 4, mode="replicate")
    Wp, Hp = W + 2 * margin, H + 2 * margin
    table = padded.permute(0, 2, 3, 1).reshape(B * Hp * Wp, d).to(_SCORE_DTYPE).contiguous()
    steps = torch.arange(-radius, radius + 1, device=pixel.device)
    grid_v, grid_u = torch.meshgrid(steps, steps, indexing="ij")
    window_u, window_v = grid_u.reshape(-1), grid_v.reshape(-1)  # (K,) offsets, row-major
    K = window_u.numel()
    dilations = range(dilation_max, 0, -1)
    # per dilation: flat row offsets of the window and its moves in u and v
    row_offsets = {dil: dil * (window_v * Wp + window_u) for dil in dilations}
    move_u = {dil: dil * window_u for dil in dilations}
    move_v = {dil: dil * window_v for dil in dilations}
    refined = pixel.reshape(B * P, 2).clone()
    rows_of = torch.arange(B * P, device=pixel.device)
    if active is not None:
        rows_of = rows_of[active.reshape(-1)]
    u_all, v_all = refined[rows_of, 0].contiguous(), refined[rows_of, 1].contiguous()
    # flat row of pixel (0, 0) of each match's padded image
    origin = torch.div(rows_of, P, rounding_mode="floor") * (Hp * Wp) + margin * Wp + margin
    query = D_query.reshape(B * P, d)[rows_of].to(_SCORE_DTYPE)
    # the dot products as an in-place product and one matrix-vector sum over d: 1.3-1.7x
    # faster than torch.linalg.vecdot (a product tensor plus a reduction over a short last
    # dimension), same scores; the gathered candidates reuse one buffer, laid out window
    # offset major (K, n, d) so the product with the queries (n, d) is between operands of
    # one shape, no broadcast inside a row (1.3x over (n, K, d) on one core)
    ones = torch.ones(d, 1, dtype=_SCORE_DTYPE, device=pixel.device)
    buffer = torch.empty(min(chunk, u_all.shape[0]) * K, d, dtype=_SCORE_DTYPE, device=pixel.device)
    for start in range(0, u_all.shape[0], chunk):
        sl = slice(start, start + chunk)
        q, u, v, origin_c = query[sl], u_all[sl], v_all[sl], origin[sl]
        n = q.shape[0]
        candidates = buffer[: n * K]
        for dil in dilations:
            rows = (row_offsets[dil][:, None] + (origin_c + v * Wp + u)).reshape(-1)
            torch.index_select(table, 0, rows, out=candidates)
            candidates.view(K, n, d).mul_(q)
            # max(dim).indices is the first maximum, as argmax, and twice as fast on CPU
            best = torch.mm(candidates, ones).view(K, n).max(dim=0).indices
            u = (u + move_u[dil][best]).clamp_(0, W - 1)
            v = (v + move_v[dil][best]).clamp_(0, H - 1)
        u_all[sl], v_all[sl] = u, v
    refined[rows_of, 0], refined[rows_of, 1] = u_all, v_all
    return refined.reshape(B, P, 2)


def match_pointmaps(
    X_search: Tensor,
    X_query: Tensor,
    D_search: Tensor,
    D_query: Tensor,
    config: MatchingConfig,
    p_init: Tensor | None = None,
) -> Matches:
    """Match every query point to a pixel of the searched view (C-Eq. 1).

    Both pointmaps are in the searched view's camera frame: ``X_search`` is that view's
    own pointmap, ``X_query`` the other view's points as the prior placed them.

    Args:
        X_search: ``(B, H, W, 3)`` pointmap of the searched view.
        X_query: ``(B, Hq, Wq, 3)`` query points (P = Hq * Wq).
        D_search: ``(B, H, W, d)`` unit descriptors of the searched view.
        D_query: ``(B, Hq, Wq, d)`` unit descriptors of the query pixels.
        config: matching parameters.
        p_init: ``(B, P, 2)`` float warm start (previous frame's matches); defaults to the
            query pixel's own coordinates.

    Returns:
        :class:`Matches` with ``P = Hq * Wq`` entries per pair.
    """
    B, H, W, _ = X_search.shape
    Hq, Wq = X_query.shape[1:3]
    queries = X_query.reshape(B, Hq * Wq, 3)
    if p_init is None:
        v, u = torch.meshgrid(
            torch.arange(Hq, device=X_query.device),
            torch.arange(Wq, device=X_query.device),
            indexing="ij",
        )
        grid = torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1).to(X_query.dtype)
        upper = torch.tensor([W - 1, H - 1], dtype=X_query.dtype, device=X_query.device)
        p_init = grid.minimum(upper).expand(B, -1, -1)
    pixel, converged = project_to_pixels(
        ray_image_with_gradients(X_search),
        psi(queries),
        p_init.to(X_query.dtype),
        config.max_iters,
        config.lambda_init,
        config.convergence_tol,
    )
    finite = torch.isfinite(queries).all(-1)
    if config.descriptor_radius > 0:
        # both given at the paper's 512 px and scaled with the image (units.py), the radius
        # never below the paper's (MatchingConfig says why); only matches that can be valid
        # (converged, finite query) are refined
        long_side = max(H, W)
        refinable = converged & finite
        searched = refine_with_descriptors(
            D_search,
            D_query.reshape(B, Hq * Wq, -1),
            pixel,
            pixels_at(config.descriptor_radius, long_side, minimum=config.descriptor_radius),
            pixels_at(config.descriptor_dilation_max, long_side),
            active=refinable,
        )
        window = consensus_window(long_side) if config.descriptor_consensus else 1
        if window > 1:
            pixel = displacement_consensus(pixel, searched, refinable, (Hq, Wq), (H, W), window)
        else:
            pixel = searched
    if X_search.device.type == "cpu":  # the same test in one compiled pass
        idx, valid = cpu_kernels.match_validity(
            X_search, queries, pixel, converged, config.occlusion_ratio
        )
        return Matches(idx=idx, pixel=pixel, valid=valid)
    idx = pixel[..., 1] * W + pixel[..., 0]
    matched_points = torch.gather(
        X_search.reshape(B, H * W, 3), 1, idx[..., None].expand(-1, -1, 3)
    )
    # occlusion gap relative to the query's range: the same test at every scene scale
    gap = (matched_points - queries).norm(dim=-1)
    not_occluded = gap < config.occlusion_ratio * queries.norm(dim=-1)
    return Matches(idx=idx, pixel=pixel, valid=converged & not_occluded & finite)


def match_confidence(Q_query: Tensor, Q_search: Tensor, idx: Tensor) -> Tensor:
    """Per-match confidence ``q = sqrt(Q_query[m] * Q_search[n])`` (C-Sec. 3.3).

    Args:
        Q_query: ``(B, P)`` descriptor confidence of the query pixels m.
        Q_search: ``(B, H, W)`` descriptor confidence of the searched view.
        idx: ``(B, P)`` matched linear pixel n per query pixel.

    Returns:
        ``(B, P)`` confidences.
    """
    Q_matched = torch.gather(Q_search.reshape(Q_search.shape[0], -1), 1, idx)
    return torch.sqrt(Q_query * Q_matched)
