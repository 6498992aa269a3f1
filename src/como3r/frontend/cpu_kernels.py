"""Compiled CPU loops of dense matching (C-Eq. 1, C-Sec. 3.3), one per pixel.

On a GPU the vectorised PyTorch of :mod:`como3r.frontend.matching` runs the whole batch at
once; on a CPU it is memory bound: it materialises every candidate of every window (the
descriptor search gathers 245 rows of ``d`` floats per pixel) and reads them back three
times. These loops, compiled by numba (:mod:`como3r.jit`), keep each pixel's
work in registers, as MASt3R-SLAM's CUDA kernels do per thread, and run the pixels in
parallel over ``torch.get_num_threads()`` threads. Same equations, same candidate order and
tie rule as the PyTorch code (tests compare the two).

Measured at 512x384 (``benchmarks/matching_kernel.py``, AMD EPYC with AVX-512): the window
search 0.236 s against 0.804 s for the PyTorch path on one thread (0.118 / 0.571 s on two),
the ray projection 0.045 / 0.154 s; in a whole front-end run (``benchmarks/slam_vs_prior.py``,
12 frames of a 640x480 scene, one thread) matching went from 595 to 242 ms per call. On an
AVX2-only EPYC the window search took 0.54 against 1.73 s.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled

#: reassociation lets the 24-term dot products vectorise; no flag that assumes finite values
_FAST_SUMS = {"reassoc", "contract"}


def _refine_windows(table: np.ndarray, height: int, width: int, query: np.ndarray,
                    pixel: np.ndarray, rows: np.ndarray, per_image: int, radius: int,
                    dilation_max: int, out: np.ndarray) -> None:  # pragma: no cover (compiled)
    d = query.shape[1]
    for k in prange(rows.shape[0]):
        row = rows[k]
        first = (row // per_image) * height * width
        q = query[row]
        u, v = pixel[row, 0], pixel[row, 1]
        for dil in range(dilation_max, 0, -1):
            best = np.float32(-np.inf)
            best_u, best_v = u, v
            for j in range(-radius, radius + 1):  # window rows, then columns: row-major
                line = first + min(max(v + dil * j, 0), height - 1) * width
                for i in range(-radius, radius + 1):
                    candidate = table[line + min(max(u + dil * i, 0), width - 1)]
                    score = np.float32(0.0)
                    for c in range(d):
                        score += candidate[c] * q[c]
                    if score > best:  # strict: the first maximum wins
                        best, best_u, best_v = score, u + dil * i, v + dil * j
            u = min(max(best_u, 0), width - 1)
            v = min(max(best_v, 0), height - 1)
        out[row, 0], out[row, 1] = u, v


def refine_windows(D_search: Tensor, D_query: Tensor, pixel: Tensor, radius: int,
                   dilation_max: int, active: Tensor | None) -> Tensor:
    """:func:`como3r.frontend.matching.refine_with_descriptors` on CPU tensors.

    Scores in float32 like the PyTorch path; window pixels outside the image count as the
    nearest border pixel. Shapes as there: ``D_search (B, H, W, d)``, ``D_query (B, P, d)``,
    ``pixel (B, P, 2)`` int64, ``active (B, P)`` bool or None; returns ``(B, P, 2)`` int64.
    """
    B, H, W, d = D_search.shape
    P = pixel.shape[1]
    table = D_search.detach().to(torch.float32).reshape(B * H * W, d).contiguous().numpy()
    query = D_query.detach().to(torch.float32).reshape(B * P, d).contiguous().numpy()
    start = pixel.detach().reshape(B * P, 2).to(torch.int64).contiguous().numpy()
    refined = start.copy()
    rows = (np.arange(B * P, dtype=np.int64) if active is None
            else np.flatnonzero(active.detach().reshape(-1).numpy()).astype(np.int64))
    search = compiled(_refine_windows, fastmath=_FAST_SUMS)
    search(table, H, W, query, start, rows, P, radius, dilation_max, refined)
    return torch.from_numpy(refined).reshape(B, P, 2)


@njit(cache=True, boundscheck=False)
def _ray_sample(table: np.ndarray, first: int, height: int, width: int, u: float, v: float,
                target: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    """Bilinear ray and gradients at (u, v), clamped into the image, as
    ``matching._bilinear``; returns ``(cost, err (3,), d/du (3,), d/dv (3,))`` as scalars
    (a tuple, no array allocated per sample)."""
    u = min(max(u, 0.0), width - 1.0)
    v = min(max(v, 0.0), height - 1.0)
    u0 = min(int(np.floor(u)), max(width - 2, 0))
    v0 = min(int(np.floor(v)), max(height - 2, 0))
    u1, v1 = min(u0 + 1, width - 1), min(v0 + 1, height - 1)
    a, b = u - u0, v - v0
    w00, w01, w10, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
    p00, p01 = table[first + v0 * width + u0], table[first + v0 * width + u1]
    p10, p11 = table[first + v1 * width + u0], table[first + v1 * width + u1]

    def mix(c: int) -> float:
        return (float(p00[c]) * w00 + float(p01[c]) * w01 + float(p10[c]) * w10
                + float(p11[c]) * w11)

    r0, r1, r2 = mix(0), mix(1), mix(2)
    norm = max(np.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-12)
    e0, e1, e2 = r0 / norm - target[0], r1 / norm - target[1], r2 / norm - target[2]
    return (e0 * e0 + e1 * e1 + e2 * e2, (e0, e1, e2), (mix(3), mix(4), mix(5)),
            (mix(6), mix(7), mix(8)))


@njit(cache=True, boundscheck=False)
def _nearest_pixel(table: np.ndarray, first: int, height: int, width: int, u: float, v: float,
                   target: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    """Of the four pixel centres around (u, v), the one whose ray is closest to the target
    (the first of equals in the order (0, 0), (1, 0), (0, 1), (1, 1)), as
    ``matching._nearest_ray_pixel``."""
    best, best_u, best_v = np.inf, 0, 0
    base_u, base_v = int(np.floor(u)), int(np.floor(v))
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        cu = min(max(base_u + du, 0), width - 1)
        cv = min(max(base_v + dv, 0), height - 1)
        ray = table[first + cv * width + cu]
        err = 0.0
        for c in range(3):
            diff = float(ray[c]) - target[c]
            err += diff * diff
        if err < best:
            best, best_u, best_v = err, cu, cv
    return best_u, best_v


def _project_rays(table: np.ndarray, height: int, width: int, target: np.ndarray,
                  start: np.ndarray, per_image: int, max_iters: int, lambda_init: float,
                  tol: float, pixel: np.ndarray, nearest: np.ndarray, cost_out: np.ndarray
                  ) -> None:  # pragma: no cover (compiled)
    for row in prange(start.shape[0]):
        first = (row // per_image) * height * width
        t = target[row]
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
            new_cost, new_err, new_J_u, new_J_v = _ray_sample(table, first, height, width,
                                                              cand_u, cand_v, t)
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


def project_rays(rays_grad: Tensor, target_rays: Tensor, p_init: Tensor, max_iters: int,
                 lambda_init: float, convergence_tol: float
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
    project(table, H, W, target, start, P, max_iters, lambda_init, convergence_tol, pixel,
            nearest, cost)
    p = torch.from_numpy(pixel).to(p_init.dtype).reshape(B, P, 2)
    return (p, torch.from_numpy(nearest).reshape(B, P, 2),
            torch.from_numpy(cost < convergence_tol).reshape(B, P))
