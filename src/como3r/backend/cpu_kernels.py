"""Compiled CPU sums of the segment-level depth refinement (C-Eq. 19-24).

Each Newton step of :class:`~como3r.backend.depth_refinement._Refiner` needs, over every
match k of the alternation's edges, the whitened point residual of C-Eq. 21
``r = w (d_b R psi_b + t) - w d_a psi_a`` (3 components), its Huber weights, and the
Jacobi-decoupled diagonal Hessian and gradient of both endpoints' log-scales (C-Eq. 24).
PyTorch on a CPU materialises ``(K, 3)`` residuals and Jacobians for millions of matches and
scatters them with ``index_add_``; this loop computes a match's sums in registers and adds
them to per-task partial sums, added in task order afterwards (the result does not depend on
the thread count). Everything per match runs in float64, whatever the problem's dtype.

Same equations as :meth:`~como3r.backend.depth_refinement._Refiner.normal_equations`;
tests compare both.

The loop runs in two parts per :data:`VECTOR_BLOCK` matches: the per-match sums in a loop
that LLVM vectorises (the matches' values read row by row from :class:`MatchStreams`, no
scatter and no running sum in it), then their scatter onto the log-scales and the cost, in
match order. One loop doing both ran scalar: 30 ns a match against 9 on 6 million
synthetic matches, one thread (AVX-512). The vectorised loop indexes the streams
with unsigned integers: a signed index makes numba wrap negative indices around, which LLVM
reads as a non-affine address and turns every load into a gather.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from numba import njit, prange, uint64
from torch import Tensor

from como3r.jit import compiled

#: matches per parallel task, at least; at most :data:`MAX_BLOCKS` tasks (each holds a
#: partial Hessian and gradient over all log-scales)
BLOCK = 1 << 16
MAX_BLOCKS = 64
#: matches whose per-match sums the vectorised loop writes before they are scattered (the
#: five sums of a block stay in the first-level cache)
VECTOR_BLOCK = 512

# rows of MatchStreams.values
_D0_A, _D0_B, _RAY_A, _RAY_B, _T_AB, _ROWS = 0, 1, 2, 5, 8, 11


@njit(cache=True, inline="always", error_model="numpy")
def _vector_block(values, sqrt_w, first, count, scale_a, scale_b, k, out):  # pragma: no cover
    """Per-match sums of matches ``first .. first + count - 1`` into ``out (5, count)``:
    ``J_a^T W J_a``, ``J_a^T W r``, ``J_b^T W J_b``, ``J_b^T W r`` and ``sum_c rho(r_c)``,
    with ``scale_a, scale_b (count,)`` the endpoints' ``exp(s)`` (1: no log-scale).

    ``r = w (d_b R psi_b + t) - w d_a psi_a`` (C-Eq. 21), ``d = ||X_init|| exp(s)``
    (C-Eq. 19); the Huber IRLS weight ``min(1, k / |r|)`` and ``rho = min(|r|, k) (2 |r| -
    min(|r|, k))``, which is ``r^2`` inside ``k`` and ``2 k |r| - k^2`` outside (the depth
    refinement's convention, twice C-Eq. 8's), written without branches."""
    base = uint64(first)
    for i in range(count):
        m = base + uint64(i)
        w = float(sqrt_w[m])
        d_a = float(values[_D0_A, m]) * scale_a[i]
        d_b = float(values[_D0_B, m]) * scale_b[i]
        Haa = gaa = Hbb = gbb = cost = 0.0
        for c in range(3):
            ray_b = float(values[_RAY_B + c, m])
            J_a = -w * d_a * float(values[_RAY_A + c, m])
            J_b = w * d_b * ray_b
            r = w * (d_b * ray_b + float(values[_T_AB + c, m])) + J_a
            a = abs(r)
            clipped = min(a, k)
            weight = clipped / a if a > 0.0 else 1.0
            cost += clipped * (2.0 * a - clipped)
            Haa += weight * J_a * J_a
            gaa += weight * J_a * r
            Hbb += weight * J_b * J_b
            gbb += weight * J_b * r
        out[0, i] = Haa
        out[1, i] = gaa
        out[2, i] = Hbb
        out[3, i] = gbb
        out[4, i] = cost


def _depth_sums(
    scale, values, sqrt_w, param_a, param_b, k, block, with_blocks, H_out, g_out, cost_out
):  # pragma: no cover (compiled)
    K = values.shape[1]
    for task in prange(cost_out.shape[0]):
        sums = np.empty((5, VECTOR_BLOCK))
        scale_a, scale_b = np.empty(VECTOR_BLOCK), np.empty(VECTOR_BLOCK)
        cost = 0.0
        for first in range(task * block, min((task + 1) * block, K), VECTOR_BLOCK):
            count = min(VECTOR_BLOCK, min((task + 1) * block, K) - first)
            for i in range(count):
                pa, pb = param_a[first + i], param_b[first + i]
                # C-Eq. 19: a pixel without a log-scale keeps ||X_init||
                scale_a[i] = scale[pa] if pa >= 0 else 1.0
                scale_b[i] = scale[pb] if pb >= 0 else 1.0
            _vector_block(values, sqrt_w, first, count, scale_a, scale_b, k, sums)
            for i in range(count):
                cost += sums[4, i]
                if with_blocks:
                    pa, pb = param_a[first + i], param_b[first + i]
                    if pa >= 0:  # Jacobi decoupling: J_a^T W J_b is dropped (C-Eq. 24)
                        H_out[task, pa] += sums[0, i]
                        g_out[task, pa] += sums[1, i]
                    if pb >= 0:
                        H_out[task, pb] += sums[2, i]
                        g_out[task, pb] += sums[3, i]
        cost_out[task] = cost


@dataclass(frozen=True)
class MatchStreams:
    """A depth problem's matches laid out match by match, so the loop reads them in order
    and looks up only the ``M`` log-scales at random (the data term gathering each
    endpoint's range, log-scale index and ray from the ``P`` pixels at every Newton step took
    2.4 times as long on a 15-keyframe, 6-million-match map at 512x384), one row per
    quantity so that the vectorised loop reads each with vector loads.

    Attributes:
        values: ``(11, K)`` in the problem's dtype, rows: ``d0_a, d0_b`` the ranges
            ``||X_init||`` of each match's pixels in keyframes i, j; ``ray_a`` (3 rows) the
            unit ray of the pixel of i; ``rays_b_in_a`` (3 rows) j's ray rotated and scaled
            into frame i; ``t_ab`` (3 rows) the translation of ``T_ij``.
        sqrt_w: ``(K,)`` the whitening ``sqrt(q) / (sigma_point d_i)``.
        param_a, param_b: ``(K,)`` int64 the matches' log-scales (-1: none, the pixel is
            fixed).
    """

    values: Tensor
    sqrt_w: Tensor
    param_a: Tensor
    param_b: Tensor

    @classmethod
    def of(
        cls,
        depth0: Tensor,
        rays: Tensor,
        match_a: Tensor,
        match_b: Tensor,
        param_a: Tensor,
        param_b: Tensor,
        rays_b_in_a: Tensor,
        t_ab: Tensor,
        sqrt_w: Tensor,
    ) -> MatchStreams:
        """Gather the per-pixel ``depth0 (P,)`` and ``rays (P, 3)`` at the matches' pixels
        ``match_a, match_b (K,)``; the per-match ``param_a = param[match_a]``, ``param_b``
        ``(K,)``, ``rays_b_in_a, t_ab (K, 3)`` and ``sqrt_w (K,)`` are laid out as rows."""
        values = torch.cat(
            [depth0[match_a][None], depth0[match_b][None], rays[match_a].T, rays_b_in_a.T, t_ab.T]
        )
        return cls(*(x.detach().contiguous() for x in (values, sqrt_w, param_a, param_b)))

    @property
    def num_matches(self) -> int:
        """K."""
        return self.values.shape[1]

    @classmethod
    def empty(cls, K: int, dtype: torch.dtype) -> MatchStreams:
        """Streams of ``K`` matches to be filled (:func:`pack_kept`), values in ``dtype``."""
        return cls(
            torch.empty(_ROWS, K, dtype=dtype),
            torch.empty(K, dtype=dtype),
            torch.empty(K, dtype=torch.int64),
            torch.empty(K, dtype=torch.int64),
        )


def depth_normal_equations(
    s: Tensor, streams: MatchStreams, huber_k: float, with_blocks: bool = True
) -> tuple[Tensor, Tensor, float]:
    """Data term of C-Eq. 20-24: diagonal Hessian and gradient of the log-scales, and cost.

    Args:
        s: ``(M,)`` the log-scales (C-Eq. 19).
        streams: the problem's matches (:meth:`MatchStreams.of`).
        huber_k: Huber breakpoint of the data term.
        with_blocks: False computes the cost alone (``H`` and ``g`` are then zero).

    Returns:
        ``(H (M,), g (M,))`` float64 and the robust cost ``sum rho(r)``.
    """
    K, num_params = streams.num_matches, s.numel()
    arrays = [getattr(streams, f.name).numpy() for f in fields(streams)]  # no copies
    blocks = max(1, min(MAX_BLOCKS, -(-K // BLOCK)))
    block = max(1, -(-K // blocks))
    width = num_params if with_blocks else 0
    H_out, g_out = np.zeros((blocks, width)), np.zeros((blocks, width))
    cost_out = np.zeros(blocks)
    scale = np.exp(s.detach().double().numpy())
    compiled(_depth_sums, error_model="numpy")(
        scale, *arrays, float(huber_k), block, with_blocks, H_out, g_out, cost_out
    )
    return (torch.from_numpy(H_out.sum(0)), torch.from_numpy(g_out.sum(0)), float(cost_out.sum()))


@njit(cache=True, boundscheck=False, inline="always")
def _usable(valid, q, n) -> bool:  # pragma: no cover (compiled)
    """Match ``n`` is valid with a finite confidence ``q > 0``."""
    return valid[n] and q[n] > 0.0 and np.isfinite(q[n])


@njit(cache=True, inline="always")
def _enters(pa, pb) -> bool:  # pragma: no cover (compiled)
    """A match whose pixels have log-scales ``pa, pb`` enters the depth problem: both
    pixels usable (not -1) and at least one free (>= 0; -2 is valid and fixed)."""
    return pa != -1 and pb != -1 and (pa >= 0 or pb >= 0)


@njit(cache=True, boundscheck=False)
def _count_kept(idx, valid, q, param, offset_i, offset_j, pixels_i):  # pragma: no cover
    count = 0
    for n in range(idx.shape[0]):
        if _usable(valid, q, n):
            m = idx[n]
            if m < 0 or m >= pixels_i:
                return -1
            count += _enters(param[offset_i + m], param[offset_j + n])
    return count


@njit(cache=True, boundscheck=False)
def _pack_kept(
    idx,
    valid,
    q,
    depth0,
    rays,
    param,
    offset_i,
    offset_j,
    R,
    scale,
    t,
    whitening,
    first,
    values,
    sqrt_w,
    param_a,
    param_b,
):  # pragma: no cover
    k = first
    for n in range(idx.shape[0]):
        if not _usable(valid, q, n):
            continue
        a, b = offset_i + idx[n], offset_j + n
        pa, pb = param[a], param[b]
        if not _enters(pa, pb):
            continue
        values[_D0_A, k] = depth0[a]
        values[_D0_B, k] = depth0[b]
        for c in range(3):
            values[_RAY_A + c, k] = rays[a, c]
            # s_ij R_ij psi_j: j's ray in frame i (C-Sec. A.6)
            values[_RAY_B + c, k] = scale * (
                rays[b, 0] * R[c, 0] + rays[b, 1] * R[c, 1] + rays[b, 2] * R[c, 2]
            )  # R: float64
            values[_T_AB + c, k] = t[c]
        sqrt_w[k] = np.sqrt(np.float64(q[n])) * whitening  # float(): float32 stays float32
        param_a[k], param_b[k] = max(pa, -1), max(pb, -1)  # fixed: no log-scale
        k += 1


def _match_arrays(matches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        matches.idx.contiguous().numpy(),
        matches.valid.contiguous().numpy(),
        matches.q.contiguous().numpy(),
    )


def count_kept(matches, param: Tensor, offset_i: int, offset_j: int, pixels_i: int) -> int:
    """How many of an edge's matches (``idx, valid, q (P_j,)``) enter the depth problem
    (valid, finite ``q > 0``, both pixels usable in ``param (P,)`` (-1: not, -2: fixed) and
    one free), keyframes i and j starting at pixels ``offset_i``, ``offset_j``; -1 if a
    valid match names a pixel outside keyframe i's ``pixels_i``."""
    return int(_count_kept(*_match_arrays(matches), param.numpy(), offset_i, offset_j, pixels_i))


def pack_kept(
    matches,
    depth0: Tensor,
    rays: Tensor,
    param: Tensor,
    offset_i: int,
    offset_j: int,
    R: Tensor,
    T_ij: Tensor,
    whitening: float,
    first: int,
    streams: MatchStreams,
) -> None:
    """Write the matches :func:`count_kept` counts, in pixel order, into ``streams`` from
    match ``first`` on: the ranges ``depth0 (P,)`` and rays ``rays (P, 3)`` of both pixels
    (j's rotated by ``R (3, 3)`` and scaled by ``T_ij[7]``), ``T_ij[:3]``, ``sqrt(q)`` times
    ``whitening`` (``1 / (sigma_point d_i)``) and both log-scales."""
    _pack_kept(
        *_match_arrays(matches),
        depth0.numpy(),
        rays.numpy(),
        param.numpy(),
        offset_i,
        offset_j,
        R.double().numpy(),
        float(T_ij[7]),
        T_ij[:3].double().numpy(),
        float(whitening),
        first,
        streams.values.numpy(),
        streams.sqrt_w.numpy(),
        streams.param_a.numpy(),
        streams.param_b.numpy(),
    )
