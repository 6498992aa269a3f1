"""What a coordinator holds in tensors and arrays, by owner (issue 41: memory at 16 agents).

``tracemalloc`` does not see torch's allocations, and a process's resident memory mixes
what is held with what glibc keeps freed (:mod:`como3r.heap`). :func:`census` walks the
objects reachable from a coordinator (its graph's keyframes and links, candidates,
encoding cache, verification pool, deferral queue, retrieval database, ...) and sums the
bytes of every tensor's storage and numpy array's buffer it meets, each storage counted
once (the first owner that reaches it keeps it), by *owner*: the attribute path that
reaches it with list indices and dictionary keys left out, e.g.
``graph.keyframes.X_hat``. It reads attributes from ``__dict__`` and slots, never through
properties or descriptors, so a paged-out keyframe's arrays are not read back by counting
them. The prior (its own data, not the map's), the journal (the session store) and
threads, locks and modules are not walked.
"""

from __future__ import annotations

import dataclasses
import threading
import types
from collections import Counter, deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

#: attributes of the coordinator not walked (not the map's memory, or not Python data)
SKIPPED = frozenset({"prior", "journal", "config"})
#: owner paths are cut to this many attribute names
DEPTH = 4


def census(coordinator: Any) -> Counter[str]:
    """Bytes of tensor storages and numpy buffers reachable from ``coordinator``, by owner
    (the module docstring); each storage counted once.

    Returns:
        owner -> bytes; the owners holding none are left out.
    """
    held: Counter[str] = Counter()
    seen_objects: set[int] = {id(coordinator)}
    seen_storages: set[int] = set()
    stack: list[tuple[Any, tuple[str, ...]]] = [
        (value, (name,)) for name, value in _attributes(coordinator) if name not in SKIPPED
    ]
    while stack:
        obj, path = stack.pop()
        if id(obj) in seen_objects or _opaque(obj):
            continue
        seen_objects.add(id(obj))
        owner = ".".join(path[:DEPTH])
        if isinstance(obj, torch.Tensor):
            storage = obj.untyped_storage()
            if storage.data_ptr() not in seen_storages and storage.nbytes() > 0:
                seen_storages.add(storage.data_ptr())
                held[owner] += storage.nbytes()
            continue
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            key = base.__array_interface__["data"][0]
            if key not in seen_storages and base.nbytes > 0:
                seen_storages.add(key)
                held[owner] += base.nbytes
            continue
        for name, value in _children(obj):
            name = name or _label(value)
            stack.append((value, path + (name,) if name else path))
    return held


def _opaque(obj: Any) -> bool:
    """Objects the walk does not enter: scalars, strings, callables, modules, threads."""
    return obj is None or isinstance(
        obj,
        (
            str,
            bytes,
            bytearray,
            int,
            float,
            complex,
            bool,
            type,
            types.ModuleType,
            types.FunctionType,
            types.BuiltinFunctionType,
            types.MethodType,
            threading.Thread,
            torch.dtype,
            torch.device,
        ),
    )


def _children(obj: Any) -> Iterator[tuple[str, Any]]:
    """``(name, value)`` of what ``obj`` holds; name "" for elements of containers."""
    if isinstance(obj, dict):
        for key, value in obj.items():
            yield "", key
            yield _key_name(key), value
    elif isinstance(obj, (list, tuple, set, frozenset)) or _is_deque(obj):
        for value in obj:
            yield "", value
    else:
        yield from _attributes(obj)


def _label(value: Any) -> str:
    """An element's path part: a graph link's kind or a candidate's status (what tells its
    memory apart), else nothing."""
    for name in ("kind", "status"):
        label = getattr(value, name, None) if not isinstance(value, dict) else None
        if isinstance(label, str) and label.isidentifier():
            return label
    return ""


def _key_name(key: Any) -> str:
    """A dictionary key as a path part: names kept (a keyframe's resident fields by name),
    numbers left out (indices)."""
    return key if isinstance(key, str) and key.isidentifier() else ""


def _is_deque(obj: Any) -> bool:
    return isinstance(obj, deque)


def _attributes(obj: Any) -> Iterator[tuple[str, Any]]:
    """An object's instance attributes, from ``__dict__`` and slots (no descriptors run)."""
    values = getattr(obj, "__dict__", None)
    if isinstance(values, dict):
        yield from values.items()
    for cls in type(obj).__mro__:
        slots = getattr(cls, "__slots__", ())
        for name in (slots,) if isinstance(slots, str) else slots:
            try:
                yield name, object.__getattribute__(obj, name)
            except AttributeError:
                continue
    if dataclasses.is_dataclass(obj) and not isinstance(values, dict):
        for field in dataclasses.fields(obj):
            yield field.name, getattr(obj, field.name, None)


def megabytes(held: Counter[str]) -> dict[str, float]:
    """``held`` in MB (1e6 bytes), largest first."""
    return {owner: n / 1e6 for owner, n in held.most_common()}
