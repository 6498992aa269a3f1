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
    ``matching._bilinear``; returns ``(cost, err (3,), d/du (3,), d/dv (3,))``."""
    u = min(max(u, 0.0), width - 1.0)
    v = min(max(v, 0.0), height - 1.0)
    u0 = min(int(np.floor(u)), max(width - 2, 0))
    v0 = min(int(np.floor(v)), max(height - 2, 0))
    u1, v1 = min(u0 + 1, width - 1), min(v0 + 1, height - 1)
    a, b = u - u0, v - v0
    top, bottom = first + v0 * width, first + v1 * width
    s = np.empty(9)
    for c in range(9):
        upper = table[top + u0, c] * (1 - a) + table[top + u1, c] * a
        lower = table[bottom + u0, c] * (1 - a) + table[bottom + u1, c] * a
        s[c] = upper * (1 - b) + lower * b
    norm = max(np.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]), 1e-12)
    err = np.empty(3)
    for c in range(3):
        err[c] = s[c] / norm - target[c]
    return (err[0] * err[0] + err[1] * err[1] + err[2] * err[2]), err, s[3:6], s[6:9]


def _project_rays(table: np.ndarray, height: int, width: int, target: np.ndarray,
                  start: np.ndarray, per_image: int, max_iters: int, lambda_init: float,
                  tol: float, pixel: np.ndarray, cost_out: np.ndarray
                  ) -> None:  # pragma: no cover (compiled)
    for row in prange(start.shape[0]):
        first = (row // per_image) * height * width
        t = target[row]
        u, v = start[row, 0], start[row, 1]
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
        cost_out[row] = cost


def project_rays(rays_grad: Tensor, target_rays: Tensor, p_init: Tensor, max_iters: int,
                 lambda_init: float, convergence_tol: float) -> tuple[Tensor, Tensor]:
    """:func:`como3r.frontend.matching.project_iteratively` on CPU tensors, per pixel in
    float64 (the PyTorch path computes in the pointmap's dtype). Shapes as there."""
    B, H, W, C = rays_grad.shape
    P = target_rays.shape[1]
    table = rays_grad.detach().reshape(B * H * W, C).to(torch.float64).contiguous().numpy()
    target = target_rays.detach().reshape(B * P, 3).to(torch.float64).contiguous().numpy()
    start = p_init.detach().reshape(B * P, 2).to(torch.float64).contiguous().numpy()
    pixel, cost = np.empty_like(start), np.empty(B * P)
    project = compiled(_project_rays)
    project(table, H, W, target, start, P, max_iters, lambda_init, convergence_tol, pixel, cost)
    p = torch.from_numpy(pixel).to(p_init.dtype).reshape(B, P, 2)
    return p, torch.from_numpy(cost < convergence_tol).reshape(B, P)
