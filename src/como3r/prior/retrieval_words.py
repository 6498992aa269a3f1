"""What place retrieval hands around (:mod:`como3r.prior.retrieval`, C-Sec. B.3): a
keyframe's quantised descriptors, a retrieved hit, and the two functions that name a codebook and assign descriptors to its words. The retrieval module
re-exports every name; import from there.
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numpy as np
import torch

__all__ = ["PACK_BITS", "Hit", "Quantized", "codebook_fingerprint", "nearest_words"]

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
