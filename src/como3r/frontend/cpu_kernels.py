"""Compiled CPU loops of dense matching (C-Eq. 1, C-Sec. 3.3), one per pixel.

On a GPU the vectorised PyTorch of :mod:`como3r.frontend.matching` runs the whole batch at
once; on a CPU it is memory bound: it materialises every candidate of every window (the
descriptor search gathers 245 rows of ``d`` floats per pixel) and reads them back three
times. These loops, compiled by numba (:mod:`como3r.jit`), keep each pixel's
work in registers, as MASt3R-SLAM's CUDA kernels do per thread, and run the pixels in
parallel over ``torch.get_num_threads()`` threads. Same equations, same candidate order and
tie rule as the PyTorch code (tests compare the two).

The window search (:func:`~como3r.frontend.cpu_window_search.refine_windows`) scores 8
candidates of a window row at once in explicit 8-lane vectors
(:mod:`como3r.frontend.cpu_window_search`).

Measured at 512x384 (``benchmarks/matching_kernel.py``, AMD EPYC with AVX-512, one thread,
one run on a shared machine): the window search 0.094 s against 0.858 s for the PyTorch path
(9.1x; the previous compiled loop, one dot product at a time, was 4.8x faster than it: 0.455
/ 2.19 s in a busier run), the ray projection 0.024 / 0.189 s. In a whole front-end run
(``benchmarks/slam_vs_prior.py``, 15 frames of the 640x480 scene of its docstring, one
thread) matching took 103-104 ms per call against 186-196 before the window search and these
changes (09379f6, same machine, alternating runs); the projection 74 instead of 88 ms per
frame once its samples were inlined, the ray image 7 instead of 12.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled


@njit(cache=True, boundscheck=False, inline="always")
def _ray_sample(
    table: np.ndarray, first: int, height: int, width: int, u: float, v: float, target: tuple
) -> tuple:  # pragma: no cover (compiled)
    """Bilinear ray and gradients at (u, v), clamped into the image, as
    ``matching._bilinear``; returns ``(cost, err (3,), d/du (3,), d/dv (3,))`` as scalars
    (a tuple, no array allocated per sample). Inlined, the target ray ``(3,)`` a tuple and
    the table read by index: a row view passed or made per sample counts references
    (atomically), and the call was not inlined: 13-16 % of the projection's time."""
    u = min(max(u, 0.0), width - 1.0)
    v = min(max(v, 0.0), height - 1.0)
    u0 = min(int(np.floor(u)), max(width - 2, 0))
    v0 = min(int(np.floor(v)), max(height - 2, 0))
    u1, v1 = min(u0 + 1, width - 1), min(v0 + 1, height - 1)
    a, b = u - u0, v - v0
    w00, w01, w10, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
    i00, i01 = first + v0 * width + u0, first + v0 * width + u1
    i10, i11 = first + v1 * width + u0, first + v1 * width + u1

    def mix(c: int) -> float:
        return (
            float(table[i00, c]) * w00
            + float(table[i01, c]) * w01
            + float(table[i10, c]) * w10
            + float(table[i11, c]) * w11
        )

    r0, r1, r2 = mix(0), mix(1), mix(2)
    norm = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
    e0, e1, e2 = r0 / norm - target[0], r1 / norm - target[1], r2 / norm - target[2]
    return (
        e0 * e0 + e1 * e1 + e2 * e2,
        (e0, e1, e2),
        (mix(3), mix(4), mix(5)),
        (mix(6), mix(7), mix(8)),
    )


@njit(cache=True, boundscheck=False, inline="always")
def _nearest_pixel(
    table: np.ndarray, first: int, height: int, width: int, u: float, v: float, target: tuple
) -> tuple:  # pragma: no cover (compiled)
    """Of the four pixel centres around (u, v), the one whose ray is closest to the target
    (the first of equals in the order (0, 0), (1, 0), (0, 1), (1, 1)), as
    ``matching._nearest_ray_pixel``."""
    best, best_u, best_v = np.inf, 0, 0
    base_u, base_v = int(np.floor(u)), int(np.floor(v))
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        cu = min(max(base_u + du, 0), width - 1)
        cv = min(max(base_v + dv, 0), height - 1)
        index = first + cv * width + cu
        err = 0.0
        for c in range(3):
            diff = float(table[index, c]) - target[c]
            err += diff * diff
        if err < best:
            best, best_u, best_v = err, cu, cv
    return best_u, best_v


@njit(cache=True, boundscheck=False)
def _project_pixels(
    table: np.ndarray,
    height: int,
    width: int,
    target: np.ndarray,
    start: np.ndarray,
    per_image: int,
    max_iters: int,
    lambda_init: float,
    tol: float,
    pixel: np.ndarray,
    nearest: np.ndarray,
    cost_out: np.ndarray,
    first_row: int,
    end_row: int,
) -> None:  # pragma: no cover (compiled)
    """The projection of pixels ``first_row`` to ``end_row`` (a serial loop: numba's
    parallel analysis does not take the inlined samples)."""
    for row in range(first_row, end_row):
        first = (row // per_image) * height * width
        t = (target[row, 0], target[row, 1], target[row, 2])
        u, v = float(start[row, 0]), float(start[row, 1])
        cost, err, J_u, J_v = _ray_sample(table, first, height, width, u, v, t)
        lam = lambda_init
        for _ in range(max_iters if not cost < tol else 0):
            a11 = J_u[0] * J_u[0] + J_u[1] * J_u[1] + J_u[2] * J_u[2] + lam
            a12 = J_u[0] * J_v[0] + J_u[1] * J_v[1] + J_u[2] * J_v[2]
            a22 = J_v[0] * J_v[0] + J_v[1] * J_v[1] + J_v[2] * J_v[2] + lam
            b1 = -(J_u[0] * err[0] + J_u[1] * err[1] + J_u[2] * err[2])
            b2 = -(J_v[0] * err[0] + J_v[1] * err[1] + J_v[2] * err[2])
            det = a11 * a22 - a12 * a12
            step_u = u + (a22 * b1 - a12 * b2) / det
            step_v = v + (a11 * b2 - a12 * b1) / det
            if not (np.isfinite(step_u) and np.isfinite(step_v)):
                break  # a singular system: the PyTorch path stops the pixel too
            cand_u = min(max(step_u, 0.0), width - 1.0)
            cand_v = min(max(step_v, 0.0), height - 1.0)
            new_cost, new_err, new_J_u, new_J_v = _ray_sample(
                table, first, height, width, cand_u, cand_v, t
            )
            better = new_cost < cost and np.isfinite(new_cost)
            if better:
                u, v, cost, err, J_u, J_v = cand_u, cand_v, new_cost, new_err, new_J_u, new_J_v
                lam *= 0.1
            else:
                lam *= 10.0
            if cost < tol or (not better and (cand_u != step_u or cand_v != step_v)):
                break  # converged, or pushed against the border without improving
        pixel[row, 0], pixel[row, 1] = u, v
        nearest[row, 0], nearest[row, 1] = _nearest_pixel(table, first, height, width, u, v, t)
        cost_out[row] = cost


#: pixels per parallel task of the ray projection
_PROJECT_BLOCK = 1024


def _project_rays(
    table: np.ndarray,
    height: int,
    width: int,
    target: np.ndarray,
    start: np.ndarray,
    per_image: int,
    max_iters: int,
    lambda_init: float,
    tol: float,
    pixel: np.ndarray,
    nearest: np.ndarray,
    cost_out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    P = start.shape[0]
    for block in prange((P + _PROJECT_BLOCK - 1) // _PROJECT_BLOCK):
        _project_pixels(
            table,
            height,
            width,
            target,
            start,
            per_image,
            max_iters,
            lambda_init,
            tol,
            pixel,
            nearest,
            cost_out,
            block * _PROJECT_BLOCK,
            min((block + 1) * _PROJECT_BLOCK, P),
        )


def project_rays(
    rays_grad: Tensor,
    target_rays: Tensor,
    p_init: Tensor,
    max_iters: int,
    lambda_init: float,
    convergence_tol: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`como3r.frontend.matching.project_iteratively` on CPU tensors, per pixel in
    float64 (the PyTorch path computes in the pointmap's dtype), followed by
    ``matching._nearest_ray_pixel``. Shapes as there.

    Returns:
        ``(p (B, P, 2) float, pixel (B, P, 2) int64, converged (B, P) bool)``: the continuous
        optimum, its nearest pixel centre by ray, and whether it converged.
    """
    B, H, W, C = rays_grad.shape
    P = target_rays.shape[1]
    table = rays_grad.detach().reshape(B * H * W, C).contiguous().numpy()
    target = target_rays.detach().reshape(B * P, 3).to(torch.float64).contiguous().numpy()
    start = p_init.detach().reshape(B * P, 2).contiguous().numpy()
    pixel, cost = np.empty((B * P, 2)), np.empty(B * P)
    nearest = np.empty((B * P, 2), dtype=np.int64)
    project = compiled(_project_rays)
    project(
        table, H, W, target, start, P, max_iters, lambda_init, convergence_tol, pixel, nearest, cost
    )
    p = torch.from_numpy(pixel).to(p_init.dtype).reshape(B, P, 2)
    return (
        p,
        torch.from_numpy(nearest).reshape(B, P, 2),
        torch.from_numpy(cost < convergence_tol).reshape(B, P),
    )


def _ray_image(X: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover (compiled)
    B, H, W, _ = X.shape
    for b in prange(B):
        for y in range(H):
            for x in range(W):
                x0, x1, x2 = X[b, y, x, 0], X[b, y, x, 1], X[b, y, x, 2]
                norm = max(np.sqrt(x2 * x2 + (x1 * x1 + x0 * x0)), 1e-12)
                out[b, y, x, 0], out[b, y, x, 1], out[b, y, x, 2] = x0 / norm, x1 / norm, x2 / norm
        for y in range(H):  # central differences, one-sided at the border (torch.gradient)
            below, above = max(y - 1, 0), min(y + 1, H - 1)
            v_scale = 1.0 if y == 0 or y == H - 1 else 0.5  # exact: halving is a division
            for x in range(W):
                left, right = max(x - 1, 0), min(x + 1, W - 1)
                u_scale = 1.0 if x == 0 or x == W - 1 else 0.5
                for c in range(3):
                    out[b, y, x, 3 + c] = (out[b, y, right, c] - out[b, y, left, c]) * u_scale
                    out[b, y, x, 6 + c] = (out[b, above, x, c] - out[b, below, x, c]) * v_scale


def ray_image_with_gradients(X: Tensor) -> Tensor:
    """:func:`como3r.frontend.matching.ray_image_with_gradients` of a CPU pointmap ``X``
    ``(B, H, W, 3)`` -> ``(B, H, W, 9)`` in one pass (PyTorch made 6 temporaries of the image):
    the norm summed as PyTorch's float32 norm does here, within an ulp of it."""
    image = X.detach().contiguous().numpy()
    out = np.empty((*image.shape[:3], 9), dtype=image.dtype)
    compiled(_ray_image, fastmath={"contract"})(image, out)
    return torch.from_numpy(out)


def _match_validity(
    X_search: np.ndarray,
    width: int,
    queries: np.ndarray,
    pixel: np.ndarray,
    converged: np.ndarray,
    ratio: float,
    idx: np.ndarray,
    valid: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    B, P = converged.shape
    for b in prange(B):
        for m in range(P):
            n = pixel[b, m, 1] * width + pixel[b, m, 0]
            idx[b, m] = n
            q0, q1, q2 = queries[b, m, 0], queries[b, m, 1], queries[b, m, 2]
            g0, g1, g2 = X_search[b, n, 0] - q0, X_search[b, n, 1] - q1, X_search[b, n, 2] - q2
            gap = np.sqrt(g2 * g2 + (g1 * g1 + g0 * g0))
            reach = ratio * np.sqrt(q2 * q2 + (q1 * q1 + q0 * q0))
            finite = np.isfinite(q0) and np.isfinite(q1) and np.isfinite(q2)
            valid[b, m] = converged[b, m] and gap < reach and finite


def match_validity(
    X_search: Tensor, queries: Tensor, pixel: Tensor, converged: Tensor, occlusion_ratio: float
) -> tuple[Tensor, Tensor]:
    """The end of :func:`como3r.frontend.matching.match_pointmaps` on CPU tensors, one pass:
    ``(idx (B, P) int64, valid (B, P) bool)``, a match valid when converged, its query finite
    and not occluded (``||X_search[idx] - query|| < occlusion_ratio * ||query||``).
    ``X_search`` ``(B, H, W, 3)``, ``queries`` ``(B, P, 3)``, ``pixel`` ``(B, P, 2)``."""
    B, H, W, _ = X_search.shape
    P = queries.shape[1]
    points = X_search.detach().reshape(B, H * W, 3).contiguous().numpy()
    idx, valid = np.empty((B, P), dtype=np.int64), np.empty((B, P), dtype=np.bool_)
    compiled(_match_validity, fastmath={"contract"})(
        points,
        W,
        queries.detach().to(X_search.dtype).contiguous().numpy(),
        pixel.detach().contiguous().numpy(),
        converged.detach().contiguous().numpy(),
        np.float32(occlusion_ratio) if points.dtype == np.float32 else occlusion_ratio,
        idx,
        valid,
    )
    return torch.from_numpy(idx), torch.from_numpy(valid)


@njit(cache=True, boundscheck=False)
def _pack_valid(
    X_i: np.ndarray,
    X_j: np.ndarray,
    idx: np.ndarray,
    valid: np.ndarray,
    q: np.ndarray,
    X_i_out: np.ndarray,
    X_j_out: np.ndarray,
    q_out: np.ndarray,
    valid_out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    k = 0
    for n in range(valid.shape[0]):
        if valid[n]:
            m = idx[n]
            for c in range(3):
                X_i_out[k, c] = X_i[m, c]
                X_j_out[k, c] = X_j[n, c]
            q_out[k] = q[n]
            valid_out[k] = True
            k += 1


def pack_valid(
    X_i: Tensor,
    X_j: Tensor,
    idx: Tensor,
    valid: Tensor,
    q: Tensor,
    X_i_out: Tensor,
    X_j_out: Tensor,
    q_out: Tensor,
    valid_out: Tensor,
) -> None:
    """An edge's valid matches written to the front of its rows of a factor batch, in pixel
    order, in one pass (PyTorch: a nonzero, three gathers and three copies): for each pixel
    ``n`` of j with ``valid[n]``, ``X_i[idx[n]]`` and ``X_j[n]`` of the flat ``(HW, 3)``
    pointmaps, ``q[n]`` and True. The outputs are CPU rows of the batch ``(P', 3)``,
    ``(P', 3)``, ``(P',)``, ``(P',)`` with ``P' >= valid.sum()``, contiguous, in the inputs'
    dtypes; their other rows are left as they are."""
    _pack_valid(
        X_i.contiguous().numpy(),
        X_j.contiguous().numpy(),
        idx.contiguous().numpy(),
        valid.contiguous().numpy(),
        q.contiguous().numpy(),
        X_i_out.numpy(),
        X_j_out.numpy(),
        q_out.numpy(),
        valid_out.numpy(),
    )


def _move_medians(
    moves: np.ndarray,
    active: np.ndarray,
    per_image: int,
    height: int,
    width: int,
    window: int,
    reach: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    """Per active match, the lower median per axis of the active moves ``(N, 2)`` (whole
    pixels, at most ``reach``) in the ``window x window`` block of query pixels around it, by
    counting: the moves are small integers."""
    half = window // 2
    values = 2 * reach + 1
    for line in prange(active.shape[0] // width):  # one query row of one image per task
        counts = np.zeros((2, values), np.int64)
        first = (line // height) * per_image
        v = line % height
        for u in range(width):
            row = first + v * width + u
            if not active[row]:
                continue
            votes = 0
            for b in range(max(v - half, 0), min(v + half + 1, height)):
                for a in range(max(u - half, 0), min(u + half + 1, width)):
                    other = first + b * width + a
                    if active[other]:
                        counts[0, moves[other, 0] + reach] += 1
                        counts[1, moves[other, 1] + reach] += 1
                        votes += 1
            need = (votes + 1) // 2
            for axis in range(2):
                seen = 0
                for k in range(values):
                    seen += counts[axis, k]
                    if seen >= need:
                        out[row, axis] = k - reach
                        break
                counts[axis, :] = 0


def move_medians(
    moves: Tensor, active: Tensor, query_shape: tuple[int, int], window: int
) -> Tensor:
    """:func:`como3r.frontend.match_consensus.displacement_consensus`'s medians on CPU tensors:
    ``moves (B, P, 2)`` int64, ``active (B, P)`` bool, ``P = Hq * Wq`` row-major ->
    ``(B, P, 2)`` int64 (0 where not active), the same values as the PyTorch median."""
    B, P, _ = moves.shape
    Hq, Wq = query_shape
    flat = moves.detach().reshape(B * P, 2).to(torch.int64).contiguous()
    on = active.detach().reshape(B * P)
    reach = int(flat[on].abs().max()) if bool(on.any()) else 0
    out = np.zeros((B * P, 2), np.int64)
    compiled(_move_medians)(flat.numpy(), on.numpy(), P, Hq, Wq, window, reach, out)
    return torch.from_numpy(out).reshape(B, P, 2)
