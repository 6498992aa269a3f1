"""Compact codings of a keyframe's retrieval on the lossy wire and in the session store
(registered in :mod:`~.codec_compact`, which states the conventions).

* ``"retrieval"``: a keyframe's ``(descriptors (N, d), attention (N,))`` float32: every
  descriptor in 8 bits with its own scale (its largest magnitude over 127), the attention
  in float16. The coordinator's binary ASMK keeps only the signs of per-word residual sums
  (:mod:`como3r.prior.retrieval`); on 17 keyframes of 2 synthetic agents (simulated prior,
  300 x 128; ``benchmarks/retrieval_precision.py``) every query's hits were the same as with
  float32 features, with the agents' words and with the coordinator quantising, their
  similarities within 4.4e-4. An agent with a codebook sends instead what that ASMK reads
  of them (:class:`~como3r.prior.retrieval.Aggregated`: per-word sign bits), losslessly:
  the query's word ids as ``"ascending"``, its bits raw, the build's words (among the
  query's: their nearest) as a mask over them and only the build bits that differ from the
  query's of the same word (MASt3R's shapes, 300 independent descriptors: 192 kB against
  230 kB for both halves whole and 287 kB for the 8-bit descriptors with their words). An
  aggregate that does not fit this travels as the object it is, its word ids as:
* ``"ascending"``: an ``(n,)`` int64 array of ascending non-negative ids, lossless, as its
  first value and steps (:func:`~.codec_planes.pack_ints`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from como3r.errors import MessageError
from como3r.prior.retrieval import Aggregated
from como3r.transport.codec_arrays import TAG, Budget, exact_keys, zstd
from como3r.transport.codec_planes import (
    CODED,
    ZSTD_LEVEL,
    as_kind,
    coded_header,
    float32_or_none,
    inflate,
    kind_of,
    pack_ints,
    unpack_ints,
)


def retrieval_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    if isinstance(value, Aggregated):
        return _aggregate_encode(value)
    if not (isinstance(value, tuple) and len(value) == 2):
        return None
    descriptors, attention = float32_or_none(value[0], 2), float32_or_none(value[1], 1)
    if descriptors is None or attention is None or not np.isfinite(descriptors).all():
        return None
    if not (np.isfinite(attention).all() and np.abs(attention).max(initial=0) < 65504):
        return None
    scale = np.abs(descriptors).max(axis=1) / 127
    scale = np.where(scale > 0, scale, 1).astype(np.float32)
    q = np.rint(descriptors / scale[:, None]).astype(np.int8)
    return {
        "kind": kind_of(value[0]),
        "shape": list(descriptors.shape),
        "q": zstd.compress(q.tobytes(), level=ZSTD_LEVEL),
        "scale": scale.tobytes(),
        "attention": attention.astype(np.float16).tobytes(),
    }


def _aggregate_encode(value: Aggregated) -> dict[str, Any] | None:
    """An :class:`Aggregated` keyframe, lossless: the query's word ids as steps and its bits
    raw; the build's words (the query's nearest, so among them) as a mask over the query's,
    and of their bits only those that differ from the query's bits of the same word (a word
    no other descriptor has among its next nearest has the same descriptors, so the same
    bits, in both: most of them)."""
    arrays = (value.query_words, value.query_bits, value.build_words, value.build_bits)
    if not all(isinstance(a, np.ndarray) for a in arrays):
        return None
    query_words, query_bits, build_words, build_bits = arrays
    if not (
        isinstance(value.codebook_id, str)
        and query_words.dtype == build_words.dtype == np.int64
        and query_bits.dtype == build_bits.dtype == np.uint32
        and query_words.ndim == build_words.ndim == 1
        and query_bits.ndim == build_bits.ndim == 2
        and query_bits.shape[0] == query_words.size
        and build_bits.shape == (build_words.size, query_bits.shape[1])
    ):
        return None
    at = np.searchsorted(query_words, build_words)
    if build_words.size and (
        at.max() >= query_words.size or not np.array_equal(query_words[at], build_words)
    ):
        return None  # build words outside the query's
    ids = ascending_encode(query_words)
    if ids is None or (build_words.size and (np.diff(build_words) <= 0).any()):
        return None
    in_build = np.zeros(query_words.size, bool)
    in_build[at] = True
    same = (query_bits[at] == build_bits).all(axis=1)
    return {
        "codebook_id": value.codebook_id,
        "width": int(query_bits.shape[1]),
        "query_words": ids,
        "query_bits": query_bits.astype("<u4").tobytes(),
        "build": zstd.compress(np.packbits(in_build).tobytes(), level=ZSTD_LEVEL),
        "same": zstd.compress(np.packbits(same).tobytes(), level=ZSTD_LEVEL),
        "build_bits": build_bits[~same].astype("<u4").tobytes(),
    }


def _aggregate_decode(body: dict, path: str, budget: Budget) -> Aggregated:
    keys = ("codebook_id", "width", "query_words", "query_bits", "build", "same", "build_bits")
    exact_keys(body, ("coding", *keys), path)
    codebook_id, width = body["codebook_id"], body["width"]
    if not (isinstance(codebook_id, str) and len(codebook_id) <= 128):
        raise MessageError(f"{path}: coded aggregate's codebook id is not a short string")
    if not (isinstance(width, int) and not isinstance(width, bool) and 0 < width <= 1024):
        raise MessageError(f"{path}: coded aggregate's width {width!r}")
    ids = body["query_words"]
    if not isinstance(ids, dict):
        raise MessageError(f"{path}: coded aggregate's query words are not a coding")
    query_words = ascending_decode(
        {**ids, TAG: CODED, "coding": "ascending"}, f"{path}.query_words", budget
    )
    n = query_words.size
    raw = body["query_bits"]
    if not (isinstance(raw, bytes) and len(raw) == 4 * n * width):
        raise MessageError(f"{path}: coded aggregate's query bits are not {n} x {width} words")
    query_bits = np.frombuffer(raw, "<u4").astype(np.uint32).reshape(n, width)
    size = (n + 7) // 8
    in_build = np.unpackbits(
        np.frombuffer(inflate(body["build"], size, path, "build mask", f"{size} bytes"), np.uint8),
        count=n,
    ).astype(bool)
    m = int(in_build.sum())
    size = (m + 7) // 8
    same = np.unpackbits(
        np.frombuffer(inflate(body["same"], size, path, "same mask", f"{size} bytes"), np.uint8),
        count=m,
    ).astype(bool)
    raw = body["build_bits"]
    differing = int((~same).sum())
    if not (isinstance(raw, bytes) and len(raw) == 4 * differing * width):
        raise MessageError(f"{path}: coded aggregate's build bits are not {differing} rows")
    build_bits = query_bits[in_build].copy()
    build_bits[~same] = np.frombuffer(raw, "<u4").reshape(differing, width)
    return Aggregated(codebook_id, query_words, query_bits, query_words[in_build], build_bits)


def retrieval_decode(body: dict, path: str, budget: Budget) -> Any:
    if "codebook_id" in body:
        return _aggregate_decode(body, path, budget)
    kind, (n, d) = coded_header(body, ("q", "scale", "attention"), 2, path)
    packed, scale, attention = body["q"], body["scale"], body["attention"]
    if not all(isinstance(b, bytes) for b in (packed, scale, attention)):
        raise MessageError(f"{path}: coded retrieval features are not bytes")
    if len(scale) != 4 * n or len(attention) != 2 * n:
        raise MessageError(f"{path}: coded retrieval scales or attention are not {n} values")
    budget.take(n * d, path)
    raw = inflate(packed, n * d, path, "coded descriptors", f"{n} x {d} bytes")
    scales = np.frombuffer(scale, "<f4").astype(np.float32)
    if not np.isfinite(scales).all():
        raise MessageError(f"{path}: coded descriptor scales are not finite")
    q = np.frombuffer(raw, np.int8).reshape(n, d).astype(np.float32)
    descriptors = q * scales[:, None]
    weights = np.frombuffer(attention, "<f2").astype(np.float32)
    return (as_kind(descriptors, kind), as_kind(weights, kind))


def ascending_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    if not (
        isinstance(value, np.ndarray)
        and value.ndim == 1
        and value.dtype == np.int64
        and (value.size == 0 or (value[0] >= 0 and (np.diff(value) > 0).all()))
    ):
        return None
    steps = pack_ints(np.diff(value, prepend=np.int64(0)))
    return None if steps is None else {"count": int(value.size), "steps": steps}


def ascending_decode(body: dict, path: str, budget: Budget) -> Any:
    exact_keys(body, ("coding", "count", "steps"), path)
    count = body["count"]
    if not (isinstance(count, int) and not isinstance(count, bool) and 0 <= count < 2**32):
        raise MessageError(f"{path}: coded ids' count {count!r}")
    steps = unpack_ints(body["steps"], count, path, budget)
    if (steps[1:] <= 0).any() or (count and steps[0] < 0):
        raise MessageError(f"{path}: coded ids are not ascending non-negative integers")
    return np.cumsum(steps)
