"""Compiled CPU sums of a keyframe pair's focal column (:mod:`como3r.frontend.focal`).

The joint solve of :func:`~como3r.frontend.focal.estimate_log_focal` takes its pose blocks
from the factors' own compiled loop (:func:`como3r.optim.cpu_loops.calibrated_block_sums`)
and adds one column, the log focal correction ``delta``'s. One pass over an edge's matches
gives its C-Eq. 17 residual, usable-depth mask and Huber weights, and from them that column:
``H_pf = J_T^T W J_f`` (7 entries in the left tangent of ``T_ij``), ``H_ff = J_f^T W J_f``
and ``g_f = J_f^T W r``. The residual moves with ``delta`` through camera i's ``fx, fy``
where camera i takes the correction, ``d (u, v, log z) = (fx x / z, fy y / z, 0)``, and
through the x and y of camera j's points where camera j does, ``d (u, v, log z) = (d e / d
x) s R (-X.x, -X.y, 0)`` (C-Eq. 18 composed with C-Eq. 9; the same columns as the joint
focal BA's, :mod:`como3r.backend.focal_factors`, summed into one). The factors come in at
the trial correction already (their ``K`` and ``X_j`` rescaled).

Everything per match runs in float64. The loop stays in this one file with its constants
as arguments: numba keys a loop's disk cache on its own source file only. Measured on a
merge of a 16-agent replay (4 edges of 4096 matches, one thread): 0.67 ms the column (the
pose blocks' compiled loop: 0.65 ms), about 5 ms the same sums in PyTorch.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import prange
from torch import Tensor

from como3r.jit import compiled
from como3r.optim.cpu_loops import MIN_DEPTH_RATIO, pose_arrays

#: depths are clamped to this before dividing, as geometry.residuals does
MIN_DEPTH = 1e-12
#: reassociation and fused multiply-adds let the per-match sums vectorise
FAST_SUMS = {"reassoc", "contract"}


def focal_column_sums(
    sR: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    side_i: np.ndarray,
    side_j: np.ndarray,
    X_j: np.ndarray,
    p_i: np.ndarray,
    z_i: np.ndarray,
    q: np.ndarray,
    valid: np.ndarray,
    inv_sigma: np.ndarray,
    k: float,
    min_ratio: float,
    min_depth: float,
    out: np.ndarray,
) -> None:  # pragma: no cover (compiled)
    """Per edge (one task each): ``H_pf (7)``, ``H_ff`` and ``g_f`` into ``out[edge]``
    ``(9,)``. Invalid matches and matches ``T`` brings nearer camera i than ``min_ratio``
    of their observed depth (behind it included; C-Eq. 17-18) get a zero weight."""
    E, P = q.shape
    info_u, info_v, info_z = inv_sigma[0], inv_sigma[1], inv_sigma[2]
    for edge in prange(E):
        r00, r01, r02 = sR[edge, 0, 0], sR[edge, 0, 1], sR[edge, 0, 2]
        r10, r11, r12 = sR[edge, 1, 0], sR[edge, 1, 1], sR[edge, 1, 2]
        r20, r21, r22 = sR[edge, 2, 0], sR[edge, 2, 1], sR[edge, 2, 2]
        t0, t1, t2 = t[edge, 0], t[edge, 1], t[edge, 2]
        fx, skew, cx = K[edge, 0, 0], K[edge, 0, 1], K[edge, 0, 2]
        fy, cy = K[edge, 1, 1], K[edge, 1, 2]
        on_i, on_j = side_i[edge], side_j[edge]
        h0 = h1 = h2 = h3 = h4 = h5 = h6 = h_ff = g_f = 0.0
        for a in range(P):
            ok = valid[edge, a]
            X0, X1, X2 = (
                (X_j[edge, a, 0], X_j[edge, a, 1], X_j[edge, a, 2]) if ok else (0.0, 0.0, 1.0)
            )
            observed = z_i[edge, a] if ok else 1.0
            x0 = r00 * X0 + r01 * X1 + r02 * X2 + t0
            x1 = r10 * X0 + r11 * X1 + r12 * X2 + t1
            x2 = r20 * X0 + r21 * X1 + r22 * X2 + t2
            inv_z = 1.0 / max(x2, min_depth)
            n0, n1 = x0 * inv_z, x1 * inv_z
            u = fx * n0 + skew * n1 + cx
            v = fy * n1 + cy
            e_u = u - p_i[edge, a, 0] if ok else 0.0
            e_v = v - p_i[edge, a, 1] if ok else 0.0
            e_z = math.log(max(x2, min_depth) / max(observed, min_depth))
            s = math.sqrt(q[edge, a]) if ok and x2 > min_ratio * observed else 0.0
            # d x / d delta through camera j's points: s R (-X0, -X1, 0)
            d0 = -(r00 * X0 + r01 * X1)
            d1 = -(r10 * X0 + r11 * X1)
            d2 = -(r20 * X0 + r21 * X1)
            # each component's pose row [j, x cross j, j . x] and its focal entry, scaled by
            # its information times the square root of its Huber weight (C-Eq. 7-8)
            # u: j = (fx, skew, cx - u) / z, j . x = 0
            w_u = s * info_u * math.sqrt(k / max(abs(e_u * s * info_u), k))
            a0, a1, a2 = w_u * fx * inv_z, w_u * skew * inv_z, w_u * (cx - u) * inv_z
            a3, a4, a5 = x1 * a2 - x2 * a1, x2 * a0 - x0 * a2, x0 * a1 - x1 * a0
            f_u = on_i * w_u * fx * n0 + on_j * (a0 * d0 + a1 * d1 + a2 * d2)
            # v: j = (0, fy, cy - v) / z, j . x = 0
            w_v = s * info_v * math.sqrt(k / max(abs(e_v * s * info_v), k))
            b1, b2 = w_v * fy * inv_z, w_v * (cy - v) * inv_z
            b3, b4, b5 = x1 * b2 - x2 * b1, -x0 * b2, x0 * b1
            f_v = on_i * w_v * fy * n1 + on_j * (b1 * d1 + b2 * d2)
            # log z: j = (0, 0, 1) / z, j . x = 1; camera i's focal length not in it
            w_z = s * info_z * math.sqrt(k / max(abs(e_z * s * info_z), k))
            c2 = w_z * inv_z
            c3, c4, c6 = x1 * c2, -x0 * c2, x2 * c2
            f_z = on_j * c2 * d2
            h0 += a0 * f_u
            h1 += a1 * f_u + b1 * f_v
            h2 += a2 * f_u + b2 * f_v + c2 * f_z
            h3 += a3 * f_u + b3 * f_v + c3 * f_z
            h4 += a4 * f_u + b4 * f_v + c4 * f_z
            h5 += a5 * f_u + b5 * f_v
            h6 += c6 * f_z
            h_ff += f_u * f_u + f_v * f_v + f_z * f_z
            g_f += w_u * e_u * f_u + w_v * e_v * f_v + w_z * e_z * f_z
        for entry, value in enumerate((h0, h1, h2, h3, h4, h5, h6, h_ff, g_f)):
            out[edge, entry] = value


def focal_column(
    T_ij: Tensor,
    K: Tensor,
    side_i: Tensor,
    side_j: Tensor,
    X_j: Tensor,
    p_i: Tensor,
    z_i: Tensor,
    q: Tensor,
    valid: Tensor,
    inv_sigma: tuple[float, float, float],
    huber_k: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """The correction's column of C-Eq. 17 edges at the trial correction: ``H_pf (e, 7)``
    in the left tangent of ``T_ij``, ``H_ff (e,)`` and ``g_f (e,)``, float64.

    Args:
        T_ij: ``(e, 8)`` relative poses; K: ``(e, 3, 3)`` intrinsics of camera i (at the
            trial correction).
        side_i, side_j: ``(e,)`` 1 where camera i (its ``K``), camera j (its points) takes
            the correction, else 0.
        X_j: ``(e, P, 3)`` points of keyframe j (at the trial correction); p_i: ``(e, P,
            2)`` observed pixels; z_i: ``(e, P)`` observed depths; q: ``(e, P)``
            confidences; valid: ``(e, P)`` bool.
        inv_sigma: inverse noise of the pixel u, v and log-depth components.
        huber_k: Huber breakpoint on whitened components.
    """
    out = np.empty((q.shape[0], 9))
    kernel = compiled(focal_column_sums, fastmath=FAST_SUMS, error_model="numpy")

    def array(x: Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
        return x.detach().to(dtype or x.dtype).contiguous().numpy()

    kernel(
        *pose_arrays(array(T_ij, torch.float64)),
        array(K, torch.float64),
        array(side_i, torch.float64),
        array(side_j, torch.float64),
        array(X_j),
        array(p_i),
        array(z_i),
        array(q),
        array(valid),
        np.asarray(inv_sigma, dtype=np.float64),
        float(huber_k),
        MIN_DEPTH_RATIO,
        MIN_DEPTH,
        out,
    )
    sums = torch.from_numpy(out)
    return sums[:, :7], sums[:, 7], sums[:, 8]
