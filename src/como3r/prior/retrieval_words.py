"""What place retrieval hands around (:mod:`como3r.prior.retrieval`, C-Sec. B.3): a
keyframe's quantised descriptors, its aggregated binary ASMK words, a retrieved hit, and the
two functions that name a codebook and assign descriptors to its words. The retrieval module
re-exports every name; import from there.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

__all__ = ["PACK_BITS", "Aggregated", "Hit", "Quantized", "codebook_fingerprint", "nearest_words"]

#: bits per packed word of ``asmk.hamming.binarize_and_pack_2D``
PACK_BITS = 32


class Quantized(NamedTuple):
    """A keyframe's retrieval descriptors with their nearest visual words, quantised once
    (:meth:`RetrievalDatabase.quantize`) for a query and a later add: at the released
    codebook's size (65,536 words of d = 1024, 300 descriptors a keyframe) the exact
    nearest-centroid search is about 0.35 s of one CPU core, the rest of a query or an add a
    few milliseconds.

    Attributes:
        descriptors: ``(n, d)`` float32 (numpy, or torch as a packet brings them).
        words: ``(n, MA)`` integer ids of the nearest centroids (L2), nearest first, ``MA``
            the larger of the query's and the build's multiple assignment.
    """

    descriptors: np.ndarray
    words: np.ndarray


@dataclass(frozen=True)
class Aggregated:
    """A keyframe as binary ASMK stores and queries it (:meth:`RetrievalDatabase.aggregate`):
    for each visual word its descriptors are assigned to, the sign bits of the summed
    residuals to the word's centroid, packed as asmk packs them. Everything the database
    reads of a keyframe: :meth:`RetrievalDatabase.query_and_add` (and :meth:`~RetrievalDatabase.add`,
    which reads the build half) with it gives the hits and similarities of the descriptors
    themselves, in a database of the same codebook (``codebook_id``) and configuration. At
    the released codebook's size (d = 1024) a word is 128 bytes: about 1,500 words for a
    query (``multiple_assignment_query`` 5) and 300 for an add
    (``multiple_assignment_build`` 1) of 300 random descriptors, fewer where descriptors
    share words. An agent sends its keyframes' retrieval so (issue 39): the coordinator
    reads nothing else of them.

    Attributes:
        codebook_id: :func:`codebook_fingerprint` of the codebook the words index.
        query_words: ``(Wq,)`` int64 ascending ids of the query's words.
        query_bits: ``(Wq, ceil(d / 32))`` uint32 packed sign bits of the query's words.
        build_words: ``(Wb,)`` int64 ascending ids of the stored image's words.
        build_bits: ``(Wb, ceil(d / 32))`` uint32 packed sign bits of the stored image's.
    """

    codebook_id: str
    query_words: np.ndarray
    query_bits: np.ndarray
    build_words: np.ndarray
    build_bits: np.ndarray


class Hit(NamedTuple):
    """One retrieved keyframe: its agent, its keyframe index and the ASMK similarity."""

    agent: int
    keyframe: int
    similarity: float


def codebook_fingerprint(codebook: np.ndarray) -> str:
    """32 hex digits (BLAKE2b) of a codebook's shape and float32 values: two processes
    whose fingerprints agree assign the same words (0.19 s for the released codebook's
    268 MB on one core, once per database)."""
    centroids = np.ascontiguousarray(codebook, dtype=np.float32)
    digest = hashlib.blake2b(repr(centroids.shape).encode(), digest_size=16)
    digest.update(memoryview(centroids).cast("B"))
    return digest.hexdigest()


def nearest_words(
    descriptors: torch.Tensor, centroids: torch.Tensor, multiple_assignment: int
) -> torch.Tensor:
    """The ``multiple_assignment`` nearest centroids of every descriptor by squared L2
    distance, nearest first, on the inputs' device, as MASt3R-SLAM quantises on the GPU
    (MAST3R_SPEC.md §8.4: ``|x|^2 + |c|^2 - 2 x.c``, then the smallest).

    Args:
        descriptors: ``(n, d)`` float32.
        centroids: ``(K, d)`` float32, same device.
        multiple_assignment: ``MA <= K``.

    Returns:
        ``(n, MA)`` int64 centroid ids.
    """
    distances = torch.addmm(
        (centroids * centroids).sum(1)[None], descriptors, centroids.T, alpha=-2.0
    )
    distances += (descriptors * descriptors).sum(1, keepdim=True)
    return distances.topk(multiple_assignment, dim=1, largest=False, sorted=True).indices
