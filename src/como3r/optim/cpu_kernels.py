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

The calibrated loops (C-Eq. 17, what tracking, local solves and the global BA use with known
or settled intrinsics) vectorise over the matches of a block: a match is read through flat
1-D views (numba indexes a 3-D array by its runtime shape, which LLVM only vectorises for a
unit stride), invalid and behind-the-camera matches are masked instead of skipped, the
Hessian's 25 possibly non-zero entries and the gradient are scalar sums, and the log-depth
residuals come from a polynomial logarithm in a loop of their own (:func:`_log`; LLVM has no
vector ``log`` here). Measured on the 21 linearizations sampled from a 15-frame
``benchmarks/slam_vs_prior.py`` run (4.1 M matches, one thread, loaded 2-core AVX-512 EPYC,
one process alternating): 53-57 -> 15 ns per match, cost 22.5 -> 8.5 ns per match; in the
whole run tracking went from 152 to 84 and the local solve from 274 to 151 ms per frame.
They are also more exact: float32 confidences took a float32 square root, which left the
blocks 1e-9 off a float64 evaluation of the same inputs; now 1e-15.

Same equations as :mod:`como3r.geometry.residuals`; tests compare both paths and autograd.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled

#: matches per parallel task (the partial sums of a block are added in a fixed order)
BLOCK = 4096
#: norms and depths are clamped to this before dividing, as geometry.residuals does
_MIN_NORM = 1e-12
#: reassociation and fused multiply-adds let the per-match sums vectorise; no flag that
#: assumes finite values
_FAST_SUMS = {"reassoc", "contract"}
#: log 2 in two parts (the high one exact in a double's 33 leading bits), and sqrt 2
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_SQRT2 = 1.4142135623730951
#: the upper triangle of a 7x7 block, row by row: the 28 accumulated Hessian entries
_TRIU = np.triu_indices(7)

#: The calibrated residual (C-Eq. 17) counts a match only where ``T_ij`` brings its point of
#: keyframe j to at least this fraction of the depth observed in camera i. Nearer points make
#: the pixel Jacobian grow as ``1 / z^2`` (C-Eq. 18): on a 5,000-frame 64x48 loop a keyframe
#: placed 2.3 m off brought loop-edge points to just in front of its camera, their Hessian
#: entries reached 4e13 (7.8e19 assembled), no Tikhonov term made the system numerically
#: positive definite, and every later local solve returned a zero step. A quarter of the
#: observed depth is a log-depth residual of -1.39 (14 sigma at the default
#: ``tracking.sigma_depth`` of 0.1): an outlier already, and its Jacobian rows stay within
#: 16 times those of a match at its observed depth.
#: (The PyTorch path, optim.factors, reads it from here: numba bakes a global into the
#: machine code and keys its disk cache on this file only.)
MIN_DEPTH_RATIO = 0.25


@njit(cache=True, inline="always")
def _add_row(
    acc: np.ndarray, row: np.ndarray, weight: float, weighted_residual: float
) -> None:  # pragma: no cover (compiled)
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
def _add_component(
    acc: np.ndarray, row: np.ndarray, error: float, info: float, k: float
) -> None:  # pragma: no cover (compiled)
    """One residual component with Jacobian ``row (7,)``: whitened by ``info`` (C-Eq. 7),
    weighted by its Huber IRLS weight (C-Sec. A.1), added to ``acc`` (:func:`_add_row`)."""
    whitened = error * info
    w = _huber(whitened, k) * info
    _add_row(acc, row, w * info, w * whitened)


@njit(cache=True, inline="always")
def _huber(whitened: float, k: float) -> float:  # pragma: no cover (compiled)
    """IRLS weight ``min(1, k / |r|)`` of the Huber kernel (C-Sec. A.1)."""
    return k / max(abs(whitened), k)


@njit(cache=True, inline="always", error_model="numpy")
def _root_weight(error: float, info: float, k: float) -> float:  # pragma: no cover (compiled)
    """``info`` times the square root of the Huber weight of the whitened ``error * info``:
    a Jacobian row scaled by it adds ``w info^2 row row^T`` to H (C-Sec. A.1)."""
    return info * math.sqrt(k / max(abs(error * info), k))


@njit(cache=True, inline="always")
def _rho(whitened: float, k: float) -> float:  # pragma: no cover (compiled)
    """Huber cost: ``r^2 / 2`` inside the breakpoint, ``k (|r| - k / 2)`` beyond."""
    a = abs(whitened)
    return 0.5 * a * a if a <= k else k * (a - 0.5 * k)


@njit(cache=True, inline="always")
def _transform(sR: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple:  # pragma: no cover
    return (
        sR[0, 0] * X[0] + sR[0, 1] * X[1] + sR[0, 2] * X[2] + t[0],
        sR[1, 0] * X[0] + sR[1, 1] * X[1] + sR[1, 2] * X[2] + t[1],
        sR[2, 0] * X[0] + sR[2, 1] * X[1] + sR[2, 2] * X[2] + t[2],
    )


@njit(cache=True, inline="always")
def _ray_range_error(
    sR: np.ndarray, t: np.ndarray, X_i: np.ndarray, X_j: np.ndarray, e: np.ndarray
) -> tuple:  # pragma: no cover (compiled)
    """C-Eq. 6 into ``e (4,)``: ``[psi(T X_j) - psi(X_i); ||T X_j|| - ||X_i||]``; returns
    ``(d, r0, r1, r2)`` with ``d = ||T X_j||`` and ``r = T X_j / d``."""
    x0, x1, x2 = _transform(sR, t, X_j)
    d = max(math.sqrt(x0 * x0 + x1 * x1 + x2 * x2), _MIN_NORM)
    r0, r1, r2 = x0 / d, x1 / d, x2 / d
    y0, y1, y2 = np.float64(X_i[0]), np.float64(X_i[1]), np.float64(X_i[2])  # float32 inputs
    d_i = max(math.sqrt(y0 * y0 + y1 * y1 + y2 * y2), _MIN_NORM)
    e[0], e[1], e[2], e[3] = r0 - y0 / d_i, r1 - y1 / d_i, r2 - y2 / d_i, d - d_i
    return d, r0, r1, r2


@njit(cache=True, inline="always", error_model="numpy")
def _log(values: np.ndarray, out: np.ndarray, n: int) -> None:  # pragma: no cover (compiled)
    """``out[:n] = log(values[:n])`` for positive normal numbers, in loops that vectorise (no
    vector ``log`` in LLVM's library here): ``x = 2^e m``, ``m`` in ``[sqrt(1/2), sqrt(2))``,
    ``log m = 2 atanh(s)``, ``s = (m - 1) / (m + 1)``, ``|s| < 0.172``, by its series to
    ``s^21`` (the next term is below 1e-17). Within 2 ulp of ``math.log``
    (tests/optim/test_cpu_kernels.py)."""
    bits = values.view(np.int64)
    mantissa = out.view(np.int64)
    for a in range(n):
        mantissa[a] = (bits[a] & 0x000FFFFFFFFFFFFF) | 0x3FF0000000000000  # m in [1, 2)
    for a in range(n):
        e = np.float64(((bits[a] >> 52) & 0x7FF) - 1023)
        m = out[a]
        halve = m > _SQRT2
        m = m * 0.5 if halve else m
        e = e + 1.0 if halve else e
        s = (m - 1.0) / (m + 1.0)
        s2 = s * s
        series = (
            (
                (
                    (
                        ((((1 / 21 * s2 + 1 / 19) * s2 + 1 / 17) * s2 + 1 / 15) * s2 + 1 / 13) * s2
                        + 1 / 11
                    )
                    * s2
                    + 1 / 9
                )
                * s2
                + 1 / 7
            )
            * s2
            + 1 / 5
        ) * s2 + 1 / 3
        out[a] = e * _LN2_HI + (e * _LN2_LO + 2.0 * s + 2.0 * s * s2 * series)


@njit(cache=True, inline="always", error_model="numpy")
def _edge_constants(
    sR: np.ndarray, t: np.ndarray, K: np.ndarray, edge: int
) -> tuple:  # pragma: no cover (compiled)
    """``(s R row by row, t, fx, skew, cx, fy, cy)`` of an edge as 17 scalars: read once per
    block, not in a loop over its matches (whose stores they could alias)."""
    return (
        sR[edge, 0, 0],
        sR[edge, 0, 1],
        sR[edge, 0, 2],
        sR[edge, 1, 0],
        sR[edge, 1, 1],
        sR[edge, 1, 2],
        sR[edge, 2, 0],
        sR[edge, 2, 1],
        sR[edge, 2, 2],
        t[edge, 0],
        t[edge, 1],
        t[edge, 2],
        K[edge, 0, 0],
        K[edge, 0, 1],
        K[edge, 0, 2],
        K[edge, 1, 1],
        K[edge, 1, 2],
    )


@njit(cache=True, inline="always", error_model="numpy")
def _in_camera_i(
    c: tuple,
    ok: bool,
    X0: float,
    X1: float,
    X2: float,
    p_u: float,
    p_v: float,
    z_i: float,
    q: float,
) -> tuple:  # pragma: no cover (compiled)
    """One match of C-Eq. 17 (the edge's :func:`_edge_constants` ``c``, the match's point in
    camera j, observed pixel and depth in camera i and confidence, as read from their arrays):
    ``(x0, x1, x2, 1 / z, u, v, e_u, e_v, z / z_i, sqrt q)`` with ``x = T X_j`` (z clamped),
    its pixel and residuals. An invalid match (``ok`` False), or one ``T`` brings nearer camera
    i than ``MIN_DEPTH_RATIO`` of its observed depth (behind it included), reads as a harmless
    point with ``sqrt q = 0``: no branch, so the loops over matches vectorise,
    and no garbage behind a mask reaches a sum. Scalars only: an array argument of an inlined
    function costs two reference counts per call."""
    X0, X1, X2 = (X0, X1, X2) if ok else (0.0, 0.0, 1.0)
    x0 = c[0] * X0 + c[1] * X1 + c[2] * X2 + c[9]
    x1 = c[3] * X0 + c[4] * X1 + c[5] * X2 + c[10]
    x2 = c[6] * X0 + c[7] * X1 + c[8] * X2 + c[11]
    inv_z = 1.0 / max(x2, _MIN_NORM)
    u = c[12] * x0 * inv_z + c[13] * x1 * inv_z + c[14]
    v = c[15] * x1 * inv_z + c[16]
    e_u = u - p_u if ok else 0.0
    e_v = v - p_v if ok else 0.0
    ratio = max(x2, _MIN_NORM) / max(z_i if ok else 1.0, _MIN_NORM)
    q = q if ok else 0.0
    # Pi_K and log z exist only in front of camera i and their Jacobian grows as 1 / z^2 near it
    s = math.sqrt(q) if x2 > MIN_DEPTH_RATIO * (z_i if ok else 1.0) else 0.0
    return x0, x1, x2, inv_z, u, v, e_u, e_v, ratio, s


@njit(cache=True, error_model="numpy", fastmath=_FAST_SUMS)
def _calibrated_block(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    edge: int,
    first: int,
    n: int,
) -> tuple:  # pragma: no cover (compiled)
    """Matches ``first`` to ``first + n`` of ``edge`` (C-Eq. 17): their inputs as flat 1-D
    views (numba indexes a 3-D array by its runtime shape, which LLVM vectorises only for a
    unit stride), the edge's :func:`_edge_constants` and the log-depth residuals
    ``log(z / z_i)`` ``(n,)``. Called, not inlined: numba's parallel analysis does not take
    the inlined arrays."""
    m0 = edge * q.shape[1] + first
    X = X_j.reshape(-1)[3 * m0 : 3 * (m0 + n)]
    p = p_i.reshape(-1)[2 * m0 : 2 * (m0 + n)]
    z, qs, ok = (
        z_i.reshape(-1)[m0 : m0 + n],
        q.reshape(-1)[m0 : m0 + n],
        valid.reshape(-1)[m0 : m0 + n],
    )
    c = _edge_constants(sR, t, K, edge)
    ratios, log_ratio = np.empty(n), np.empty(n)
    for a in range(n):
        ratios[a] = _in_camera_i(
            c, ok[a], X[3 * a], X[3 * a + 1], X[3 * a + 2], p[2 * a], p[2 * a + 1], z[a], qs[a]
        )[8]
    _log(ratios, log_ratio, n)
    return X, p, z, qs, ok, c, log_ratio


def _ray_range_blocks(
    sR: np.ndarray,
    t: np.ndarray,
    X_i: np.ndarray,
    X_j: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    block: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
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
            s = math.sqrt(np.float64(q[edge, m]))
            # ray rows (C-Eq. 9-10): [(I - r r^T) / d, -[r]_x, 0]
            for c, r_c, s0, s1, s2 in (
                (0, r0, 0.0, r2, -r1),
                (1, r1, -r2, 0.0, r0),
                (2, r2, r1, -r0, 0.0),
            ):
                row[0], row[1], row[2] = -r_c * r0 / d, -r_c * r1 / d, -r_c * r2 / d
                row[c] += 1.0 / d
                row[3], row[4], row[5], row[6] = s0, s1, s2, 0.0
                _add_component(acc, row, e[c], s * inv_sigma[edge, c], k)
            # range row: [r^T, 0, d]
            row[0], row[1], row[2] = r0, r1, r2
            row[3], row[4], row[5], row[6] = 0.0, 0.0, 0.0, d
            _add_component(acc, row, e[3], s * inv_sigma[edge, 3], k)
        out[task] = acc


def _calibrated_blocks(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    block: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        n = min(block, P - first)
        X, p, z, qs, ok, c, log_ratio = _calibrated_block(
            sR, t, K, X_j, p_i, z_i, q, valid, edge, first, n
        )
        fx, skew, cx, fy, cy = c[12:]
        info_u, info_v, info_z = inv_sigma[edge, 0], inv_sigma[edge, 1], inv_sigma[edge, 2]
        # Each component's Jacobian row [j, x cross j, dz] (C-Sec. A.5) scaled by the square
        # root of its whitened Huber weight w: H += row row^T, g += (w e) row. Summed over
        # the three components, H has 25 entries that can be non-zero (upper triangle)
        h00 = h01 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = 0.0
        h22 = h23 = h24 = h25 = h26 = h33 = h34 = h35 = h36 = h44 = h45 = h46 = 0.0
        h55 = h66 = g0 = g1 = g2 = g3 = g4 = g5 = g6 = 0.0
        for a in range(n):
            x0, x1, x2, inv_z, u, v, e_u, e_v, _, s = _in_camera_i(
                c, ok[a], X[3 * a], X[3 * a + 1], X[3 * a + 2], p[2 * a], p[2 * a + 1], z[a], qs[a]
            )
            # u: j = (fx, skew, cx - u) / z
            w = _root_weight(e_u, s * info_u, k)
            a0, a1, a2 = w * fx * inv_z, w * skew * inv_z, w * (cx - u) * inv_z
            a3, a4, a5 = x1 * a2 - x2 * a1, x2 * a0 - x0 * a2, x0 * a1 - x1 * a0
            ea = w * e_u
            # v: j = (0, fy, cy - v) / z
            w = _root_weight(e_v, s * info_v, k)
            b1, b2 = w * fy * inv_z, w * (cy - v) * inv_z
            b3, b4, b5 = x1 * b2 - x2 * b1, -x0 * b2, x0 * b1
            eb = w * e_v
            # log z: j = (0, 0, 1) / z, and x2 / z for the scale
            e_z = log_ratio[a]
            w = _root_weight(e_z, s * info_z, k)
            c2 = w * inv_z
            c3, c4, c6 = x1 * c2, -x0 * c2, x2 * c2
            ec = w * e_z
            h00 += a0 * a0
            h01 += a0 * a1
            h02 += a0 * a2
            h03 += a0 * a3
            h04 += a0 * a4
            h05 += a0 * a5
            h11 += a1 * a1 + b1 * b1
            h12 += a1 * a2 + b1 * b2
            h13 += a1 * a3 + b1 * b3
            h14 += a1 * a4 + b1 * b4
            h15 += a1 * a5 + b1 * b5
            h22 += a2 * a2 + b2 * b2 + c2 * c2
            h23 += a2 * a3 + b2 * b3 + c2 * c3
            h24 += a2 * a4 + b2 * b4 + c2 * c4
            h25 += a2 * a5 + b2 * b5
            h26 += c2 * c6
            h33 += a3 * a3 + b3 * b3 + c3 * c3
            h34 += a3 * a4 + b3 * b4 + c3 * c4
            h35 += a3 * a5 + b3 * b5
            h36 += c3 * c6
            h44 += a4 * a4 + b4 * b4 + c4 * c4
            h45 += a4 * a5 + b4 * b5
            h46 += c4 * c6
            h55 += a5 * a5 + b5 * b5
            h66 += c6 * c6
            g0 += ea * a0
            g1 += ea * a1 + eb * b1
            g2 += ea * a2 + eb * b2 + ec * c2
            g3 += ea * a3 + eb * b3 + ec * c3
            g4 += ea * a4 + eb * b4 + ec * c4
            g5 += ea * a5 + eb * b5
            g6 += ec * c6
        # the upper triangle row by row, then g (as _add_row lays them out)
        for entry, value in enumerate(
            (
                h00,
                h01,
                h02,
                h03,
                h04,
                h05,
                0.0,
                h11,
                h12,
                h13,
                h14,
                h15,
                0.0,
                h22,
                h23,
                h24,
                h25,
                h26,
                h33,
                h34,
                h35,
                h36,
                h44,
                h45,
                h46,
                h55,
                0.0,
                h66,
                g0,
                g1,
                g2,
                g3,
                g4,
                g5,
                g6,
            )
        ):
            out[task, entry] = value


def _ray_range_cost(
    sR: np.ndarray,
    t: np.ndarray,
    X_i: np.ndarray,
    X_j: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    block: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        total = 0.0
        e = np.empty(4)
        for m in range(first, min(first + block, P)):
            if valid[edge, m]:
                _ray_range_error(sR[edge], t[edge], X_i[edge, m], X_j[edge, m], e)
                s = math.sqrt(np.float64(q[edge, m]))
                for c in range(4):
                    total += _rho(e[c] * s * inv_sigma[edge, c], k)
        out[task] = total


def _calibrated_cost(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    block: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        n = min(block, P - first)
        X, p, z, qs, ok, c, log_ratio = _calibrated_block(
            sR, t, K, X_j, p_i, z_i, q, valid, edge, first, n
        )
        info_u, info_v, info_z = inv_sigma[edge, 0], inv_sigma[edge, 1], inv_sigma[edge, 2]
        total = 0.0
        for a in range(n):
            _, _, _, _, _, _, e_u, e_v, _, s = _in_camera_i(
                c, ok[a], X[3 * a], X[3 * a + 1], X[3 * a + 2], p[2 * a], p[2 * a + 1], z[a], qs[a]
            )
            total += (
                _rho(e_u * s * info_u, k)
                + _rho(e_v * s * info_v, k)
                + _rho(log_ratio[a] * s * info_z, k)
            )
        out[task] = total


@njit(cache=True)
def _pose_arrays(T: np.ndarray) -> tuple:  # pragma: no cover (compiled)
    """``s R`` ``(e, 3, 3)`` and ``t`` ``(e, 3)`` of float64 poses ``T`` ``(e, 8)``, as
    :func:`como3r.geometry.lie.quat_to_matrix` (a few PyTorch calls cost more than a small
    linearization)."""
    E = T.shape[0]
    sR, t = np.empty((E, 3, 3)), np.empty((E, 3))
    for e in range(E):
        x, y, z, w, s = T[e, 3], T[e, 4], T[e, 5], T[e, 6], T[e, 7]
        xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
        wx, wy, wz = w * x, w * y, w * z
        sR[e, 0, 0], sR[e, 0, 1], sR[e, 0, 2] = 1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)
        sR[e, 1, 0], sR[e, 1, 1], sR[e, 1, 2] = 2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)
        sR[e, 2, 0], sR[e, 2, 1], sR[e, 2, 2] = 2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)
        for r in range(3):
            t[e, r] = T[e, r]
            for c in range(3):
                sR[e, r, c] *= s
    return sR, t


def _array(x: Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    return x.detach().to(dtype or x.dtype).contiguous().numpy()


def _sums(
    loop: Callable[..., None],
    T_ij: Tensor,
    data: tuple[Tensor, ...],
    q: Tensor,
    valid: Tensor,
    inv_sigma: Tensor,
    huber_k: float,
    width: int,
    error_model: str = "python",
) -> np.ndarray:
    """Run ``loop`` over the edges' match blocks; per-edge sums ``(e, width)`` float64."""
    E, P = q.shape
    blocks = -(-P // BLOCK)
    out = np.empty((E * blocks, width)) if width > 1 else np.empty(E * blocks)
    kernel = compiled(loop, fastmath=_FAST_SUMS, error_model=error_model)
    kernel(
        *_pose_arrays(_array(T_ij, torch.float64)),
        *(_array(x) for x in data),
        _array(q),
        _array(valid),
        _array(inv_sigma, torch.float64),
        float(huber_k),
        BLOCK,
        out,
    )
    return out.reshape(E, blocks, width).sum(1)


def _blocks(sums: np.ndarray) -> tuple[Tensor, Tensor]:
    """``H (e, 7, 7)`` from the accumulated upper triangles and ``g (e, 7)``."""
    H = np.zeros((sums.shape[0], 7, 7))
    H[:, _TRIU[0], _TRIU[1]] = sums[:, :28]
    H[:, _TRIU[1], _TRIU[0]] = sums[:, :28]
    return torch.from_numpy(H), torch.from_numpy(sums[:, 28:])


def ray_range_blocks(
    T_ij: Tensor,
    X_i: Tensor,
    X_j: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: Tensor,
    huber_k: float,
) -> tuple[Tensor, Tensor]:
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


def calibrated_blocks(
    T_ij: Tensor,
    K: Tensor,
    X_j: Tensor,
    p_i: Tensor,
    z_i: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: Tensor,
    huber_k: float,
) -> tuple[Tensor, Tensor]:
    """``H`` ``(e, 7, 7)`` and ``g`` ``(e, 7)`` float64 of C-Eq. 17 per edge; matches that
    ``T_ij`` brings nearer camera i than ``MIN_DEPTH_RATIO`` of their observed depth (behind
    it included) count nothing.

    Args:
        T_ij: ``(e, 8)``; K: ``(e, 3, 3)`` intrinsics of camera i; X_j: ``(e, P, 3)``;
        p_i: ``(e, P, 2)`` observed pixels; z_i: ``(e, P)`` observed depths; q, valid as in
        :func:`ray_range_blocks`; inv_sigma: ``(e, 3)`` (pixel u, v and log-depth).
    """
    K64 = K.detach().to(torch.float64)
    H_and_g = _sums(
        _calibrated_blocks,
        T_ij,
        (K64, X_j, p_i, z_i),
        q,
        valid,
        inv_sigma,
        huber_k,
        35,
        error_model="numpy",
    )
    return _blocks(H_and_g)


def ray_range_costs(
    T_ij: Tensor,
    X_i: Tensor,
    X_j: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: Tensor,
    huber_k: float,
) -> Tensor:
    """Robust energy ``sum rho(r)`` of C-Eq. 6 of each edge, ``(e,)`` float64 (arguments
    as in :func:`ray_range_blocks`)."""
    return torch.from_numpy(
        _sums(_ray_range_cost, T_ij, (X_i, X_j), q, valid, inv_sigma, huber_k, 1)[:, 0]
    )


def calibrated_costs(
    T_ij: Tensor,
    K: Tensor,
    X_j: Tensor,
    p_i: Tensor,
    z_i: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: Tensor,
    huber_k: float,
) -> Tensor:
    """Robust energy of C-Eq. 17 of each edge, ``(e,)`` float64 (arguments as in
    :func:`calibrated_blocks`)."""
    K64 = K.detach().to(torch.float64)
    return torch.from_numpy(
        _sums(
            _calibrated_cost,
            T_ij,
            (K64, X_j, p_i, z_i),
            q,
            valid,
            inv_sigma,
            huber_k,
            1,
            error_model="numpy",
        )[:, 0]
    )


# ---------------------------------------------------------------------------------------------
# Preparing a factor batch (optim.factors): validity of the matched points and the
# valid-first order of each edge's matches, one pass over memory each and no temporary
# (PyTorch made a bool tensor per test and sorted the validity to partition it: 75 ms per
# frame of a 512x384 front-end run, the local solve's and tracking's factor batches)
# ---------------------------------------------------------------------------------------------


@njit(cache=True, boundscheck=False)
def _confident(
    valid: np.ndarray, q: np.ndarray, valid_out: np.ndarray, q_out: np.ndarray
) -> None:  # pragma: no cover (compiled)
    for m in range(q.shape[0]):
        ok = valid[m] and np.isfinite(q[m]) and q[m] > 0
        valid_out[m] = ok
        q_out[m] = q[m] if ok else 0


def confident(valid: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """``(valid & isfinite(q) & (q > 0), q there and 0 elsewhere)`` for CPU tensors."""
    valid_out, q_out = np.empty(q.shape, dtype=np.bool_), np.empty(q.shape, dtype=_array(q).dtype)
    _confident(
        _array(valid).reshape(-1), _array(q).reshape(-1), valid_out.reshape(-1), q_out.reshape(-1)
    )
    return torch.from_numpy(valid_out), torch.from_numpy(q_out)


@njit(cache=True, boundscheck=False)
def _observed(p: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    for m in range(z.shape[0]):
        out[m] = np.isfinite(p[m, 0]) and np.isfinite(p[m, 1]) and np.isfinite(z[m]) and z[m] > 0


def observed(p_i: Tensor, z_i: Tensor) -> Tensor:
    """``isfinite(p_i).all(-1) & isfinite(z_i) & (z_i > 0)`` for CPU ``p_i`` ``(..., 2)`` and
    ``z_i`` ``(...)``."""
    out = np.empty(z_i.shape, dtype=np.bool_)
    _observed(_array(p_i).reshape(-1, 2), _array(z_i).reshape(-1), out.reshape(-1))
    return torch.from_numpy(out)


@njit(cache=True, boundscheck=False)
def _usable_rows(X: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover (compiled)
    for m in range(X.shape[0]):
        x0, x1, x2 = X[m, 0], X[m, 1], X[m, 2]
        finite = np.isfinite(x0) and np.isfinite(x1) and np.isfinite(x2)
        out[m] = finite and (x0 * x0 > 0 or x1 * x1 > 0 or x2 * x2 > 0)  # in X's dtype


def usable_points(X: Tensor) -> Tensor:
    """``(...)`` bool: rows of ``X`` ``(..., 3)`` (CPU) that are finite and not the camera
    centre, as ``isfinite(X).all(-1) & (norm(X, dim=-1) > 0)``: PyTorch sums the squares in
    X's dtype, so a float32 point within 1e-23 of the origin has norm 0."""
    out = np.empty(X.shape[:-1], dtype=np.bool_)
    _usable_rows(_array(X).reshape(-1, 3), out.reshape(-1))
    return torch.from_numpy(out)


@njit(cache=True, boundscheck=False)
def _all_finite(values: np.ndarray) -> bool:  # pragma: no cover (compiled)
    for k in range(values.shape[0]):
        if not np.isfinite(values[k]):
            return False
    return True


def all_finite(values: Tensor) -> bool:
    """``bool(isfinite(values).all())`` for a CPU tensor, without the bool tensor."""
    return bool(_all_finite(_array(values).reshape(-1)))


@njit(cache=True, boundscheck=False)
def _valid_first(valid: np.ndarray, out: np.ndarray) -> int:  # pragma: no cover (compiled)
    E, P = valid.shape
    flags = valid.view(np.uint8)
    kept = 0
    for e in range(E):
        count = 0
        for m in range(P):
            count += flags[e, m]
        kept = max(kept, count)
        front, back = 0, count  # branch-free: every index goes to one of the two cursors
        for m in range(P):
            ok = flags[e, m]
            out[e, front if ok else back] = m
            front += ok
            back += 1 - ok
    return kept


def valid_first(valid: Tensor) -> tuple[Tensor, int]:
    """Per edge the indices of its valid matches, then of its invalid ones, each in their
    order (``sort(~valid, stable=True).indices`` for a CPU ``valid`` ``(E, P)`` bool), and
    the largest valid count: ``(order (E, P) int64, kept)``."""
    out = np.empty(valid.shape, dtype=np.int64)
    kept = _valid_first(_array(valid), out)
    return torch.from_numpy(out), int(kept)


@njit(cache=True, boundscheck=False)
def _take_matches(
    values: np.ndarray, order: np.ndarray, kept: int, out: np.ndarray
) -> None:  # pragma: no cover (compiled)
    width = values.shape[2]
    for e in range(order.shape[0]):
        if width == 1:
            for k in range(kept):
                out[e, k, 0] = values[e, order[e, k], 0]
        else:
            for k in range(kept):
                m = order[e, k]
                for c in range(width):
                    out[e, k, c] = values[e, m, c]


def take_matches(values: Tensor, order: Tensor, kept: int) -> Tensor:
    """``values`` ``(E, P, ...)`` (CPU) at each edge's first ``kept`` matches of ``order``
    ``(E, >= kept)``: ``gather(values, 1, order[:, :kept] expanded)``."""
    E = order.shape[0]
    flat = _array(values).reshape(E, values.shape[1], -1)
    out = np.empty((E, kept, flat.shape[2]), dtype=flat.dtype)
    _take_matches(flat, _array(order), kept, out)
    return torch.from_numpy(out).reshape(E, kept, *values.shape[2:])
