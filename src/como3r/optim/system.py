"""The block normal equations of a pose solve: per-edge blocks and their assembly (C-Eq. 25).

Factors linearize into per-edge 7x7 blocks (:class:`EdgeBlocks`); :func:`assemble`
scatter-adds them into the global block system (:class:`BlockSystem`) over N poses, which
:func:`como3r.optim.linear.solve` solves. The assembled system is float64 (see
:mod:`como3r.optim.linear` for why).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from como3r.errors import InputError

D = 7  # tangent dimension of Sim(3)


@dataclass(frozen=True, eq=False)
class EdgeBlocks:
    """Per-edge Gauss-Newton blocks of a relative-pose factor batch over E edges.

    For an edge (i, j) with stacked whitened Jacobians J_i, J_j and IRLS weights W:
    ``H_ii = J_i^T W J_i``, ``H_jj = J_j^T W J_j``, ``H_ij = J_i^T W J_j``,
    ``g_i = J_i^T W e``, ``g_j = J_j^T W e``.

    Attributes:
        i, j: ``(E,)`` int64 pose indices.
        H_ii, H_jj, H_ij: ``(E, 7, 7)`` blocks.
        g_i, g_j: ``(E, 7)`` gradient blocks.
    """

    i: torch.Tensor
    j: torch.Tensor
    H_ii: torch.Tensor
    H_jj: torch.Tensor
    H_ij: torch.Tensor
    g_i: torch.Tensor
    g_j: torch.Tensor

    @staticmethod
    def cat(parts: Sequence[EdgeBlocks]) -> EdgeBlocks:
        """Concatenate edge batches (e.g. the chunks of one factor); one batch is itself."""
        if len(parts) == 1:
            return parts[0]
        return EdgeBlocks(*(torch.cat([getattr(p, name) for p in parts]) for name in _EDGE_FIELDS))


_EDGE_FIELDS = ("i", "j", "H_ii", "H_jj", "H_ij", "g_i", "g_j")


@dataclass(frozen=True, eq=False)
class BlockSystem:
    """Global block normal equations ``H tau = -g`` over N poses, H symmetric.

    Attributes:
        H_diag: ``(N, 7, 7)`` float64 diagonal blocks (scatter-added over edges).
        off_i, off_j: ``(M,)`` int64 indices of the upper off-diagonal blocks; repeated
            pairs are summed, the lower triangle is their transpose.
        H_off: ``(M, 7, 7)`` float64 block at (off_i, off_j).
        g: ``(N, 7)`` float64 gradient.
    """

    H_diag: torch.Tensor
    off_i: torch.Tensor
    off_j: torch.Tensor
    H_off: torch.Tensor
    g: torch.Tensor

    @property
    def num_poses(self) -> int:
        """N, the number of pose variables (pinned ones included)."""
        return self.H_diag.shape[0]

    def to_dense(self) -> torch.Tensor:
        """The full ``(7N, 7N)`` Hessian, both triangles."""
        return triplets_to_dense(
            *free_triplets(self, torch.ones_like(self.g[:, 0], dtype=torch.bool))
        )


def assemble(num_poses: int, contributions: Sequence[EdgeBlocks]) -> BlockSystem:
    """Scatter-add per-edge blocks of one or more factor batches into a ``BlockSystem``.

    Args:
        num_poses: N.
        contributions: edge blocks whose indices lie in ``[0, N)``.
    """
    if not contributions:
        raise InputError("assemble: no factor contributions to assemble")
    device = contributions[0].i.device
    H_diag = torch.zeros(num_poses, D, D, dtype=torch.float64, device=device)
    g = torch.zeros(num_poses, D, dtype=torch.float64, device=device)
    for c in contributions:
        H_diag.index_add_(0, c.i, c.H_ii.to(torch.float64))
        H_diag.index_add_(0, c.j, c.H_jj.to(torch.float64))
        g.index_add_(0, c.i, c.g_i.to(torch.float64))
        g.index_add_(0, c.j, c.g_j.to(torch.float64))
    return BlockSystem(
        H_diag=H_diag,
        off_i=torch.cat([c.i for c in contributions]),
        off_j=torch.cat([c.j for c in contributions]),
        H_off=torch.cat([c.H_ij.to(torch.float64) for c in contributions]),
        g=g,
    )


def free_triplets(
    system: BlockSystem, free: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Scalar (row, col, value) triplets of the free-pose Hessian, both triangles, with
    repeated entries left to be summed, and its size 7F. Built for all blocks at once."""
    n = system.num_poses
    new_index = torch.full((n,), -1, dtype=torch.int64, device=free.device)
    new_index[free] = torch.arange(int(free.sum()), device=free.device)
    diag = torch.arange(n, device=free.device)
    rows, cols, values = [], [], []
    for bi, bj, blocks in (
        (diag, diag, system.H_diag),
        (system.off_i, system.off_j, system.H_off),
        (system.off_j, system.off_i, system.H_off.transpose(-1, -2)),
    ):
        keep = free[bi] & free[bj]
        r, c = _block_entry_indices(new_index[bi[keep]], new_index[bj[keep]])
        rows.append(r.reshape(-1))
        cols.append(c.reshape(-1))
        values.append(blocks[keep].reshape(-1))
    return torch.cat(rows), torch.cat(cols), torch.cat(values), int(free.sum()) * D


def free_dense(system: BlockSystem, free: torch.Tensor) -> torch.Tensor:
    """The free-pose Hessian ``(7F, 7F)``, both triangles: ``triplets_to_dense(*free_triplets(
    system, free))`` entry for entry (each entry sums the same blocks in the same order: the
    diagonal blocks, the upper off-diagonal ones in edge order, then their transposes), from
    block indices instead of scalar triplets (a small solve's cost is its tensor operations).
    """
    n, F = system.num_poses, int(free.sum())
    new_index = torch.full((n,), -1, dtype=torch.int64, device=free.device)
    new_index[free] = torch.arange(F, device=free.device)
    entry = torch.arange(D, device=free.device)
    rows, cols = entry[None, :, None], entry[None, None, :]
    H = torch.zeros(F, D, F, D, dtype=system.H_diag.dtype, device=free.device)
    diag = torch.arange(F, device=free.device)[:, None, None]
    H.index_put_((diag, rows, diag, cols), system.H_diag[free], accumulate=True)
    keep = free[system.off_i] & free[system.off_j]
    if bool(keep.any()):
        bi = new_index[system.off_i[keep]][:, None, None]
        bj = new_index[system.off_j[keep]][:, None, None]
        blocks = system.H_off[keep]
        H.index_put_((bi, rows, bj, cols), blocks, accumulate=True)
        H.index_put_((bj, rows, bi, cols), blocks.transpose(-1, -2), accumulate=True)
    return H.reshape(F * D, F * D)


def triplets_to_dense(
    rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, size: int
) -> torch.Tensor:
    """Dense matrix of summed triplets."""
    H = torch.zeros(size, size, dtype=values.dtype, device=values.device)
    return H.index_put_((rows, cols), values, accumulate=True)


def _block_entry_indices(
    rows: torch.Tensor, cols: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Scalar row / column indices ``(B, 7, 7)`` of the entries of 7x7 blocks at (rows, cols)."""
    offset = torch.arange(D, device=rows.device)
    r = (rows[:, None, None] * D + offset[None, :, None]).expand(-1, D, D)
    c = (cols[:, None, None] * D + offset[None, None, :]).expand(-1, D, D)
    return r, c
