"""The compiled per-match loops of :mod:`como3r.optim.cpu_kernels` (C-Eq. 6-10, 17-18).

Each loop sums, over the matches of one block of one edge, the Huber-weighted Gauss-Newton
blocks or the robust energy of C-Eq. 6 (ray and range) or C-Eq. 17 (pixel and log-depth);
the inline helpers above them are one match's residual, Jacobian rows and weights, in
float64. Host code (array conversion, block layout, thread count) is in
:mod:`como3r.optim.cpu_kernels`, which documents the design and its measurements.

The loops and every helper they inline stay in this one file: numba keys a loop's disk
cache on its own source file only, so a helper edited in another file would leave stale
machine code behind.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: norms and depths are clamped to this before dividing, as geometry.residuals does
_MIN_NORM = 1e-12
#: reassociation and fused multiply-adds let the per-match sums vectorise; no flag that
#: assumes finite values
FAST_SUMS = {"reassoc", "contract"}
#: log 2 in two parts (the high one exact in a double's 33 leading bits), and sqrt 2
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_SQRT2 = 1.4142135623730951
#: The calibrated residual (C-Eq. 17) counts a match only where ``T_ij`` brings its point of
#: keyframe j to at least this fraction of the depth observed in camera i. Nearer points make
#: the pixel Jacobian grow as ``1 / z^2`` (C-Eq. 18): on a 5,000-frame 64x48 loop a keyframe
#: placed 2.3 m off brought loop-edge points to just in front of its camera, their Hessian
#: entries reached 4e13 (7.8e19 assembled), no Tikhonov term made the system numerically
#: positive definite, and every later local solve returned a zero step. A quarter of the
#: observed depth is a log-depth residual of -1.39 (14 sigma at the default
#: ``tracking.sigma_depth`` of 0.1): an outlier already, and its Jacobian rows stay within
#: 16 times those of a match at its observed depth.
#: (The PyTorch path, optim.match_factors, reads it from here: numba bakes a global into the
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


@njit(cache=True, error_model="numpy", fastmath=FAST_SUMS)
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


def ray_range_block_sums(
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


def calibrated_block_sums(
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


def ray_range_cost_sums(
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


def calibrated_cost_sums(
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
def pose_arrays(T: np.ndarray) -> tuple:  # pragma: no cover (compiled)
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
