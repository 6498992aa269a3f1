"""Compiled CPU sums of the segment-level depth refinement (C-Eq. 19-24).

Each Newton step of :class:`~como3r.backend.depth_refinement._Refiner` needs, over every
match k of the alternation's edges, the whitened point residual of C-Eq. 21
``r = w (d_b R psi_b + t) - w d_a psi_a`` (3 components), its Huber weights, and the
Jacobi-decoupled diagonal Hessian and gradient of both endpoints' log-scales (C-Eq. 24).
PyTorch on a CPU materialises ``(K, 3)`` residuals and Jacobians for millions of matches and
scatters them with ``index_add_``; this loop keeps one match in registers and adds it to
per-block partial sums, added in block order afterwards (the result does not depend on the
thread count). Everything per match runs in float64, whatever the problem's dtype.

Same equations as :meth:`~como3r.backend.depth_refinement._Refiner.normal_equations`;
tests compare both.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled

#: matches per parallel task, at least; at most :data:`MAX_BLOCKS` tasks (each holds a
#: partial Hessian and gradient over all log-scales)
BLOCK = 1 << 16
MAX_BLOCKS = 64


@njit(cache=True, inline="always")
def _huber_pieces(r: float, k: float) -> tuple:  # pragma: no cover (compiled)
    """IRLS weight ``min(1, k / |r|)`` and ``rho(r)``: ``r^2`` inside ``k``, ``2 k |r| - k^2``
    outside (the depth refinement's convention, twice C-Eq. 8's)."""
    a = abs(r)
    if a <= k:
        return 1.0, a * a
    return k / a, 2.0 * k * a - k * k


def _depth_sums(scale, d0_a, d0_b, param_a, param_b, ray_a, rays_b_in_a, t_ab, sqrt_w, k,
                block, with_blocks, H_out, g_out, cost_out):  # pragma: no cover (compiled)
    K = d0_a.shape[0]
    for task in prange(cost_out.shape[0]):
        cost = 0.0
        for m in range(task * block, min((task + 1) * block, K)):
            pa, pb, w = param_a[m], param_b[m], float(sqrt_w[m])
            # C-Eq. 19: d = ||X_init|| exp(s_g); a pixel without a log-scale keeps ||X_init||
            d_a = float(d0_a[m]) * (scale[pa] if pa >= 0 else 1.0)
            d_b = float(d0_b[m]) * (scale[pb] if pb >= 0 else 1.0)
            Haa = gaa = Hbb = gbb = 0.0
            for c in range(3):
                ray_b = float(rays_b_in_a[m, c])
                J_a = -w * d_a * float(ray_a[m, c])
                J_b = w * d_b * ray_b
                r = w * (d_b * ray_b + float(t_ab[m, c])) + J_a
                weight, rho = _huber_pieces(r, k)
                cost += rho
                Haa += weight * J_a * J_a
                gaa += weight * J_a * r
                Hbb += weight * J_b * J_b
                gbb += weight * J_b * r
            if with_blocks:
                if pa >= 0:  # Jacobi decoupling: J_a^T W J_b is dropped (C-Eq. 24)
                    H_out[task, pa] += Haa
                    g_out[task, pa] += gaa
                if pb >= 0:
                    H_out[task, pb] += Hbb
                    g_out[task, pb] += gbb
        cost_out[task] = cost


@dataclass(frozen=True)
class MatchStreams:
    """A depth problem's matches laid out match by match, so the loop reads them in order
    and looks up only the ``M`` log-scales at random (the data term gathering each
    endpoint's range, log-scale index and ray from the ``P`` pixels at every Newton step took
    2.4 times as long on a 15-keyframe, 6-million-match map at 512x384).

    Attributes:
        d0_a, d0_b: ``(K,)`` ranges ``||X_init||`` of each match's pixels in keyframes i, j.
        param_a, param_b: ``(K,)`` int64 their log-scales (-1: none, the pixel is fixed).
        ray_a: ``(K, 3)`` unit ray of the pixel of i; rays_b_in_a: ``(K, 3)`` j's ray rotated
            and scaled into frame i; t_ab: ``(K, 3)`` translation of ``T_ij``; sqrt_w:
            ``(K,)`` whitening. Contiguous CPU tensors; the gathered ones are copies.
    """

    d0_a: Tensor
    d0_b: Tensor
    param_a: Tensor
    param_b: Tensor
    ray_a: Tensor
    rays_b_in_a: Tensor
    t_ab: Tensor
    sqrt_w: Tensor

    @classmethod
    def of(cls, depth0: Tensor, rays: Tensor, match_a: Tensor, match_b: Tensor,
           param_a: Tensor, param_b: Tensor, rays_b_in_a: Tensor, t_ab: Tensor,
           sqrt_w: Tensor) -> MatchStreams:
        """Gather the per-pixel ``depth0 (P,)`` and ``rays (P, 3)`` at the matches' pixels
        ``match_a, match_b (K,)``; the per-match arrays (``param_a = param[match_a]`` …)
        are taken as they are (a copy only if not contiguous)."""
        def flat(x: Tensor) -> Tensor:
            return x.detach().contiguous()

        return cls(flat(depth0[match_a]), flat(depth0[match_b]), flat(param_a), flat(param_b),
                   flat(rays[match_a]), flat(rays_b_in_a), flat(t_ab), flat(sqrt_w))


def depth_normal_equations(s: Tensor, streams: MatchStreams, huber_k: float,
                           with_blocks: bool = True) -> tuple[Tensor, Tensor, float]:
    """Data term of C-Eq. 20-24: diagonal Hessian and gradient of the log-scales, and cost.

    Args:
        s: ``(M,)`` the log-scales (C-Eq. 19).
        streams: the problem's matches (:meth:`MatchStreams.of`).
        huber_k: Huber breakpoint of the data term.
        with_blocks: False computes the cost alone (``H`` and ``g`` are then zero).

    Returns:
        ``(H (M,), g (M,))`` float64 and the robust cost ``sum rho(r)``.
    """
    K, num_params = streams.d0_a.shape[0], s.numel()
    arrays = [getattr(streams, f.name).numpy() for f in fields(streams)]  # no copies
    blocks = max(1, min(MAX_BLOCKS, -(-K // BLOCK)))
    block = max(1, -(-K // blocks))
    width = num_params if with_blocks else 0
    H_out, g_out = np.zeros((blocks, width)), np.zeros((blocks, width))
    cost_out = np.zeros(blocks)
    scale = np.exp(s.detach().double().numpy())
    compiled(_depth_sums)(scale, *arrays, float(huber_k), block, with_blocks, H_out, g_out,
                          cost_out)
    return (torch.from_numpy(H_out.sum(0)), torch.from_numpy(g_out.sum(0)),
            float(cost_out.sum()))
