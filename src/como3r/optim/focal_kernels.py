"""Compiled CPU sums of C-Eq. 17 edges with focal rows: the joint pose and focal BA's
(:mod:`como3r.backend.focal_factors`) and a keyframe pair's focal correction's
(:mod:`como3r.frontend.focal`, which sums the two focal columns into one).

One pass over an edge's matches gives its C-Eq. 17 residual, usable-depth mask and Huber
weights once, and from them the whole ``9 x 9`` Gauss-Newton block in ``(T_ij, phi_i,
phi_j)``: the pose rows of C-Eq. 18 composed with C-Eq. 9 (as
:func:`como3r.optim.cpu_loops.calibrated_block_sums`) and the two focal columns of the
module docstring of :mod:`~como3r.backend.focal_factors`. The keyframes' pointmaps and
intrinsics are read as stored; the trial focal corrections enter as per-edge factors
(``f exp(phi_i)`` for camera i's ``fx, fy``, ``exp(-phi_j)`` on the x and y of camera j's
points: :func:`~como3r.geometry.camera.rescale_focal` without making the rescaled copies).

Everything per match runs in float64, in blocks of :data:`BLOCK` matches (one parallel task
each) whose partial sums are added in block order, so the result does not depend on the
thread count. Measured (issue 41, ``benchmarks/focal_stage.py``; one thread): on the
focal stage of stored 4- and 16-agent sessions a linearization takes 25-27 ns a match with
this loop, 440-460 with the PyTorch path; with the factors built once per solve instead of
every iteration, the stage went from 9.4 to 1.9 s of CPU at 4 agents and from 19.8 to 3.5 s
at 16.

The loops and their helper stay in this one file and take the depth ratio and clamp as
arguments: numba keys a loop's disk cache on its own source file only, so a helper or
constant of another file changed later would leave stale machine code behind.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled
from como3r.optim.cpu_loops import MIN_DEPTH_RATIO, pose_arrays

#: matches per parallel task (the partial sums of a block are added in a fixed order)
BLOCK = 4096
#: depths are clamped to this before dividing, as geometry.residuals does
MIN_DEPTH = 1e-12
#: reassociation and fused multiply-adds let the per-match sums vectorise
FAST_SUMS = {"reassoc", "contract"}
#: the upper triangle of a 9x9 block, row by row: the 45 accumulated Hessian entries
_TRIU = np.triu_indices(9)


@njit(cache=True, inline="always", error_model="numpy")
def _point(
    c: tuple, ok: bool, X0: float, X1: float, X2: float, z_i: float, min_depth: float
) -> tuple:  # pragma: no cover (compiled)
    """One match's point ``x = T (X0 f_j, X1 f_j, X2)`` in camera i (``c``: the edge's
    constants, :func:`_block_sums`) and its depth ratio ``z / z_i`` (both clamped); an
    invalid match (``ok`` False) reads as the point ``(0, 0, 1)`` of camera j observed at
    depth 1: no branch, so the loops over matches vectorise."""
    X0, X1, X2 = (X0 * c[17], X1 * c[17], X2) if ok else (0.0, 0.0, 1.0)
    x0 = c[0] * X0 + c[1] * X1 + c[2] * X2 + c[9]
    x1 = c[3] * X0 + c[4] * X1 + c[5] * X2 + c[10]
    x2 = c[6] * X0 + c[7] * X1 + c[8] * X2 + c[11]
    observed = z_i if ok else 1.0
    return X0, X1, x0, x1, x2, observed, max(x2, min_depth) / max(observed, min_depth)


@njit(cache=True, error_model="numpy", fastmath=FAST_SUMS)
def _block_sums(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    scale_i: np.ndarray,
    scale_j: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    min_ratio: float,
    min_depth: float,
    edge: int,
    first: int,
    n: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    """Matches ``first`` to ``first + n`` of ``edge``: the upper triangle of ``H`` and ``g``
    ``(54,)`` into ``out``. The inputs are read through flat 1-D views (numba indexes a 3-D
    array by its runtime shape, which LLVM vectorises only for a unit stride), the log depth
    ratios in a loop of their own (no vector ``log``), then the sums in one that vectorises:
    invalid matches and matches ``T`` brings nearer camera i than ``min_ratio`` of their
    observed depth (behind it included; C-Eq. 17-18) get a zero weight, not a branch."""
    m0 = edge * q.shape[1] + first
    X = X_j.reshape(-1)[3 * m0 : 3 * (m0 + n)]
    p = p_i.reshape(-1)[2 * m0 : 2 * (m0 + n)]
    z = z_i.reshape(-1)[m0 : m0 + n]
    qs = q.reshape(-1)[m0 : m0 + n]
    ok = valid.reshape(-1)[m0 : m0 + n]
    # s R row by row, t, then camera i's fx, skew, cx, fy, cy at its trial focal length and
    # the factor on the x and y of camera j's points
    f_i = scale_i[edge]
    c = (
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
        K[edge, 0, 0] * f_i,
        K[edge, 0, 1],
        K[edge, 0, 2],
        K[edge, 1, 1] * f_i,
        K[edge, 1, 2],
        scale_j[edge],
    )
    fx, skew, cx, fy, cy = c[12], c[13], c[14], c[15], c[16]
    info_u, info_v, info_z = inv_sigma[0], inv_sigma[1], inv_sigma[2]
    log_ratio = np.empty(n)
    for a in range(n):
        log_ratio[a] = _point(c, ok[a], X[3 * a], X[3 * a + 1], X[3 * a + 2], z[a], min_depth)[6]
    for a in range(n):
        log_ratio[a] = math.log(log_ratio[a])
    h00 = h01 = h02 = h03 = h04 = h05 = h07 = h08 = h11 = h12 = h13 = h14 = h15 = h17 = 0.0
    h18 = h22 = h23 = h24 = h25 = h26 = h27 = h28 = h33 = h34 = h35 = h36 = h37 = h38 = 0.0
    h44 = h45 = h46 = h47 = h48 = h55 = h57 = h58 = h66 = h68 = h77 = h78 = h88 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = g6 = g7 = g8 = 0.0
    for a in range(n):
        X0, X1, x0, x1, x2, observed, _ = _point(
            c, ok[a], X[3 * a], X[3 * a + 1], X[3 * a + 2], z[a], min_depth
        )
        inv_z = 1.0 / max(x2, min_depth)
        n0, n1 = x0 * inv_z, x1 * inv_z
        u = fx * n0 + skew * n1 + cx
        v = fy * n1 + cy
        e_u = u - p[2 * a] if ok[a] else 0.0
        e_v = v - p[2 * a + 1] if ok[a] else 0.0
        e_z = log_ratio[a]
        weight = qs[a] if ok[a] else 0.0
        s = math.sqrt(weight) if x2 > min_ratio * observed else 0.0
        # d x / d phi_j = s R (-X0, -X1, 0)
        d0 = -(c[0] * X0 + c[1] * X1)
        d1 = -(c[3] * X0 + c[4] * X1)
        d2 = -(c[6] * X0 + c[7] * X1)
        # Each component's row [j, x cross j, j . x, d e / d phi_i, d e / d phi_j] (C-Eq.
        # 9, 18; module docstring) scaled by its information times the square root of its
        # whitened Huber weight (C-Eq. 7-8): H += row row^T, g += (w e) row.
        # u: j = (fx, skew, cx - u) / z, j . x = 0, d u / d phi_i = fx x / z
        w = s * info_u * math.sqrt(k / max(abs(e_u * s * info_u), k))
        a0, a1, a2 = w * fx * inv_z, w * skew * inv_z, w * (cx - u) * inv_z
        a3, a4, a5 = x1 * a2 - x2 * a1, x2 * a0 - x0 * a2, x0 * a1 - x1 * a0
        a7, a8 = w * fx * n0, a0 * d0 + a1 * d1 + a2 * d2
        ea = w * e_u
        # v: j = (0, fy, cy - v) / z, j . x = 0, d v / d phi_i = fy y / z
        w = s * info_v * math.sqrt(k / max(abs(e_v * s * info_v), k))
        b1, b2 = w * fy * inv_z, w * (cy - v) * inv_z
        b3, b4, b5 = x1 * b2 - x2 * b1, -x0 * b2, x0 * b1
        b7, b8 = w * fy * n1, b1 * d1 + b2 * d2
        eb = w * e_v
        # log z: j = (0, 0, 1) / z, j . x = 1 (x2 / z), camera i's focal length not in it
        w = s * info_z * math.sqrt(k / max(abs(e_z * s * info_z), k))
        c2 = w * inv_z
        c3, c4, c6, c8 = x1 * c2, -x0 * c2, x2 * c2, c2 * d2
        ec = w * e_z
        h00 += a0 * a0
        h01 += a0 * a1
        h02 += a0 * a2
        h03 += a0 * a3
        h04 += a0 * a4
        h05 += a0 * a5
        h07 += a0 * a7
        h08 += a0 * a8
        h11 += a1 * a1 + b1 * b1
        h12 += a1 * a2 + b1 * b2
        h13 += a1 * a3 + b1 * b3
        h14 += a1 * a4 + b1 * b4
        h15 += a1 * a5 + b1 * b5
        h17 += a1 * a7 + b1 * b7
        h18 += a1 * a8 + b1 * b8
        h22 += a2 * a2 + b2 * b2 + c2 * c2
        h23 += a2 * a3 + b2 * b3 + c2 * c3
        h24 += a2 * a4 + b2 * b4 + c2 * c4
        h25 += a2 * a5 + b2 * b5
        h26 += c2 * c6
        h27 += a2 * a7 + b2 * b7
        h28 += a2 * a8 + b2 * b8 + c2 * c8
        h33 += a3 * a3 + b3 * b3 + c3 * c3
        h34 += a3 * a4 + b3 * b4 + c3 * c4
        h35 += a3 * a5 + b3 * b5
        h36 += c3 * c6
        h37 += a3 * a7 + b3 * b7
        h38 += a3 * a8 + b3 * b8 + c3 * c8
        h44 += a4 * a4 + b4 * b4 + c4 * c4
        h45 += a4 * a5 + b4 * b5
        h46 += c4 * c6
        h47 += a4 * a7 + b4 * b7
        h48 += a4 * a8 + b4 * b8 + c4 * c8
        h55 += a5 * a5 + b5 * b5
        h57 += a5 * a7 + b5 * b7
        h58 += a5 * a8 + b5 * b8
        h66 += c6 * c6
        h68 += c6 * c8
        h77 += a7 * a7 + b7 * b7
        h78 += a7 * a8 + b7 * b8
        h88 += a8 * a8 + b8 * b8 + c8 * c8
        g0 += ea * a0
        g1 += ea * a1 + eb * b1
        g2 += ea * a2 + eb * b2 + ec * c2
        g3 += ea * a3 + eb * b3 + ec * c3
        g4 += ea * a4 + eb * b4 + ec * c4
        g5 += ea * a5 + eb * b5
        g6 += ec * c6
        g7 += ea * a7 + eb * b7
        g8 += ea * a8 + eb * b8 + ec * c8
    # the upper triangle row by row (zero where no component has both entries), then g
    for entry, value in enumerate(
        (
            h00, h01, h02, h03, h04, h05, 0.0, h07, h08,
            h11, h12, h13, h14, h15, 0.0, h17, h18,
            h22, h23, h24, h25, h26, h27, h28,
            h33, h34, h35, h36, h37, h38,
            h44, h45, h46, h47, h48,
            h55, 0.0, h57, h58,
            h66, 0.0, h68,
            h77, h78,
            h88,
            g0, g1, g2, g3, g4, g5, g6, g7, g8,
        )
    ):  # fmt: skip
        out[entry] = value


def focal_block_sums(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    scale_i: np.ndarray,
    scale_j: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    min_ratio: float,
    min_depth: float,
    block: int,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    """Per block of matches (one task each), :func:`_block_sums` into ``out[task]``."""
    E, P = q.shape
    blocks = (P + block - 1) // block
    for task in prange(E * blocks):
        edge, first = task // blocks, (task % blocks) * block
        _block_sums(
            sR,
            t,
            K,
            scale_i,
            scale_j,
            X_j,
            p_i,
            z_i,
            q,
            valid,
            inv_sigma,
            k,
            min_ratio,
            min_depth,
            edge,
            first,
            min(block, P - first),
            out[task],
        )


def focal_blocks(
    T_ij: Tensor,
    K: Tensor,
    scale_i: Tensor,
    scale_j: Tensor,
    X_j: Tensor,
    p_i: Tensor,
    z_i: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: tuple[float, float, float],
    huber_k: float,
) -> tuple[Tensor, Tensor]:
    """``H`` ``(e, 9, 9)`` and ``g`` ``(e, 9)`` float64 of C-Eq. 17 edges in the left
    tangent of ``T_ij``, then camera i's and camera j's log focal.

    Args:
        T_ij: ``(e, 8)`` relative poses; K: ``(e, 3, 3)`` intrinsics of camera i as stored.
        scale_i: ``(e,)`` ``exp(phi_i)``; scale_j: ``(e,)`` ``exp(-phi_j)``: the trial
            corrections of the two cameras.
        X_j: ``(e, P, 3)`` points of keyframe j as stored; p_i: ``(e, P, 2)`` observed
            pixels; z_i: ``(e, P)`` observed depths; q: ``(e, P)`` confidences; valid:
            ``(e, P)`` bool.
        inv_sigma: inverse noise of the pixel u, v and log-depth components.
        huber_k: Huber breakpoint on whitened components.
    """
    E, P = q.shape
    blocks = -(-P // BLOCK)
    out = np.empty((E * blocks, 54))
    kernel = compiled(focal_block_sums, fastmath=FAST_SUMS, error_model="numpy")

    def array(x: Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
        return x.detach().to(dtype or x.dtype).contiguous().numpy()

    kernel(
        *pose_arrays(array(T_ij, torch.float64)),
        array(K, torch.float64),
        array(scale_i, torch.float64),
        array(scale_j, torch.float64),
        array(X_j),
        array(p_i),
        array(z_i),
        array(q),
        array(valid),
        np.asarray(inv_sigma, dtype=np.float64),
        float(huber_k),
        MIN_DEPTH_RATIO,
        MIN_DEPTH,
        BLOCK,
        out,
    )
    sums = out.reshape(E, blocks, 54).sum(1)
    H = np.zeros((E, 9, 9))
    H[:, _TRIU[0], _TRIU[1]] = sums[:, :45]
    H[:, _TRIU[1], _TRIU[0]] = sums[:, :45]
    return torch.from_numpy(H), torch.from_numpy(sums[:, 45:])
