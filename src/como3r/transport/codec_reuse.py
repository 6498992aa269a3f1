"""Coded values decoded in this process, taken again when the very value is coded again.

The coordinator receives every keyframe through the lossy codings
(:mod:`como3r.runtime.ingest`) and its session store then codes the same arrays in the same
codings (:mod:`como3r.store.coded`): the pinhole fit, octahedral directions and compressed
planes of the pointmap, the confidence's and the matches' planes, the colours' lossless
WebP, each twice per keyframe (about 0.5 s of the coordinator's CPU per keyframe at
512x384: ``benchmarks/coordinator_stages.py``). Every decode of a coded field remembers its
wire map with the value it gave (weakly, by the value's identity: a value no longer held is
forgotten with it); an encode inside :func:`reusing` takes that map for the same value, if
it is unchanged since, instead of coding it again, and forgets it (what took it keeps it).
The map decodes to that value bit for bit (the value was decoded from it), which is all a
coded field promises its reader; the bytes may differ from a fresh encode of it (the codings
give back their own output unchanged, not their own bytes).

Unchanged means: a tensor whose version counter (bumped by every in-place operation on it
or a view of it) is the one it was decoded with, a read-only array, or a dataclass of such
(:class:`~como3r.frontend.pairs.DirectedMatches`) holding the very arrays it was decoded
with. Anything else is coded afresh. Only the encodes inside :func:`reusing` take a map;
every other encode (a message that leaves) codes its values as before.

Threads: a value is remembered by the thread that decoded it and asked for and taken on
another (``como3r run`` decodes on the pipes' reader threads): the registry is behind one
lock; :func:`reusing` and :func:`unremembered` hold per thread (context variables).
"""

from __future__ import annotations

import dataclasses
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

import numpy as np
from torch import Tensor

#: id of a decoded value -> (a weak reference to it, its coding, its wire map, its state)
_DECODED: dict[int, tuple[weakref.ref, str, dict[str, Any], tuple]] = {}
#: Decodes remember from any thread (the pipes' readers, :mod:`.pipe_readers`) while the
#: coordinator's thread asks and takes: every access holds this lock. Reentrant: a weak
#: reference's callback (``forget``) runs on whichever thread drops the value's last
#: reference, which may be this module's own, inside its lock (a garbage collection started
#: by an allocation there).
_LOCK = threading.RLock()


@dataclass
class Reuse:
    """What the encodes inside one :func:`reusing` block did: coded fields whose decoded
    map was taken (``taken``) or that were coded afresh (``coded``)."""

    taken: int = 0
    coded: int = 0

    @property
    def complete(self) -> bool:
        """Every coded field was taken: a decode gives back the very values encoded."""
        return self.taken > 0 and self.coded == 0


_REUSE: ContextVar[Reuse | None] = ContextVar("codec_reuse", default=None)
_QUIET: ContextVar[bool] = ContextVar("codec_reuse_quiet", default=False)


@contextmanager
def reusing() -> Iterator[Reuse]:
    """Encodes in this block (this thread or task) take a coded field's decoded map for
    the very value, unchanged (the module docstring)."""
    reuse = Reuse()
    token = _REUSE.set(reuse)
    try:
        yield reuse
    finally:
        _REUSE.reset(token)


@contextmanager
def unremembered() -> Iterator[None]:
    """Decodes in this block (this thread or task) keep nothing: their values are coded
    already where they will be kept (the store's own read-back of what it wrote)."""
    token = _QUIET.set(True)
    try:
        yield
    finally:
        _QUIET.reset(token)


def _state(value: Any) -> tuple | None:
    """What must be the same for ``value`` to be unchanged; None: it cannot be told."""
    if isinstance(value, Tensor):  # an inference tensor counts no versions: not told
        return None if value.is_inference() else (id(value), value._version)
    if isinstance(value, np.ndarray):
        return None if value.flags.writeable else (id(value),)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = [getattr(value, f.name) for f in dataclasses.fields(value)]
        arrays = [f for f in fields if isinstance(f, (Tensor, np.ndarray))]
        parts = tuple(_state(a) for a in arrays)
        return parts if arrays and None not in parts else None
    return None


def remember(value: Any, coding: str, wire: dict[str, Any]) -> None:
    """Keep ``wire``, the coded map ``value`` was just decoded from (where its state can
    be told and it can be referred to weakly; not inside :func:`unremembered`)."""
    if _QUIET.get():
        return
    state = _state(value)
    if state is None:
        return
    key = id(value)

    def forget(_: weakref.ref) -> None:
        with _LOCK:
            if key in _DECODED and _DECODED[key][0]() is None:
                del _DECODED[key]

    try:
        ref = weakref.ref(value, forget)
    except TypeError:  # not weakly referable (a slotted class): never taken
        return
    with _LOCK:
        _DECODED[key] = (ref, coding, wire, state)


def _matching(coding: str, value: Any) -> tuple | None:
    """(Under ``_LOCK``) ``value``'s entry if it was decoded from ``coding`` and is unchanged
    since, else None."""
    entry = _DECODED.get(id(value))
    if (
        entry is not None
        and entry[0]() is value
        and entry[1] == coding
        and entry[3] == _state(value)
    ):
        return entry
    return None


def held(coding: str, value: Any) -> bool:
    """Whether ``value`` was decoded from ``coding`` in this process and is unchanged since,
    its map not yet taken (:func:`recall`): a value as its sender coded it."""
    with _LOCK:
        return _matching(coding, value) is not None


def recall(coding: str, value: Any) -> dict[str, Any] | None:
    """Inside :func:`reusing`: the map ``value`` was decoded from in ``coding``, if it is
    unchanged since (counted as taken, and forgotten: what takes it keeps it, so a
    coordinator holds its keyframes' maps only from the ingest to the store's write),
    else None (counted as coded afresh by the caller). Outside: None, counting nothing."""
    reuse = _REUSE.get()
    if reuse is None:
        return None
    with _LOCK:
        entry = _matching(coding, value)
        if entry is not None:
            del _DECODED[id(value)]
    if entry is not None:
        reuse.taken += 1
        return entry[2]
    reuse.coded += 1
    return None
