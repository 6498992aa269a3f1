"""Reciprocal nearest-neighbour matching of two views' descriptors (F-Sec. III-B).

MASt3R's fast reciprocal matching (official ``fast_nn.fast_reciprocal_NNs``): queries start
on a grid of view i; each iteration maps them to their nearest neighbour in view j and back
to view i, and a query whose round trip returns to itself is a match.

The nearest neighbours are searched coarse to fine instead of over every pixel of the other
view (the official code's exact search cost a third of a MASt3R decode per pair on a CPU):
the coarse level is the other view's confident pixels on the query grid
(:func:`query_grid`, the same spacing in both views), searched exactly with faiss' flat
inner-product index for the ``match_coarse_candidates`` most similar; the fine level is every
confident pixel within half a grid spacing of one of them (:func:`refine_radius`: the
candidate's grid cell), of which the most similar is the neighbour. Matches therefore land
on any pixel, not only on the grid. Each pixel's neighbour is searched at most once per
call: the round trips of different queries meet on the same pixels, and later iterations
start where earlier ones ended. With a grid of one pixel the search is exact.
"""

from __future__ import annotations

import logging
import math

import faiss
import numpy as np
import torch
from torch import Tensor

from como3r.config_decentralized import RegistrationConfig

logger = logging.getLogger(__name__)


class _CoarseToFine:
    """Nearest neighbours of one view's pixels in the other view (module docstring), each
    pixel searched once.

    Args:
        source: ``(N, d)`` float32 descriptors of every pixel of the view asking.
        target: ``(H, W, d)`` float32 descriptors of the view searched.
        confident: ``(H * W,)`` bool, the target pixels that may be neighbours.
        coarse: ``(G,)`` int64 flat indices of the confident target pixels of the coarse
            level (G >= 1).
        radius: half side of the square window searched around a coarse candidate [px].
        candidates: coarse candidates refined per pixel (clipped to G).
    """

    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        confident: np.ndarray,
        coarse: np.ndarray,
        radius: int,
        candidates: int,
    ) -> None:
        self._source = source
        self._height, self._width, d = target.shape
        self._target = target.reshape(-1, d)
        self._confident = confident
        self._coarse = coarse
        self._index = faiss.IndexFlatIP(d)
        self._index.add(np.ascontiguousarray(self._target[coarse]))
        self._candidates = min(candidates, coarse.size)
        side = np.arange(-radius, radius + 1)
        self._dy, self._dx = (o.reshape(-1) for o in np.meshgrid(side, side, indexing="ij"))
        self._nearest = np.full(source.shape[0], -1, dtype=np.int64)

    def __call__(self, pixels: np.ndarray) -> np.ndarray:
        """``(Q,)`` int64 flat target pixels nearest to the ``(Q,)`` source ``pixels``."""
        missing = np.unique(pixels[self._nearest[pixels] < 0])
        if missing.size:
            self._nearest[missing] = self._search(np.ascontiguousarray(self._source[missing]))
        return self._nearest[pixels]

    def _search(self, queries: np.ndarray) -> np.ndarray:
        """``(Q,)`` flat target pixels nearest to ``queries (Q, d)`` among the windows of
        their coarse candidates."""
        _, found = self._index.search(queries, self._candidates)
        rows = np.arange(queries.shape[0])
        best = np.full(queries.shape[0], -np.inf, dtype=np.float32)
        nearest = np.zeros(queries.shape[0], dtype=np.int64)
        for candidate in self._coarse[found.T]:
            y = candidate[:, None] // self._width + self._dy
            x = candidate[:, None] % self._width + self._dx
            inside = (y >= 0) & (y < self._height) & (x >= 0) & (x < self._width)
            window = np.clip(y, 0, self._height - 1) * self._width + np.clip(x, 0, self._width - 1)
            scores = np.einsum("qkd,qd->qk", self._target[window], queries)
            scores[~(inside & self._confident[window])] = -np.inf
            column = scores.argmax(axis=1)
            score = scores[rows, column]
            better = score > best
            best[better] = score[better]
            nearest[better] = window[rows, column][better]
        return nearest

    @property
    def searched(self) -> int:
        """Source pixels whose neighbour has been searched so far."""
        return int((self._nearest >= 0).sum())


def _grid_axis(size: int, spacing: float) -> Tensor:
    """Pixel centres ``floor((k + 1/2) spacing)`` along an axis of ``size`` pixels (at least
    one), int64."""
    count = max(1, math.ceil(size / spacing - 0.5))
    positions = torch.floor((torch.arange(count, dtype=torch.float64) + 0.5) * spacing)
    return torch.unique(positions.long().clamp(max=size - 1))


def grid_spacing(height: int, width: int, stride_ratio: float) -> float:
    """Spacing [px] of the query grid of a ``height`` x ``width`` view: ``stride_ratio``
    times its long side, at least one pixel."""
    return max(1.0, stride_ratio * max(height, width))


def refine_radius(height: int, width: int, stride_ratio: float) -> int:
    """Half side [px] of the window searched at full resolution around a coarse candidate:
    half the grid spacing (:func:`grid_spacing`), rounded up, so the windows of neighbouring
    grid pixels meet (4 px at 512 and the default 1/64; 2 px at 160)."""
    return math.ceil(grid_spacing(height, width, stride_ratio) / 2)


def query_grid(height: int, width: int, stride_ratio: float) -> Tensor:
    """Flat indices ``(G,)`` int64 of the query pixels of a ``height`` x ``width`` view.

    The grid's spacing is ``stride_ratio`` times the view's long side (at least one pixel),
    so a view sees the same grid at any resolution: about ``1 / stride_ratio`` queries along
    the long side. With an integer spacing ``S`` in pixels the pixels are the official
    code's ``S // 2 + k S`` (``fast_reciprocal_NNs(subsample_or_initxy1=S)``).
    """
    spacing = grid_spacing(height, width, stride_ratio)
    rows, cols = _grid_axis(height, spacing), _grid_axis(width, spacing)
    return (rows[:, None] * width + cols[None, :]).reshape(-1)


def reciprocal_matches(
    D_i: Tensor, D_j: Tensor, Q_i: Tensor, Q_j: Tensor, config: RegistrationConfig
) -> tuple[Tensor, Tensor]:
    """Reciprocal nearest neighbours between the confident descriptors of two views.

    Only pixels with descriptor confidence ``Q > min_descriptor_confidence`` take part, as
    queries and as neighbours. Queries start on :func:`query_grid` of view i; at most
    ``match_iterations`` round trips; neighbours searched coarse to fine (module docstring).

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
    confident_i = (Q_i.reshape(-1) > q_min).numpy()
    confident_j = (Q_j.reshape(-1) > q_min).numpy()
    grid = query_grid(H, W, config.match_stride_ratio).numpy()
    coarse_i, coarse_j = grid[confident_i[grid]], grid[confident_j[grid]]
    none = torch.zeros(0, dtype=torch.long)
    if coarse_i.size == 0 or coarse_j.size == 0:
        return none, none
    # faiss parallelises over OpenMP's own thread count (every core): give it this
    # process's PyTorch threads, as the compiled kernels take them (como3r.jit)
    faiss.omp_set_num_threads(torch.get_num_threads())
    flat_i = D_i.float().contiguous().numpy()
    flat_j = D_j.float().contiguous().numpy()
    radius = refine_radius(H, W, config.match_stride_ratio)
    k = config.match_coarse_candidates
    i_to_j = _CoarseToFine(flat_i.reshape(-1, d), flat_j, confident_j, coarse_j, radius, k)
    j_to_i = _CoarseToFine(flat_j.reshape(-1, d), flat_i, confident_i, coarse_i, radius, k)
    query = coarse_i
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
    pairs = np.unique(np.stack([np.concatenate(found_i), np.concatenate(found_j)], axis=1), axis=0)
    logger.debug(
        "reciprocal matching: %d matches, %d + %d neighbours searched",
        pairs.shape[0],
        i_to_j.searched,
        j_to_i.searched,
    )
    return torch.from_numpy(pairs[:, 0]), torch.from_numpy(pairs[:, 1])
