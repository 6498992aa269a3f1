"""Reciprocal nearest-neighbour matching of two views' descriptors (F-Sec. III-B).

MASt3R's fast reciprocal matching (official ``fast_nn.fast_reciprocal_NNs``): queries start
on a grid of view i; each iteration maps them to their nearest neighbour in view j and back
to view i, and a query whose round trip returns to itself is a match.

The nearest neighbours are exact (largest dot product over every confident pixel of the
other view), searched with faiss' flat inner-product index, which fuses the product with
the top-1 selection block by block instead of writing a ``(queries, pixels)`` score matrix.
Each pixel's neighbour is searched at most once per call: the round trips of different
queries meet on the same pixels, and later iterations start where earlier ones ended.
"""

from __future__ import annotations

import logging
import math

import faiss
import numpy as np
import torch
from torch import Tensor

from como3r.decentralized.config import RegistrationConfig

logger = logging.getLogger(__name__)


class _NearestCache:
    """Exact nearest neighbours of one view's pixels in the other view, each searched once.

    Args:
        source: ``(N, d)`` float32 descriptors whose neighbours are asked for.
        target: ``(M, d)`` float32 descriptors searched (M >= 1).
    """

    def __init__(self, source: np.ndarray, target: np.ndarray) -> None:
        self._source = source
        self._index = faiss.IndexFlatIP(target.shape[1])
        self._index.add(target)
        self._nearest = np.full(source.shape[0], -1, dtype=np.int64)

    def __call__(self, rows: np.ndarray) -> np.ndarray:
        """``(Q,)`` int64 target rows nearest to the ``(Q,)`` source ``rows``."""
        missing = np.unique(rows[self._nearest[rows] < 0])
        if missing.size:
            _, found = self._index.search(np.ascontiguousarray(self._source[missing]), 1)
            self._nearest[missing] = found[:, 0]
        return self._nearest[rows]

    @property
    def searched(self) -> int:
        """Source rows whose neighbour has been searched so far."""
        return int((self._nearest >= 0).sum())


def _grid_axis(size: int, spacing: float) -> Tensor:
    """Pixel centres ``floor((k + 1/2) spacing)`` along an axis of ``size`` pixels (at least
    one), int64."""
    count = max(1, math.ceil(size / spacing - 0.5))
    positions = torch.floor((torch.arange(count, dtype=torch.float64) + 0.5) * spacing)
    return torch.unique(positions.long().clamp(max=size - 1))


def query_grid(height: int, width: int, stride_ratio: float) -> Tensor:
    """Flat indices ``(G,)`` int64 of the query pixels of a ``height`` x ``width`` view.

    The grid's spacing is ``stride_ratio`` times the view's long side (at least one pixel),
    so a view sees the same grid at any resolution: about ``1 / stride_ratio`` queries along
    the long side. With an integer spacing ``S`` in pixels the pixels are the official
    code's ``S // 2 + k S`` (``fast_reciprocal_NNs(subsample_or_initxy1=S)``).
    """
    spacing = max(1.0, stride_ratio * max(height, width))
    rows, cols = _grid_axis(height, spacing), _grid_axis(width, spacing)
    return (rows[:, None] * width + cols[None, :]).reshape(-1)


def reciprocal_matches(D_i: Tensor, D_j: Tensor, Q_i: Tensor, Q_j: Tensor,
                       config: RegistrationConfig) -> tuple[Tensor, Tensor]:
    """Reciprocal nearest neighbours between the confident descriptors of two views.

    Only pixels with descriptor confidence ``Q > min_descriptor_confidence`` take part, as
    queries and as neighbours. Queries start on :func:`query_grid` of view i; at most
    ``match_iterations`` round trips (module docstring).

    Args:
        D_i, D_j: ``(H, W, d)`` unit descriptors of views i and j (one decode).
        Q_i, Q_j: ``(H, W)`` descriptor confidences.
        config: matching parameters.

    Returns:
        ``(M,)`` int64 flat pixel indices of view i and ``(M,)`` of view j, unique pairs
        sorted by view i's index.
    """
    H, W, d = D_i.shape
    q_min = config.min_descriptor_confidence
    pixels_i = torch.nonzero(Q_i.reshape(-1) > q_min)[:, 0]
    pixels_j = torch.nonzero(Q_j.reshape(-1) > q_min)[:, 0]
    none = torch.zeros(0, dtype=torch.long)
    if pixels_i.numel() == 0 or pixels_j.numel() == 0:
        return none, none
    # faiss parallelises over OpenMP's own thread count (every core): give it this
    # process's PyTorch threads, as the compiled kernels take them (como3r.jit)
    faiss.omp_set_num_threads(torch.get_num_threads())
    flat_i = D_i.reshape(-1, d)[pixels_i].float().contiguous().numpy()
    flat_j = D_j.reshape(-1, d)[pixels_j].float().contiguous().numpy()
    i_to_j, j_to_i = _NearestCache(flat_i, flat_j), _NearestCache(flat_j, flat_i)
    # row of each pixel in flat_i (-1: not confident), to start from the grid's pixels
    row_of = torch.full((H * W,), -1, dtype=torch.long)
    row_of[pixels_i] = torch.arange(pixels_i.numel())
    query = row_of[query_grid(H, W, config.match_stride_ratio)]
    query = query[query >= 0].numpy()
    found_i, found_j = [], []
    for _ in range(config.match_iterations):
        if query.size == 0:
            break
        in_j = i_to_j(query)
        back = j_to_i(in_j)
        converged = back == query
        found_i.append(query[converged])
        found_j.append(in_j[converged])
        query = np.unique(back[~converged])
    if not found_i:
        return none, none
    pairs = np.unique(np.stack([np.concatenate(found_i), np.concatenate(found_j)], axis=1),
                      axis=0)
    logger.debug("reciprocal matching: %d matches, %d + %d neighbours searched",
                 pairs.shape[0], i_to_j.searched, j_to_i.searched)
    return pixels_i[torch.from_numpy(pairs[:, 0])], pixels_j[torch.from_numpy(pairs[:, 1])]
