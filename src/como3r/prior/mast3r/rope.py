"""2-D rotary position embedding of MASt3R (``'RoPE100'``, MAST3R_SPEC.md §3.2-3.3).

A head vector ``t`` of dimension ``D`` is split in two halves: dims ``[0, D/2)`` are rotated by
the token's row ``y``, dims ``[D/2, D)`` by its column ``x``. Inside a half (``Q = D/4``) the
pair ``(k, k + Q)`` is rotated by the angle ``theta_k = p * base**(-k / Q)``::

    u' = u cos(theta_k) - v sin(theta_k)
    v' = v cos(theta_k) + u sin(theta_k)

It is applied to queries and keys only. Token positions are always the regular patch grid,
so the cosine/sine tables are cached per grid size, device and precision.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: (cos, sin) tables of shape ``(N, D)``; the sine table carries the rotation's signs
RopeTable = tuple[Tensor, Tensor]


def grid_positions(grid: tuple[int, int], device: torch.device | str = "cpu") -> Tensor:
    """Patch positions ``(N, 2)`` int64, row-major: token ``n`` is at ``(n // w, n % w)``.

    Args:
        grid: ``(h, w)`` token grid.
    """
    h, w = grid
    rows = torch.arange(h, device=device).repeat_interleave(w)
    cols = torch.arange(w, device=device).repeat(h)
    return torch.stack([rows, cols], dim=-1)


class RoPE2D:
    """Cached 2-D RoPE tables and their application to ``(B, heads, N, D)`` tensors.

    Args:
        base: base frequency (100 for ``'RoPE100'``).
    """

    def __init__(self, base: float) -> None:
        self.base = float(base)
        self._tables: dict[tuple[int, int, int, torch.device, torch.dtype], RopeTable] = {}

    def table(
        self, grid: tuple[int, int], head_dim: int, device: torch.device, dtype: torch.dtype
    ) -> RopeTable:
        """Cosine and signed-sine tables ``(N, head_dim)`` for the ``(h, w)`` token grid.

        The angles are computed in float64 and stored in ``dtype`` (float64 or float32).
        """
        key = (grid[0], grid[1], head_dim, torch.device(device), dtype)
        cached = self._tables.get(key)
        if cached is None:
            cached = self._build(grid, head_dim, torch.device(device), dtype)
            self._tables[key] = cached
        return cached

    def _build(
        self, grid: tuple[int, int], head_dim: int, device: torch.device, dtype: torch.dtype
    ) -> RopeTable:
        quarter = head_dim // 4
        inv_freq = self.base ** (-torch.arange(quarter, dtype=torch.float64) / quarter)
        pos = grid_positions(grid).to(torch.float64)
        # (N, 2, Q): angles of the row half then the column half
        angles = pos[:, :, None] * inv_freq
        cos = angles.cos()
        sin = angles.sin()
        # per half: [cos, cos] and [-sin, +sin] so that rotate(t) = t*cos + swap(t)*sin
        cos_table = torch.cat([cos, cos], dim=-1).reshape(-1, head_dim)
        sin_table = torch.cat([-sin, sin], dim=-1).reshape(-1, head_dim)
        return cos_table.to(device, dtype), sin_table.to(device, dtype)

    def apply(self, t: Tensor, grid: tuple[int, int]) -> Tensor:
        """Rotate ``t`` ``(B, heads, N, D)`` by the positions of the ``(h, w)`` grid.

        Half-precision inputs are rotated in float32 and cast back (as the official CUDA
        kernel does); float32 and float64 inputs keep their precision.
        """
        head_dim = t.shape[-1]
        work_dtype = t.dtype if t.dtype in (torch.float32, torch.float64) else torch.float32
        cos, sin = self.table(grid, head_dim, t.device, work_dtype)
        work = t.to(work_dtype)
        quarter = head_dim // 4
        # swap the (u, v) parts inside each half: (..., half, part, k) -> flip part
        swapped = work.unflatten(-1, (2, 2, quarter)).flip(-2).flatten(-3)
        return (work * cos + swapped * sin).to(t.dtype)
