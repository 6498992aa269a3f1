"""The registry of message types: which dataclasses may cross a process or network boundary,
under which wire name and schema version, which of their fields travel in half precision,
and the per-type checks run on every decoded one (manual: docs/architecture.md, "Processes
and messages").

:mod:`como3r.transport.codec` encodes and decodes against it; a module that defines
messages registers them here when it is imported (:func:`register`, :func:`add_check`).
Classes registered by path are imported on first use, so an optional dependency costs
nothing until a message of its type arrives.
"""

from __future__ import annotations

import dataclasses
import importlib
import threading
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from como3r.errors import MessageError


@dataclass(frozen=True)
class MessageType:
    """One entry of the registry.

    Attributes:
        name: the type's name on the wire.
        path: ``"module:QualName"`` of the dataclass (imported on first use).
        version: the schema version; decoding any other version is an error.
        half: float32 array fields that travel in half precision (:func:`register`).
        coded: ``(field, coding)`` pairs: fields that travel in a compact coding
            (:mod:`.codec_compact`) in a ``lossy`` encode.
    """

    name: str
    path: str
    version: int
    half: frozenset[str] = frozenset()
    coded: tuple[tuple[str, str], ...] = ()

    def coding(self, field: str) -> str | None:
        """The compact coding of ``field`` on the lossy wire, or None."""
        return dict(self.coded).get(field)


REGISTRY: dict[str, MessageType] = {}
"""Every type :func:`decode` may instantiate, by wire name."""

BY_PATH: dict[str, MessageType] = {}
RESOLVED: dict[str, type] = {}
_HINTS: dict[type, dict[str, Any]] = {}
_HINTS_LOCK = threading.Lock()
CHECKS: dict[str, Callable[[Any], None]] = {}


def register(
    target: type | str,
    *,
    version: int = 1,
    name: str | None = None,
    half: tuple[str, ...] = (),
    coded: dict[str, str] | None = None,
) -> None:
    """Allow a dataclass on the wire.

    Args:
        target: the dataclass, or its ``"module:QualName"`` path (imported lazily, so an
            optional dependency such as the MASt3R prior costs nothing until used).
        version: schema version; a class with a ``version`` field must default it to this.
        name: wire name (default: the class name).
        half: fields whose float32 arrays (also those in a tuple that is the field) travel
            as float16 in a ``lossy`` :func:`encode` and are decoded back to float32 (only
            where the loss was measured negligible);
            an array float16 cannot hold (a finite value beyond +-65504) travels in float32.
        coded: field -> name of a coding of :data:`~.codec_compact.CODINGS`: the field
            travels in it in a ``lossy`` encode (where the value fits it; else as ``half``
            says).

    Raises:
        ValueError: the name is taken by a different class or version.
        TypeError: the class is not a dataclass or its ``version`` default differs.
    """
    path = target if isinstance(target, str) else f"{target.__module__}:{target.__qualname__}"
    wire_name = name or path.rpartition(":")[2].rpartition(".")[2]
    entry = MessageType(
        wire_name, path, int(version), frozenset(half), tuple(sorted((coded or {}).items()))
    )
    known = REGISTRY.get(wire_name)
    if known is not None and known != entry:
        raise ValueError(
            f"message type name {wire_name!r} already registered as "
            f"{known.path} version {known.version}"
        )
    if not isinstance(target, str):
        _check_registrable(target, entry)
        RESOLVED[wire_name] = target
    REGISTRY[wire_name] = entry
    BY_PATH[path] = entry


def add_check(name: str, check: Callable[[Any], None]) -> None:
    """Run ``check(obj)`` on every decoded ``name`` (shape and range checks beyond types).

    ``check`` raises :class:`MessageError` (or ``ValueError``) naming what is wrong.
    """
    if name not in REGISTRY:
        raise ValueError(f"no registered message type {name!r}")
    CHECKS[name] = check


def resolve(entry: MessageType) -> type:
    """The class of a registry entry, importing its module on first use."""
    cls = RESOLVED.get(entry.name)
    if cls is None:
        module, _, qualname = entry.path.partition(":")
        try:
            obj: Any = importlib.import_module(module)
            for part in qualname.split("."):
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as exc:
            raise MessageError(
                f"message type {entry.name} ({entry.path}) is not available here: {exc}"
            ) from None
        cls = obj
        _check_registrable(cls, entry)
        RESOLVED[entry.name] = cls
    return cls


def _check_registrable(cls: type, entry: MessageType) -> None:
    """A registered class is a dataclass whose ``version`` default, if any, matches."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{entry.path} is not a dataclass")
    for f in dataclasses.fields(cls):
        if f.name == "version" and f.default != entry.version:
            raise TypeError(
                f"{entry.path}.version defaults to {f.default}, "
                f"registered as version {entry.version}"
            )


def resolve_all() -> None:
    """Import every registered type and resolve its field types now, e.g. before starting
    threads that will encode and decode concurrently."""
    for cls in registered_types().values():
        type_hints(cls)


def type_hints(cls: type) -> dict[str, Any]:
    with _HINTS_LOCK:
        # get_type_hints compiles string annotations; CPython 3.11's AST constructor is not
        # safe when robots (threads) decode their first messages at the same time
        if cls not in _HINTS:
            _HINTS[cls] = typing.get_type_hints(cls)
        return _HINTS[cls]


def init_fields(cls: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.init]


def registered_types() -> dict[str, type]:
    """Every registered type that can be imported here, by wire name."""
    out = {}
    for name, entry in REGISTRY.items():
        try:
            out[name] = resolve(entry)
        except MessageError:
            continue
    return out
