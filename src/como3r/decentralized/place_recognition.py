"""Inter-robot place recognition (F-Sec. III-A).

Robots in range exchange one compact place descriptor per keyframe and compare them; the
best match of each keyframe whose similarity exceeds a permissive threshold (F-Sec. IV:
0.1) becomes an inter-robot loop-closure candidate. The paper uses CosPlace; como3r has no
separate place network, so the descriptor comes from the prior's retrieval features
(:meth:`~como3r.prior.base.Prior.retrieval_features`), in one of two ways:

* ``cosine``: the attention-weighted mean of the local retrieval features, L2-normalised,
  compared by cosine similarity (CosPlace-like: one ``d``-vector per keyframe);
* ``asmk``: the local features themselves, compared by binary ASMK
  (:class:`~como3r.prior.retrieval.RetrievalDatabase`), as MASt3R-SfM does.

Both robots of a pair compute the same similarity matrix (rows: the robot with the
smaller id) and so the same candidates without another message. A candidate found as the
best match of a keyframe of robot a is registered by robot a (it decodes and owns the loop);
one found from both sides by the robot with the smaller id.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from como3r.config import RetrievalConfig
from como3r.errors import ConfigError
from como3r.prior.retrieval import Quantized, RetrievalDatabase

METHODS = ("cosine", "asmk")


@dataclass(frozen=True)
class Candidate:
    """An inter-robot loop-closure candidate between keyframe ``row`` of the robot with the
    smaller id and keyframe ``col`` of the other.

    Attributes:
        row: keyframe index of the robot with the smaller id.
        col: keyframe index of the other robot.
        similarity: place similarity.
        by_row: ``col`` is the best match of ``row`` (found from the smaller id's side).
        by_col: ``row`` is the best match of ``col``.
    """

    row: int
    col: int
    similarity: float
    by_row: bool
    by_col: bool


class PlaceRecognizer:
    """Place descriptors and their similarity for one of :data:`METHODS`.

    Args:
        method: ``cosine`` or ``asmk``.
        codebook: ``(K, d)`` ASMK codebook (``asmk`` only).
        retrieval: ASMK parameters (``asmk`` only).
    """

    def __init__(
        self,
        method: str,
        codebook: np.ndarray | None = None,
        retrieval: RetrievalConfig | None = None,
    ) -> None:
        if method not in METHODS:
            raise ConfigError(f"decentralized.place_method: {method!r} is not one of {METHODS}")
        if method == "asmk" and codebook is None:
            raise ConfigError(
                "decentralized.place_method asmk needs the prior's retrieval codebook"
            )
        self.method = method
        self._codebook = codebook
        self._retrieval = retrieval or RetrievalConfig()
        # asmk: each keyframe's descriptors quantised once, by identity (the array is kept,
        # so its id is not reused): a round's similarity re-indexes every keyframe, and at
        # the released codebook's size the search is 0.3 s a keyframe
        self._quantizer: RetrievalDatabase | None = None
        self._quantized: dict[int, tuple[np.ndarray, Quantized]] = {}

    def describe(self, features: Tensor, attention: Tensor) -> np.ndarray:
        """The place descriptor of one keyframe.

        Args:
            features: ``(N, d)`` local retrieval descriptors of the keyframe.
            attention: ``(N,)`` non-negative attention of each descriptor.

        Returns:
            ``cosine``: ``(d,)`` float32 unit vector; ``asmk``: ``(N, d)`` float32.
        """
        local = features.detach().to("cpu").float().numpy()
        if self.method == "asmk":
            return np.ascontiguousarray(local)
        weights = attention.detach().to("cpu").double().numpy()
        if not np.any(weights > 0):
            weights = np.ones_like(weights)
        aggregate = weights @ local.astype(np.float64)
        norm = np.linalg.norm(aggregate)
        return (aggregate / norm if norm > 0 else aggregate).astype(np.float32)

    def similarity(self, rows: Sequence[np.ndarray], cols: Sequence[np.ndarray]) -> np.ndarray:
        """``(len(rows), len(cols))`` float64 similarity of every pair of descriptors.

        ``asmk`` indexes ``cols`` and queries each row: the result is the same on both robots
        as long as both pass the smaller id's keyframes as ``rows``.
        """
        if not rows or not cols:
            return np.zeros((len(rows), len(cols)))
        if self.method == "cosine":
            return np.stack(rows).astype(np.float64) @ np.stack(cols).astype(np.float64).T
        database = RetrievalDatabase(self._codebook, self._retrieval)
        for k, descriptors in enumerate(cols):
            database.add(1, k, self._quantize(descriptors))
        return np.stack([database.scores(self._quantize(descriptors)) for descriptors in rows])

    def _quantize(self, descriptors: np.ndarray) -> Quantized:
        """``descriptors`` (one keyframe's, ``asmk``) with their words, searched once."""
        known = self._quantized.get(id(descriptors))
        if known is None or known[0] is not descriptors:
            if self._quantizer is None:
                self._quantizer = RetrievalDatabase(self._codebook, self._retrieval)
            known = (descriptors, self._quantizer.quantize(descriptors))
            self._quantized[id(descriptors)] = known
        return known[1]


def candidate_pairs(
    similarity: np.ndarray,
    threshold: float,
    exclude: set[tuple[int, int]] | frozenset = frozenset(),
) -> list[Candidate]:
    """Best matches of every row and every column above ``threshold`` (F-Sec. III-A).

    Args:
        similarity: ``(n_rows, n_cols)`` place similarity (rows: the smaller robot id).
        threshold: a candidate's similarity must be strictly greater.
        exclude: ``(row, col)`` pairs already handled (earlier rounds).

    Returns:
        Candidates sorted by ``(row, col)``.
    """
    found: dict[tuple[int, int], list[bool]] = {}
    if similarity.size:
        for r, c in enumerate(np.argmax(similarity, axis=1)):
            found.setdefault((r, int(c)), [False, False])[0] = True
        for c, r in enumerate(np.argmax(similarity, axis=0)):
            found.setdefault((int(r), c), [False, False])[1] = True
    return [
        Candidate(r, c, float(similarity[r, c]), by_row, by_col)
        for (r, c), (by_row, by_col) in sorted(found.items())
        if similarity[r, c] > threshold and (r, c) not in exclude
    ]
