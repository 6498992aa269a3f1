"""Compiled CPU linearization of the dense relative-pose factors (C-Eq. 6-10, 17-18).

:class:`~como3r.optim.factors.RayRangeFactors` and :class:`~como3r.optim.factors.
CalibratedFactors` sum, over every match of an edge, ``H = J^T W J`` and ``g = J^T W e`` in
the tangent of ``T_ij`` (C-Sec. A.1-A.2, B.2). PyTorch on a CPU materialises per-match
residuals, Jacobians and weights for millions of matches and reads them back several times;
these loops keep one match's residual, Huber weights and Jacobian rows in registers and add
them to the edge's 7x7 sums, as MASt3R-SLAM's CUDA kernels do per thread. The matches of an
edge are cut into blocks of :data:`BLOCK` (one parallel task each), and the block sums are
added in block order, so the result does not depend on the thread count. Everything per
match runs in float64 (the PyTorch path computes in the matches' dtype).

Same equations as :mod:`como3r.geometry.residuals`; tests compare both paths and autograd.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.geometry.lie import quat_to_matrix
from como3r.jit import compiled

#: matches per parallel task (the partial sums of a block are added in a fixed order)
BLOCK = 4096
#: norms and depths are clamped to this before dividing, as geometry.residuals does
_MIN_NORM = 1e-12
#: reassociation and fused multiply-adds let the per-match sums vectorise; no flag that
#: assumes finite values
_FAST_SUMS = {"reassoc", "contract"}
#: the upper triangle of a 7x7 block, row by row: the 28 accumulated Hessian entries
_TRIU = torch.triu_indices(7, 7)


@njit(cache=True, inline="always")
def _add_row(acc: np.ndarray, row: np.ndarray, weight: float,
             weighted_residual: float) -> None:  # pragma: no cover (compiled)
    """``acc[:28] += weight * row row^T`` (upper triangle), ``acc[28:] += weighted_residual
    * row`` for one Jacobian row ``(7,)``."""
    k = 0
    for a in range(7):
        scaled = weight * row[a]
        for b in range(a, 7):
            acc[k] += scaled * row[b]
            k += 1
        acc[28 + a] += weighted_residual * row[a]


@njit(cache=True, inline="always")
def _add_component(acc: np.ndarray, row: np.ndarray, error: float, info: float,
                   k: float) -> None:  # pragma: no cover (compiled)
    """One residual component with Jacobian ``row (7,)``: whitened by ``info`` (C-Eq. 7),
    weighted by its Huber IRLS weight (C-Sec. A.1), added to ``acc`` (:func:`_add_row`)."""
    whitened = error * info
    w = _huber(whitened, k) * info
    _add_row(acc, row, w * info, w * whitened)


@njit(cache=True, inline="always")
def _huber(whitened: float, k: float) -> float:  # pragma: no cover (compiled)
    """IRLS weight ``min(1, k / |r|)`` of the Huber kernel (C-Sec. A.1)."""
    return k / max(abs(whitened), k)


@njit(cache=True, inline="always")
def _rho(whitened: float, k: float) -> float:  # pragma: no cover (compiled)
    """Huber cost: ``r^2 / 2`` inside the breakpoint, ``k (|r| - k / 2)`` beyond."""
    a = abs(whitened)
    return 0.5 * a * a if a <= k else k * (a - 0.5 * k)


@njit(cache=True, inline="always")
def _transform(sR: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple:  # pragma: no cover
    return (sR[0, 0] * X[0] + sR[0, 1] * X[1] + sR[0, 2] * X[2] + t[0],
            sR[1, 0] * X[0] + sR[1, 1] * X[1] + sR[1, 2] * X[2] + t[1],
            sR[2, 0] * X[0] + sR[2, 1] * X[1] + sR[2, 2] * X[2] + t[2])


@njit(cache=True, inline="always")
def _ray_range_error(sR: np.ndarray, t: np.ndarray, X_i: np.ndarray, X_j: np.ndarray,
                     e: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    """C-Eq. 6 into ``e (4,)``: ``[psi(T X_j) - psi(X_i); ||T X_j|| - ||X_i||]``; returns
    ``(d, r0, r1, r2)`` with ``d = ||T X_j||`` and ``r = T X_j / d``."""
    x0, x1, x2 = _transform(sR, t, X_j)
    d = max(math.sqrt(x0 * x0 + x1 * x1 + x2 * x2), _MIN_NORM)
    r0, r1, r2 = x0 / d, x1 / d, x2 / d
    d_i = max(math.sqrt(X_i[0] * X_i[0] + X_i[1] * X_i[1] + X_i[2] * X_i[2]), _MIN_NORM)
    e[0], e[1], e[2], e[3] = r0 - X_i[0] / d_i, r1 - X_i[1] / d_i, r2 - X_i[2] / d_i, d - d_i
    return d, r0, r1, r2


@njit(cache=True, inline="always")
def _calibrated_error(sR: np.ndarray, t: np.ndarray, K: np.ndarray, X_j: np.ndarray,
                      p_i: np.ndarray, z_i: float,
                      e: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    """C-Eq. 17 into ``e (3,)``: ``[Pi_K(T X_j) - p_i; log z(T X_j) - log z_i]``; returns
    ``(x0, x1, x2, 1 / z, u, v)`` with ``x = T X_j`` (z clamped) and its pixel."""
    x0, x1, x2 = _transform(sR, t, X_j)
    inv_z = 1.0 / max(x2, _MIN_NORM)
    u = K[0, 0] * x0 * inv_z + K[0, 1] * x1 * inv_z + K[0, 2]
    v = K[1, 1] * x1 * inv_z + K[1, 2]
    e[0], e[1] = u - p_i[0], v - p_i[1]
    e[2] = math.log(max(x2, _MIN_NORM)) - math.log(max(z_i, _MIN_NORM))
    return x0, x1, x2, inv_z, u, v


def _ray_range_blocks(sR, t, X_i, X_j, q, valid, inv_sigma, k, block,
                      out):  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        acc = np.zeros(35)
        e = np.empty(4)
        row = np.empty(7)
        for m in range(first, min(first + block, P)):
            if not valid[edge, m]:
                continue
            d, r0, r1, r2 = _ray_range_error(sR[edge], t[edge], X_i[edge, m], X_j[edge, m], e)
            s = math.sqrt(q[edge, m])
            # ray rows (C-Eq. 9-10): [(I - r r^T) / d, -[r]_x, 0]
            for c, r_c, s0, s1, s2 in ((0, r0, 0.0, r2, -r1), (1, r1, -r2, 0.0, r0),
                                       (2, r2, r1, -r0, 0.0)):
                row[0], row[1], row[2] = -r_c * r0 / d, -r_c * r1 / d, -r_c * r2 / d
                row[c] += 1.0 / d
                row[3], row[4], row[5], row[6] = s0, s1, s2, 0.0
                _add_component(acc, row, e[c], s * inv_sigma[edge, c], k)
            # range row: [r^T, 0, d]
            row[0], row[1], row[2] = r0, r1, r2
            row[3], row[4], row[5], row[6] = 0.0, 0.0, 0.0, d
            _add_component(acc, row, e[3], s * inv_sigma[edge, 3], k)
        out[task] = acc


def _calibrated_blocks(sR, t, K, X_j, p_i, z_i, q, valid, inv_sigma, k, block,
                       out):  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        fx, skew, fy = K[edge, 0, 0], K[edge, 0, 1], K[edge, 1, 1]
        acc = np.zeros(35)
        e = np.empty(3)
        row = np.empty(7)
        for m in range(first, min(first + block, P)):
            if not valid[edge, m]:
                continue
            x0, x1, x2, inv_z, u, v = _calibrated_error(sR[edge], t[edge], K[edge],
                                                        X_j[edge, m], p_i[edge, m],
                                                        z_i[edge, m], e)
            if not x2 > 0:
                continue  # Pi_K and log z exist only in front of camera i
            s = math.sqrt(q[edge, m])
            # rows j_c of d e_c / d x composed with [I, -[x]_x, x]: [j_c, x cross j_c, j_c . x]
            for c, j0, j1, j2 in ((0, fx * inv_z, skew * inv_z, (K[edge, 0, 2] - u) * inv_z),
                                  (1, 0.0, fy * inv_z, (K[edge, 1, 2] - v) * inv_z),
                                  (2, 0.0, 0.0, inv_z)):
                row[0], row[1], row[2] = j0, j1, j2
                row[3] = x1 * j2 - x2 * j1
                row[4] = x2 * j0 - x0 * j2
                row[5] = x0 * j1 - x1 * j0
                row[6] = x2 * inv_z if c == 2 else 0.0
                _add_component(acc, row, e[c], s * inv_sigma[edge, c], k)
        out[task] = acc


def _ray_range_cost(sR, t, X_i, X_j, q, valid, inv_sigma, k, block,
                    out):  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        total = 0.0
        e = np.empty(4)
        for m in range(first, min(first + block, P)):
            if valid[edge, m]:
                _ray_range_error(sR[edge], t[edge], X_i[edge, m], X_j[edge, m], e)
                s = math.sqrt(q[edge, m])
                for c in range(4):
                    total += _rho(e[c] * s * inv_sigma[edge, c], k)
        out[task] = total


def _calibrated_cost(sR, t, K, X_j, p_i, z_i, q, valid, inv_sigma, k, block,
                     out):  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        total = 0.0
        e = np.empty(3)
        for m in range(first, min(first + block, P)):
            if valid[edge, m]:
                x2 = _calibrated_error(sR[edge], t[edge], K[edge], X_j[edge, m],
                                       p_i[edge, m], z_i[edge, m], e)[2]
                if x2 > 0:
                    s = math.sqrt(q[edge, m])
                    for c in range(3):
                        total += _rho(e[c] * s * inv_sigma[edge, c], k)
        out[task] = total


def _pose_arrays(T_ij: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``s R`` ``(e, 3, 3)`` and ``t`` ``(e, 3)`` float64 of poses ``T_ij`` ``(e, 8)``."""
    T = T_ij.detach().to(torch.float64)
    sR = T[:, 7:, None] * quat_to_matrix(T[:, 3:7])
    return sR.contiguous().numpy(), T[:, :3].contiguous().numpy()


def _array(x: Tensor) -> np.ndarray:
    return x.detach().contiguous().numpy()


def _sums(loop, T_ij: Tensor, data: tuple[Tensor, ...], q: Tensor, valid: Tensor,
          inv_sigma: Tensor, huber_k: float, width: int) -> np.ndarray:
    """Run ``loop`` over the edges' match blocks; per-edge sums ``(e, width)`` float64."""
    E, P = q.shape
    blocks = -(-P // BLOCK)
    out = np.empty((E * blocks, width)) if width > 1 else np.empty(E * blocks)
    compiled(loop, fastmath=_FAST_SUMS)(*_pose_arrays(T_ij), *(_array(x) for x in data), _array(q), _array(valid),
                   _array(inv_sigma.to(torch.float64)), float(huber_k), BLOCK, out)
    return out.reshape(E, blocks, width).sum(1)


def _blocks(sums: np.ndarray) -> tuple[Tensor, Tensor]:
    """``H (e, 7, 7)`` from the accumulated upper triangles and ``g (e, 7)``."""
    sums_t = torch.from_numpy(sums)
    H = sums_t.new_zeros(sums.shape[0], 7, 7)
    H[:, _TRIU[0], _TRIU[1]] = sums_t[:, :28]
    H[:, _TRIU[1], _TRIU[0]] = sums_t[:, :28]
    return H, sums_t[:, 28:]


def ray_range_blocks(T_ij: Tensor, X_i: Tensor, X_j: Tensor, q: Tensor, valid: Tensor,
                     inv_sigma: Tensor, huber_k: float) -> tuple[Tensor, Tensor]:
    """``H = J^T W J`` ``(e, 7, 7)`` and ``g = J^T W e`` ``(e, 7)`` float64 of C-Eq. 6 per edge.

    Args:
        T_ij: ``(e, 8)`` relative poses.
        X_i, X_j: ``(e, P, 3)`` matched points in cameras i and j.
        q: ``(e, P)`` confidences (zero where ``valid`` is False); valid: ``(e, P)`` bool.
        inv_sigma: ``(e, 4)`` inverse noise of the three ray and the range components.
        huber_k: Huber breakpoint on whitened components.
    """
    H_and_g = _sums(_ray_range_blocks, T_ij, (X_i, X_j), q, valid, inv_sigma, huber_k, 35)
    return _blocks(H_and_g)


def calibrated_blocks(T_ij: Tensor, K: Tensor, X_j: Tensor, p_i: Tensor, z_i: Tensor,
                      q: Tensor, valid: Tensor, inv_sigma: Tensor,
                      huber_k: float) -> tuple[Tensor, Tensor]:
    """``H`` ``(e, 7, 7)`` and ``g`` ``(e, 7)`` float64 of C-Eq. 17 per edge; matches behind
    camera i at ``T_ij`` count nothing.

    Args:
        T_ij: ``(e, 8)``; K: ``(e, 3, 3)`` intrinsics of camera i; X_j: ``(e, P, 3)``;
        p_i: ``(e, P, 2)`` observed pixels; z_i: ``(e, P)`` observed depths; q, valid as in
        :func:`ray_range_blocks`; inv_sigma: ``(e, 3)`` (pixel u, v and log-depth).
    """
    K64 = K.detach().to(torch.float64)
    H_and_g = _sums(_calibrated_blocks, T_ij, (K64, X_j, p_i, z_i), q, valid, inv_sigma,
                    huber_k, 35)
    return _blocks(H_and_g)


def ray_range_cost(T_ij: Tensor, X_i: Tensor, X_j: Tensor, q: Tensor, valid: Tensor,
                   inv_sigma: Tensor, huber_k: float) -> Tensor:
    """Robust energy ``sum rho(r)`` of C-Eq. 6 over the edges, a float64 scalar (arguments
    as in :func:`ray_range_blocks`)."""
    per_edge = _sums(_ray_range_cost, T_ij, (X_i, X_j), q, valid, inv_sigma, huber_k, 1)
    return torch.tensor(float(per_edge.sum()), dtype=torch.float64)


def calibrated_cost(T_ij: Tensor, K: Tensor, X_j: Tensor, p_i: Tensor, z_i: Tensor,
                    q: Tensor, valid: Tensor, inv_sigma: Tensor, huber_k: float) -> Tensor:
    """Robust energy of C-Eq. 17 over the edges, a float64 scalar (arguments as in
    :func:`calibrated_blocks`)."""
    K64 = K.detach().to(torch.float64)
    per_edge = _sums(_calibrated_cost, T_ij, (K64, X_j, p_i, z_i), q, valid, inv_sigma,
                     huber_k, 1)
    return torch.tensor(float(per_edge.sum()), dtype=torch.float64)
