"""A keyframe's large arrays in the session store in the wire's compact codings (format
version 5; issue 39, item 4: at most 3 MB per keyframe with MASt3R's shapes).

The coordinator computes on what the lossy wire gives back (:mod:`como3r.runtime.ingest`:
every keyframe and pointmap refresh goes through :func:`como3r.transport.codec.encode` with
``lossy`` and :func:`~como3r.transport.codec.decode` before it reaches the coordinator), and
those codings give back their own output unchanged. So the store keeps an array in its
coding (pointmaps as log-range and ray direction, confidences in log steps, colours as
lossless WebP, retrieval descriptors in 8 bits, matches as offsets with their ``q`` in log
steps: :mod:`como3r.transport.codec_compact`) wherever the coding gives back the very array,
and otherwise in the exact blob (:func:`~.blobs.pack_arrays`): a read always returns the
arrays the coordinator held, bit for bit.

Pointmaps the coordinator makes itself (the terminal depth refinement, a focal rescale, a
refresh corrected to the map's camera) do not code to themselves: the store writes their
coding and the coordinator takes its decoded value in their place
(:meth:`~.tables.TableWriter._write_pointmaps` *settles* them), as a pointmap received across
machines (in a run's store, :func:`~.resume.open_store`). With the ingest and this, the
demo scene (2 agents x 30 frames at 512x384, simulated prior, ``--single-process``) ended
with a merged ATE of 7.814 mm against 7.879 exact, and 1.9 MB per keyframe in ``session.db``
besides the simulated prior's encoding, against 7.1 MB (``benchmarks/message_sizes.py`` and
``benchmarks/store_speed.py`` measure the parts).

A coded blob is an object blob (:func:`~.blobs.pack_object`'s ``C3RO``, Zstandard with its
content checksum around the lossy encoding) of one of the store's own registered types
below; :func:`unpack` reads either kind.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from como3r.errors import MessageError, StoreError
from como3r.frontend.pairs import DirectedMatches
from como3r.prior.retrieval import Aggregated
from como3r.store.blobs import (
    MAX_BYTES,
    OBJECT_MAGIC,
    ZSTD_OPTIONS,
    pack_arrays,
    unpack_arrays,
    unpack_object,
)
from como3r.transport import codec
from como3r.transport.codec_arrays import zstd
from como3r.transport.codec_registry import register
from como3r.transport.codec_reuse import reusing, unremembered


@dataclass(frozen=True)
class StoredPointmap:
    """A keyframe's ``(H, W, 3)`` float32 pointmap (``X_hat`` or ``X_init``)."""

    X_hat: Tensor


@dataclass(frozen=True)
class StoredConfidence:
    """A keyframe's ``(H, W)`` float32 confidence (``C_hat`` or ``C_init``)."""

    C_hat: Tensor


@dataclass(frozen=True)
class StoredImage:
    """A keyframe's ``(H, W, 3)`` uint8 colours."""

    colors: np.ndarray


@dataclass(frozen=True)
class StoredRetrieval:
    """A keyframe's retrieval features ``(descriptors (N, d), attention (N,))``, or their
    :class:`~como3r.prior.retrieval.Aggregated` (format 6)."""

    retrieval: tuple[Tensor, Tensor] | Aggregated


@dataclass(frozen=True)
class StoredMatches:
    """Both directions of an edge's matches; ``width``: the keyframes' row length."""

    width: int
    ij: DirectedMatches
    ji: DirectedMatches

    @property
    def X_hat(self) -> Tensor:
        """An empty ``(0, width)`` array: the matches coding reads the row length of its
        owner's pointmap (offsets split into columns and rows)."""
        return torch.empty(0, self.width)


@dataclass(frozen=True)
class StoredInterMatches(StoredMatches):
    """An inter-agent edge's matches (a verification's), their ``q`` in the finer steps of
    the ``"inter_matches"`` coding (format 6)."""


STORED_TYPES = (
    StoredPointmap,
    StoredConfidence,
    StoredImage,
    StoredRetrieval,
    StoredMatches,
    StoredInterMatches,
)
for _cls, _coded in zip(
    STORED_TYPES,
    (
        {"X_hat": "pointmap"},
        {"C_hat": "confidence"},
        {"colors": "image"},
        {"retrieval": "retrieval"},
        {"ij": "matches", "ji": "matches"},
        {"ij": "inter_matches", "ji": "inter_matches"},
    ),
):
    register(_cls, version=1, coded=_coded)


def _arrays(obj: Any) -> list[Tensor]:
    """The arrays of a stored object, in the order :func:`~.blobs.pack_arrays` had them."""
    if isinstance(obj, StoredPointmap):
        return [obj.X_hat]
    if isinstance(obj, StoredConfidence):
        return [obj.C_hat]
    if isinstance(obj, StoredImage):
        return [torch.from_numpy(np.array(obj.colors))]  # decoded images may be read-only
    if isinstance(obj, StoredRetrieval):
        if isinstance(obj.retrieval, Aggregated):
            raise StoreError("retrieval aggregate: not arrays (read it with unpack_retrieval)")
        return list(obj.retrieval)
    return [getattr(m, f) for m in (obj.ij, obj.ji) for f in ("idx", "valid", "q")]


def identical(a: Any, b: Any) -> bool:
    """Same type, dtype, shape and bits (NaN never equals: it is then stored exactly)."""
    if isinstance(a, Tensor):
        return isinstance(b, Tensor) and a.dtype == b.dtype and torch.equal(a.cpu(), b)
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(identical(x, y) for x, y in zip(a, b))
    return a == b


def code(obj: Any) -> tuple[bytes, Any]:
    """A coded blob of a stored object and the object a read gives back.

    Arrays the coordinator holds as the ingest decoded them (or a read of this store)
    keep the coded maps they were decoded from (:mod:`como3r.transport.codec_reuse`): an
    object whose every coded field is such an array is neither coded nor decoded again,
    a read gives back its very arrays (half the coordinator's store writes: each
    keyframe's pointmap, confidence, colours and sequential matches were coded twice)."""
    try:
        with reusing() as reuse:
            data = codec.encode(obj, max_bytes=MAX_BYTES, lossy=True)
        if reuse.complete:
            back = obj
        else:
            with unremembered():  # the store has its map: kept, it would only take memory
                back = codec.decode(data, max_bytes=MAX_BYTES, expected=type(obj))
    except MessageError as exc:  # an array the codec cannot carry: a bug, not bad input
        raise StoreError(f"{type(obj).__name__}: cannot be coded ({exc})") from None
    return OBJECT_MAGIC + zstd.compress(data, options=ZSTD_OPTIONS), back


def pack_pointmap(array: Tensor) -> tuple[bytes, Tensor]:
    """A pointmap field's blob (``(H, W, 3)`` pointmap or ``(H, W)`` confidence) and the
    array a read gives back: ``array`` itself where its coding keeps it, else its coded
    value (the caller settles on it)."""
    # the very tensor where it can be: a copy would not be the one the ingest decoded
    plain = (
        array if array.device.type == "cpu" and not array.requires_grad else array.detach().cpu()
    )
    if array.ndim == 3:
        blob, back = code(StoredPointmap(plain))
        value = back.X_hat
    else:
        blob, back = code(StoredConfidence(plain))
        value = back.C_hat
    if value.dtype != array.dtype or value.shape != array.shape:  # not the coding's
        return pack_arrays(array), array
    same = value is array or identical(array, value)
    return blob, (array if same else value.to(array.device))


def pack_exact(obj: Any, *arrays: Tensor | np.ndarray) -> bytes:
    """``obj``'s coded blob where a read gives back the very ``arrays`` (what
    :func:`unpack` returns), else their exact blob."""
    blob, back = code(obj)
    got = [b.numpy() if isinstance(a, np.ndarray) else b for a, b in zip(arrays, _arrays(back))]
    return blob if identical(list(arrays), got) else pack_arrays(*arrays)


def pack_colours(colors: np.ndarray) -> bytes:
    return pack_exact(StoredImage(colors), colors)


def pack_retrieval(retrieval: tuple[Tensor, Tensor] | Aggregated) -> bytes:
    """A keyframe's retrieval blob: its descriptors and attention, or their
    :class:`~como3r.prior.retrieval.Aggregated` (an object blob, exact: since format 6)."""
    if isinstance(retrieval, Aggregated):
        return code(StoredRetrieval(retrieval))[0]  # lossless
    return pack_exact(StoredRetrieval(tuple(retrieval)), *retrieval)  # type: ignore[arg-type]


def unpack_retrieval(blob: bytes, what: str) -> tuple[Tensor, Tensor] | Aggregated:
    """The retrieval of a :func:`pack_retrieval` blob.

    Raises:
        StoreError: not such a blob, or damaged.
    """
    if bytes(blob[:4]) == OBJECT_MAGIC:
        obj = unpack_object(blob, STORED_TYPES, what)
        if isinstance(obj, StoredRetrieval) and isinstance(obj.retrieval, Aggregated):
            return obj.retrieval
        arrays = _arrays(obj)
    else:
        arrays = unpack_arrays(blob, what)
    if len(arrays) != 2:
        raise StoreError(f"{what}: holds {len(arrays)} arrays, not 2")
    return arrays[0], arrays[1]


def pack_matches(ij: DirectedMatches, ji: DirectedMatches, width: int) -> bytes:
    """Both directions' matches of an edge in one blob (``width``: the row length)."""
    stored = StoredMatches(width, *(_plain(m) for m in (ij, ji)))
    return pack_exact(stored, *_arrays(stored))


def _plain(matches: DirectedMatches) -> DirectedMatches:
    """``matches`` as a plain :class:`DirectedMatches`: itself where it is one (then the
    coded map it was decoded from is taken again: :func:`code`)."""
    if type(matches) is DirectedMatches:
        return matches
    return DirectedMatches(matches.idx, matches.valid, matches.q)


def settle_matches(
    ij: DirectedMatches, ji: DirectedMatches, width: int
) -> tuple[bytes, tuple[DirectedMatches, DirectedMatches] | None]:
    """Both directions' matches of an edge the coordinator made (an inter-agent edge) in
    their coding, and the matches a read gives back, which the coordinator takes in their
    place (its ``q`` in ``2^-3`` log2 steps: within 4.4 %, every valid index exact;
    :data:`~como3r.transport.codec_compact.INTER_MATCH_Q_BITS`); None
    where those are the very matches (or the matches fit no coding: their exact blob)."""
    stored = StoredInterMatches(width, *(DirectedMatches(m.idx, m.valid, m.q) for m in (ij, ji)))
    arrays = _arrays(stored)
    blob, back = code(stored)
    got = _arrays(back)
    if identical(arrays, got):
        return blob, None
    if any(a.dtype != b.dtype or a.shape != b.shape for a, b in zip(arrays, got)):
        return pack_arrays(*arrays), None  # pragma: no cover - the codec keeps dtypes
    return blob, (back.ij, back.ji)


def unpack(blob: bytes, what: str) -> list[Tensor]:
    """The arrays of a blob of either kind (:func:`~.blobs.unpack_arrays`, or a coded one).

    Raises:
        StoreError: not such a blob, or damaged.
    """
    if bytes(blob[:4]) == OBJECT_MAGIC:
        return _arrays(unpack_object(blob, STORED_TYPES, what))
    return unpack_arrays(blob, what)


def unpack_one(blob: bytes, what: str) -> Tensor:
    arrays = unpack(blob, what)
    if len(arrays) != 1:
        raise StoreError(f"{what}: holds {len(arrays)} arrays, not one")
    return arrays[0]


def unpack_matches(blob: bytes, what: str) -> Sequence[Tensor]:
    arrays = unpack(blob, what)
    if len(arrays) != 6:
        raise StoreError(f"{what}: holds {len(arrays)} arrays, not 6")
    return arrays
