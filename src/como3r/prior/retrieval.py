"""Place retrieval with binary ASMK over an incremental inverted file (C-Sec. B.3).

Prior-agnostic: the MASt3R retrieval head and the simulated prior both produce local
descriptors ``(n, d)``; this module indexes them per keyframe and answers "which stored
keyframes look like this one". The ASMK kernel, the aggregation and the inverted file are
those of the ``asmk`` package (MIT, jenicek/asmk; MAST3R_SPEC.md §8.7), configured as the
MASt3R ``Retriever`` configures it (§8.3, :class:`~como3r.config.RetrievalConfig`):

* quantisation to the ``multiple_assignment_build`` (1) nearest centroids when adding and
  ``multiple_assignment_query`` (5) when querying;
* per visual word, the residuals to the centroid are summed and binarised (``binary``);
* ``s = 1 - 2 h`` for the normalised Hamming distance ``h`` of two words' bit vectors,
  ``sigma(s) = s^alpha`` where ``s >= similarity_threshold_asmk`` and 0 elsewhere;
* score ``S(q, d) = sum_w sigma(s_w) / sqrt(|W_q| |W_d|)`` (no IDF, ``use_idf`` False).

The normaliser of ``h`` is the packed bit count, ``32 * ceil(d / 32)``: for ``d`` not a
multiple of 32 the padding bits always agree and ``s`` is biased towards 1 (asmk behaviour,
kept for identical scores). Features of the simulated prior should use such a ``d``.

The codebook of the official release is a pickle; :func:`load_codebook` reads it with a
restricted unpickler that admits only the numpy objects an array needs
(:mod:`como3r.prior.codebook`, which also trains one).

A keyframe's quantised descriptors (:class:`Quantized`), a hit (:class:`Hit`) and the word
assignment live in :mod:`como3r.prior.retrieval_words`; this module re-exports them.
:class:`Aggregated` stays here: the wire codec names it by this module (``transport.codec``).
"""

from __future__ import annotations

import functools
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from como3r.config import RetrievalConfig
from como3r.errors import ConfigError, InputError
from como3r.prior.codebook import as_descriptor_array

# load_codebook is named here by the manual (docs/api/index.md, "Retrieval")
from como3r.prior.codebook import load_codebook as load_codebook
from como3r.prior.retrieval_words import (
    PACK_BITS,
    Hit,
    Quantized,
    codebook_fingerprint,
    nearest_words,
)

_CPU = torch.device("cpu")


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


def _unquantized(descriptors: Any) -> Any:
    """The descriptors of a :class:`Quantized`, or ``descriptors`` themselves."""
    return descriptors.descriptors if isinstance(descriptors, Quantized) else descriptors


class RetrievalDatabase:
    """Incremental ASMK inverted file over the keyframes of all agents (C-Sec. B.3).

    Every stored image is one keyframe ``(agent, keyframe)``; asmk image ids are assigned
    consecutively in insertion order, as its inverted file requires (§8.4, "IVF add").

    Args:
        codebook: ``(K, d)`` float32 centroids (:func:`load_codebook`,
            :func:`~como3r.prior.codebook.train_codebook`).
        config: ASMK parameters. ``config.codebook_size`` describes the official MASt3R
            codebook and is not checked here: other priors bring codebooks of other sizes.
    """

    def __init__(self, codebook: np.ndarray, config: RetrievalConfig) -> None:
        from asmk import codebook as asmk_codebook  # deferred: optional dependency
        from asmk import index as asmk_index
        from asmk import inverted_file, kernel

        centroids = as_descriptor_array(codebook, "codebook")
        if min(config.multiple_assignment_build, config.multiple_assignment_query) < 1:
            raise ConfigError("retrieval.multiple_assignment_* must be >= 1")
        self.config = config
        self._codebook = asmk_codebook.Codebook(
            asmk_index.FaissL2Index(), size=int(centroids.shape[0])
        )
        self._codebook.index(centroids)
        self._centroids = centroids
        self._device_centroids: dict[torch.device, torch.Tensor] = {}  # the latest non-CPU
        self._kernel = kernel.ASMKKernel(self._codebook, binary=config.binary)
        self._ivf = inverted_file.IVF.initialize_empty(
            use_idf=config.use_idf, codebook_size=self._codebook.size
        )
        self._similarity = functools.partial(
            self._kernel.similarity,
            alpha=config.alpha,
            similarity_threshold=config.similarity_threshold_asmk,
        )
        self._keys: list[tuple[int, int]] = []
        self._index_of: dict[tuple[int, int], int] = {}

    def __len__(self) -> int:
        """Number of stored keyframes."""
        return len(self._keys)

    @property
    def dim(self) -> int:
        """Descriptor dimension ``d`` of the codebook."""
        return int(self._codebook.centroids.shape[1])

    @property
    def codebook_size(self) -> int:
        """Number of visual words ``K``."""
        return int(self._codebook.size)

    @functools.cached_property
    def codebook_id(self) -> str:
        """:func:`codebook_fingerprint` of this database's codebook: words quantised by a
        database with the same id (another process's) can be passed as :class:`Quantized`."""
        return codebook_fingerprint(self._centroids)

    @property
    def keys(self) -> list[tuple[int, int]]:
        """``(agent, keyframe)`` of every stored image, in insertion order."""
        return list(self._keys)

    def _assign(
        self, descriptors: np.ndarray, multiple_assignment: int, device: torch.device = _CPU
    ) -> np.ndarray:
        """``(n, MA)`` ids of the nearest centroids (L2), nearest first: by faiss on the CPU
        (asmk's index: 0.34 s at the released codebook's size against 0.45 s for torch's
        float32 matmul on one core), by :func:`nearest_words` on any other ``device`` (the
        descriptors' own: a CUDA run does not wait for the CPU)."""
        ma = min(multiple_assignment, self.codebook_size)
        if device.type == "cpu":
            _, word_ids = self._codebook.quantize(descriptors, multiple_assignment=ma)
            return word_ids
        if device not in self._device_centroids:
            self._device_centroids = {device: torch.from_numpy(self._centroids).to(device)}
        words = nearest_words(
            torch.from_numpy(descriptors).to(device), self._device_centroids[device], ma
        )
        return words.cpu().numpy()

    def quantize(self, descriptors: Any) -> Quantized:
        """``(n, d)`` descriptors (numpy or torch) with their nearest words for both a query
        (``multiple_assignment_query``) and an add (``multiple_assignment_build``): pass the
        result to :meth:`query`, :meth:`scores` and :meth:`add` of this database instead of
        the descriptors, which are then not quantised again."""
        config = self.config
        return Quantized(
            *self._words(
                descriptors, max(config.multiple_assignment_query, config.multiple_assignment_build)
            )
        )

    def _words(self, descriptors: Any, multiple_assignment: int) -> tuple[np.ndarray, np.ndarray]:
        """``(descriptors (n, d) float32, words (n, MA))``, from a :class:`Quantized` or by
        quantising now."""
        array = as_descriptor_array(_unquantized(descriptors), "descriptors", self.dim)
        if isinstance(descriptors, Quantized):
            ma = min(multiple_assignment, self.codebook_size)
            words = np.asarray(descriptors.words)
            if words.ndim != 2 or words.shape[0] != array.shape[0] or words.shape[1] < ma:
                raise InputError(
                    f"quantized descriptors: words of shape {words.shape}, "
                    f"expected ({array.shape[0]}, >= {ma})"
                )
            if (
                words.dtype.kind not in "iu"
                or not ((words >= 0) & (words < self.codebook_size)).all()
            ):
                raise InputError(
                    f"quantized descriptors: words must be integers in [0, {self.codebook_size})"
                )
            return array, words[:, :ma].astype(np.int64)
        device = descriptors.device if isinstance(descriptors, torch.Tensor) else _CPU
        return array, self._assign(array, multiple_assignment, device)

    def _store(self, agent: int, keyframe: int, descriptors: np.ndarray, words: np.ndarray) -> None:
        """Aggregate the assigned descriptors and append them as the next asmk image."""
        self._store_aggregated(agent, keyframe, *self._kernel.aggregate_image(descriptors, words))

    def _store_aggregated(
        self, agent: int, keyframe: int, aggregated: np.ndarray, unique_words: np.ndarray
    ) -> None:
        """Append an aggregated image (``(W, ceil(d / 32))`` bits, ``(W,)`` words)."""
        image_ids = np.full(unique_words.shape[0], len(self._keys), dtype=np.int64)
        self._ivf.add(aggregated, unique_words, image_ids)
        self._index_of[(agent, keyframe)] = len(self._keys)
        self._keys.append((agent, keyframe))

    def _prepare(
        self, agent: int, keyframe: int, descriptors: Any, attention: Any, multiple_assignment: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Validate an image to add; return its descriptors as float32 numpy and their words
        (:meth:`_words`)."""
        self._new_key(agent, keyframe)
        if attention is not None:
            n = np.shape(_unquantized(descriptors))[0]
            if tuple(np.shape(attention)) != (n,):
                raise InputError(
                    f"attention: expected shape ({n},), got {tuple(np.shape(attention))}"
                )
        return self._words(descriptors, multiple_assignment)

    def add(
        self, agent: int, keyframe: int, descriptors: Any, attention: Any | None = None
    ) -> None:
        """Index one keyframe.

        Args:
            agent: agent id of the keyframe.
            keyframe: keyframe index within the agent; ``(agent, keyframe)`` must be new.
            descriptors: ``(n, d)`` local descriptors (numpy or torch), or their
                :meth:`quantize`.
            attention: optional ``(n,)`` attention of the descriptors. Binary ASMK does not
                weight descriptors (the head's top-k selection already used attention); it
                is accepted so ``add(a, k, *prior.retrieval_features(enc))`` works.
                An :class:`Aggregated` keyframe is added by its build half (``attention``
                None).
        """
        if isinstance(descriptors, Aggregated):
            key = self._new_key(agent, keyframe)
            self._store_aggregated(*key, *self._checked(descriptors, "build"))
            return
        array, words = self._prepare(
            agent, keyframe, descriptors, attention, self.config.multiple_assignment_build
        )
        self._store(int(agent), int(keyframe), array, words)

    def _scores_of(self, descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
        """``(len(self),)`` float64 ASMK similarity of the query to every stored image."""
        return self._scores_of_aggregated(*self._kernel.aggregate_image(descriptors, words))

    def _scores_of_aggregated(self, aggregated: np.ndarray, unique_words: np.ndarray) -> np.ndarray:
        """:meth:`_scores_of` of an aggregated query (``(W, ceil(d / 32))``, ``(W,)``)."""
        ranks, ranked_scores = self._ivf.search(
            aggregated, unique_words, similarity_func=self._similarity, topk=None
        )
        scores = np.zeros(len(self._keys), dtype=np.float64)
        scores[ranks] = ranked_scores
        return scores

    def scores(self, descriptors: Any) -> np.ndarray:
        """ASMK similarity of a query image to every stored image.

        Args:
            descriptors: ``(n, d)`` query descriptors, or their :meth:`quantize` or
                :meth:`aggregate` (its query half).

        Returns:
            ``(len(self),)`` float64 scores in insertion order (see :attr:`keys`).
        """
        if isinstance(descriptors, Aggregated):
            query = self._checked(descriptors, "query")
            return self._scores_of_aggregated(*query) if self._keys else np.zeros(0)
        if not self._keys:  # validated, not quantised
            as_descriptor_array(_unquantized(descriptors), "descriptors", self.dim)
            return np.zeros(0, dtype=np.float64)
        return self._scores_of(*self._words(descriptors, self.config.multiple_assignment_query))

    def _select(
        self,
        scores: np.ndarray,
        k: int | None,
        min_similarity: float | None,
        agent: int | None,
        exclude_agent: int | None,
        exclude_keyframes: Collection[tuple[int, int]],
    ) -> list[Hit]:
        """Filter by agent, take the top ``k`` and keep those scoring > ``min_similarity``."""
        k = self.config.k_nn if k is None else int(k)
        threshold = self.config.min_similarity if min_similarity is None else min_similarity
        if k < 0:
            raise InputError(f"retrieval query: k = {k} must be >= 0")
        excluded = {(int(a), int(f)) for a, f in exclude_keyframes}
        candidates = [
            i
            for i, key in enumerate(self._keys)
            if (agent is None or key[0] == agent)
            and (exclude_agent is None or key[0] != exclude_agent)
            and key not in excluded
        ]
        # Stable sort: equal scores keep insertion order, so results are deterministic.
        ranked = sorted(candidates, key=lambda i: -scores[i])[:k]
        return [Hit(*self._keys[i], float(scores[i])) for i in ranked if scores[i] > threshold]

    def query(
        self,
        descriptors: Any,
        k: int | None = None,
        min_similarity: float | None = None,
        agent: int | None = None,
        exclude_agent: int | None = None,
        exclude_keyframes: Collection[tuple[int, int]] = (),
    ) -> list[Hit]:
        """Top-``k`` stored keyframes most similar to a query image.

        Candidates are filtered first (``agent``: only this agent's keyframes;
        ``exclude_agent``: only other agents'; ``exclude_keyframes``: ``(agent, keyframe)``
        pairs to skip), then the ``k`` best are kept if their similarity is strictly greater
        than ``min_similarity`` (MASt3R-SLAM's rule, §8.5).

        Args:
            descriptors: ``(n, d)`` query descriptors, or their :meth:`quantize`.
            k: number of neighbours; default ``config.k_nn``.
            min_similarity: similarity threshold; default ``config.min_similarity``.

        Returns:
            Hits sorted by similarity, highest first.
        """
        scores = self.scores(descriptors)
        return self._select(scores, k, min_similarity, agent, exclude_agent, exclude_keyframes)

    def query_and_add(
        self,
        agent: int,
        keyframe: int,
        descriptors: Any,
        attention: Any | None = None,
        k: int | None = None,
        min_similarity: float | None = None,
        scope: Literal["all", "own", "others"] = "all",
        exclude_keyframes: Collection[tuple[int, int]] = (),
    ) -> list[Hit]:
        """Query with a new keyframe, then index it (MASt3R-SLAM ``update``, §8.5).

        The nearest centroid of the query assignment is reused for indexing, so the
        descriptors are quantised once. ``scope`` restricts the query to the keyframe's own
        agent (``"own"``), to the other agents (``"others"``) or to none (``"all"``).

        Returns:
            The hits of the query, before the keyframe was added.
        """
        if scope not in ("all", "own", "others"):
            raise InputError(f"query_and_add: scope {scope!r} is not 'all', 'own' or 'others'")
        if isinstance(descriptors, Aggregated):
            return self._query_and_add_aggregated(
                agent, keyframe, descriptors, k, min_similarity, scope, exclude_keyframes
            )
        ma_query, ma_build = (
            self.config.multiple_assignment_query,
            self.config.multiple_assignment_build,
        )
        array, words = self._prepare(
            agent, keyframe, descriptors, attention, max(ma_query, ma_build)
        )
        hits: list[Hit] = []
        if self._keys:
            scores = self._scores_of(array, words[:, :ma_query])
            hits = self._select(
                scores,
                k,
                min_similarity,
                agent if scope == "own" else None,
                agent if scope == "others" else None,
                exclude_keyframes,
            )
        self._store(int(agent), int(keyframe), array, words[:, :ma_build])
        return hits

    def aggregate(self, descriptors: Any) -> Aggregated:
        """What this database reads of a keyframe (:class:`Aggregated`): ``(n, d)``
        descriptors (numpy or torch) or their :meth:`quantize`, aggregated per word for a
        query and for an add."""
        config = self.config
        array, words = self._words(
            descriptors, max(config.multiple_assignment_query, config.multiple_assignment_build)
        )
        ma_query = min(config.multiple_assignment_query, self.codebook_size)
        ma_build = min(config.multiple_assignment_build, self.codebook_size)
        query_bits, query_words = self._kernel.aggregate_image(array, words[:, :ma_query])
        build_bits, build_words = self._kernel.aggregate_image(array, words[:, :ma_build])
        return Aggregated(
            self.codebook_id,
            query_words.astype(np.int64),
            query_bits,
            build_words.astype(np.int64),
            build_bits,
        )

    def _checked(
        self, aggregated: Aggregated, half: Literal["query", "build"]
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(bits, words)`` of one half of an :class:`Aggregated`, or :class:`InputError`
        (another codebook's, or malformed)."""
        if aggregated.codebook_id != self.codebook_id:
            raise InputError(
                f"aggregated retrieval of codebook {aggregated.codebook_id}, this database's "
                f"is {self.codebook_id}: give every process the same codebook"
            )
        words, bits = (np.asarray(getattr(aggregated, f"{half}_{n}")) for n in ("words", "bits"))
        width = -(-self.dim // PACK_BITS)
        if words.ndim != 1 or bits.shape != (words.shape[0], width) or bits.dtype != np.uint32:
            raise InputError(
                f"aggregated {half}: words {words.shape} and uint32 bits {bits.shape} "
                f"({bits.dtype}), expected (W,) and (W, {width})"
            )
        if words.dtype.kind not in "iu" or not (
            ((words >= 0) & (words < self.codebook_size)).all() and (np.diff(words) > 0).all()
        ):
            raise InputError(
                f"aggregated {half}: words must be ascending integers in [0, {self.codebook_size})"
            )
        return bits, words.astype(np.int64)

    def _query_and_add_aggregated(
        self,
        agent: int,
        keyframe: int,
        aggregated: Aggregated,
        k: int | None,
        min_similarity: float | None,
        scope: str,
        exclude_keyframes: Collection[tuple[int, int]],
    ) -> list[Hit]:
        """:meth:`query_and_add` of an :class:`Aggregated` keyframe."""
        key = self._new_key(agent, keyframe)
        query = self._checked(aggregated, "query")
        build = self._checked(aggregated, "build")
        hits: list[Hit] = []
        if self._keys:
            hits = self._select(
                self._scores_of_aggregated(*query),
                k,
                min_similarity,
                key[0] if scope == "own" else None,
                key[0] if scope == "others" else None,
                exclude_keyframes,
            )
        self._store_aggregated(*key, *build)
        return hits

    def _new_key(self, agent: int, keyframe: int) -> tuple[int, int]:
        """``(agent, keyframe)`` as ints, or :class:`InputError` where it is stored already."""
        key = (int(agent), int(keyframe))
        if key in self._index_of:
            raise InputError(f"retrieval database: agent {key[0]} keyframe {key[1]} already added")
        return key
