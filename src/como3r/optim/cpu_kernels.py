"""Compiled CPU linearization of the dense relative-pose factors (C-Eq. 6-10, 17-18).

:class:`~como3r.optim.match_factors.RayRangeFactors` and
:class:`~como3r.optim.match_factors.CalibratedFactors` sum, over every match of an edge,
``H = J^T W J`` and ``g = J^T W e`` in the tangent of ``T_ij`` (C-Sec. A.1-A.2, B.2). PyTorch on a CPU materialises per-match
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
residuals come from a polynomial logarithm in a loop of their own (:func:`~como3r.optim.cpu_loops._log`; LLVM has no
vector ``log`` here). Measured on the 21 linearizations sampled from a 15-frame
``benchmarks/slam_vs_prior.py`` run (4.1 M matches, one thread, loaded 2-core AVX-512 EPYC,
one process alternating): 53-57 -> 15 ns per match, cost 22.5 -> 8.5 ns per match; in the
whole run tracking went from 152 to 84 and the local solve from 274 to 151 ms per frame.
They are also more exact: float32 confidences took a float32 square root, which left the
blocks 1e-9 off a float64 evaluation of the same inputs; now 1e-15.

Same equations as :mod:`como3r.geometry.residuals`; tests compare both paths and autograd.
The loops themselves are in :mod:`como3r.optim.cpu_loops`; this module runs them on a
batch's tensors and holds the compiled passes that prepare a factor batch.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from numba import njit
from torch import Tensor

from como3r.jit import compiled
from como3r.optim.cpu_loops import (
    FAST_SUMS,
    calibrated_block_sums,
    calibrated_cost_sums,
    pose_arrays,
    ray_range_block_sums,
    ray_range_cost_sums,
)

#: matches per parallel task (the partial sums of a block are added in a fixed order)
BLOCK = 4096
#: the upper triangle of a 7x7 block, row by row: the 28 accumulated Hessian entries
_TRIU = np.triu_indices(7)


def _array(x: Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    """``x.detach().to(dtype).contiguous().numpy()``, each step only where it changes
    something (a small solve calls this a dozen times per linearization)."""
    if x.requires_grad:
        x = x.detach()
    if dtype is not None and x.dtype != dtype:
        x = x.to(dtype)
    return (x if x.is_contiguous() else x.contiguous()).numpy()


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
    kernel = compiled(loop, fastmath=FAST_SUMS, error_model=error_model)
    kernel(
        *pose_arrays(_array(T_ij, torch.float64)),
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
    H_and_g = _sums(ray_range_block_sums, T_ij, (X_i, X_j), q, valid, inv_sigma, huber_k, 35)
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
    ``T_ij`` brings nearer camera i than ``cpu_loops.MIN_DEPTH_RATIO`` of their observed depth (behind
    it included) count nothing.

    Args:
        T_ij: ``(e, 8)``; K: ``(e, 3, 3)`` intrinsics of camera i; X_j: ``(e, P, 3)``;
        p_i: ``(e, P, 2)`` observed pixels; z_i: ``(e, P)`` observed depths; q, valid as in
        :func:`ray_range_blocks`; inv_sigma: ``(e, 3)`` (pixel u, v and log-depth).
    """
    K64 = K.detach().to(torch.float64)
    H_and_g = _sums(
        calibrated_block_sums,
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
        _sums(ray_range_cost_sums, T_ij, (X_i, X_j), q, valid, inv_sigma, huber_k, 1)[:, 0]
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
            calibrated_cost_sums,
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
