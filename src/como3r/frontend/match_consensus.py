"""The descriptor search's consensus below the paper's 512 px (C-Sec. 3.3; como3r addition,
``matching.descriptor_consensus``): each match's move by the search is replaced by the median
move of its neighbours, which keeps the prior's slowly varying error the search corrects and
drops the per-pixel descriptor noise it follows on flat paint.
:class:`como3r.config.MatchingConfig` says why and what it measured.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from como3r.frontend import cpu_kernels
from como3r.geometry.units import PAPER_LONG_SIDE


def consensus_window(long_side: int) -> int:
    """Side of the query-pixel window whose median displacement replaces each match's own
    (:func:`displacement_consensus`): the smallest odd number of pixels at least
    ``512 / long_side``; 1 (no consensus, the paper's search) at 512 px and above.
    :class:`como3r.config.MatchingConfig` says why and what it measured."""
    ratio = PAPER_LONG_SIDE / long_side
    return max(1, 2 * math.ceil((ratio - 1.0) / 2.0) + 1)


def displacement_consensus(
    projected: Tensor,
    searched: Tensor,
    active: Tensor,
    query_shape: tuple[int, int],
    search_shape: tuple[int, int],
    window: int,
) -> Tensor:
    """Each match moved by the median of the descriptor search's moves around its query pixel,
    unless the search's own pixel is within a pixel of that.

    The search corrects the prior's geometric error, which varies slowly over the image
    (pose, focal and principal point of the two heads); the descriptors' noise is per
    pixel and, where they cannot tell pixels apart (flat paint), the search follows it.
    The median over a ``window x window`` block of query pixels keeps the first and
    drops the second (per axis; only active matches vote, the lower median of an even
    count, so every displacement stays a whole number of pixels).

    Args:
        projected: ``(B, P, 2)`` int64 matches before the search.
        searched: ``(B, P, 2)`` int64 matches after it.
        active: ``(B, P)`` bool, the matches the search refined; the others keep
            ``searched``.
        query_shape: ``(Hq, Wq)`` with ``P = Hq * Wq``, row-major.
        search_shape: ``(H, W)`` of the searched view.
        window: odd side of the block.

    Returns:
        ``(B, P, 2)`` int64 matches inside the searched view.
    """
    (H, W) = search_shape
    if projected.device.type == "cpu":  # counting in a compiled loop, 10-20x faster
        median = cpu_kernels.move_medians(searched - projected, active, query_shape, window)
    else:
        median = _move_medians(searched - projected, active, query_shape, window)
    consensus = projected + median
    upper = torch.tensor([W - 1, H - 1], device=projected.device)
    consensus = consensus.clamp(min=0).minimum(upper)
    # within a pixel of the consensus the search's own pixel stays: the median cannot carry
    # the per-pixel part (the rounding to the pixel grid; a noise-free prior tracked 10 deg
    # of yaw 1.005e-3 rad off without this, tests/frontend/test_tracker.py, bound 1e-3)
    agree = (searched - consensus).abs().amax(dim=-1) <= 1
    kept = torch.where(agree[..., None], searched, consensus)
    return torch.where(active[..., None], kept, searched)


def _move_medians(
    moves: Tensor, active: Tensor, query_shape: tuple[int, int], window: int
) -> Tensor:
    """Per match the lower median per axis of the active ``moves`` ``(B, P, 2)`` int64 in the
    ``window x window`` block of query pixels around it -> ``(B, P, 2)`` int64 (0 where no
    active move votes), as batched PyTorch (any device)."""
    B = moves.shape[0]
    Hq, Wq = query_shape
    grid = moves.to(torch.float32).masked_fill(~active[..., None], float("nan"))
    grid = grid.reshape(B, Hq, Wq, 2).permute(0, 3, 1, 2)
    pad = window // 2
    grid = torch.nn.functional.pad(grid, (pad,) * 4, value=float("nan"))
    blocks = grid.unfold(2, window, 1).unfold(3, window, 1).reshape(B, 2, Hq, Wq, -1)
    median = blocks.nanmedian(dim=-1).values.permute(0, 2, 3, 1).reshape(B, -1, 2)
    return median.nan_to_num(0.0).round().long()
