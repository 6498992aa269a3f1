"""Typed, versioned, pickle-free encoding of messages (manual:
docs/architecture.md, "Processes and messages").

Processes share nothing but messages; a message is a registered dataclass encoded by
:func:`encode` into one msgpack document and rebuilt by :func:`decode`, which only ever
instantiates classes of :data:`REGISTRY` and validates everything it reads.

Wire format (msgpack, every map carries a ``"#"`` tag):

* ``None``, ``bool``, ``int``, ``float``, ``str``, ``bytes`` and lists: msgpack natives;
* tuple: ``{"#": "tuple", "items": [...]}``;
* dict (``str`` or ``int`` keys): ``{"#": "dict", "items": [[key, value], ...]}``;
* ``np.ndarray`` / ``torch.Tensor``: ``{"#": "ndarray" | "tensor", "dtype": name,
  "shape": [...], "data": raw little-endian bytes}`` (:mod:`.codec_arrays`); an array of
  4 KiB or more has ``"zstd"`` instead of ``"data"``: its bytes split into byte planes and
  compressed with Zstandard. Lossless; measured on 512x384 payloads (``benchmarks/
  message_sizes.py``) it takes MASt3R's float32 encoder tokens to 0.79 of their size and
  the simulated prior's encodings to 0.66, at about 1 GB/s each way, where zlib at level 1
  reaches 0.80 at 0.06 GB/s;
* registered dataclass: ``{"#": "object", "type": name, "version": v, "fields": {...}}``.

Decoding rejects with :class:`MessageError`: input over the size cap, anything that is not
well-formed msgpack (pickle bytes, garbage, truncation), untagged or unknown maps, types not
in the registry, a version other than the registered one, a field set other than the
dataclass's, field values that do not match the dataclass's annotations, dtypes outside the
allow-list, shapes that disagree with the byte count, compressed arrays that do not
decompress to exactly their shape's bytes or that would take the message past
:data:`MAX_EXPANSION` times its size cap (a decompression bomb), and whatever the per-type
checks of
:func:`add_check` reject (shapes and ranges the receiver relies on, see
:mod:`como3r.transport.messages`).
"""

from __future__ import annotations

import dataclasses
import threading
import weakref
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
from torch import Tensor

from como3r.errors import Como3rError, MessageError
from como3r.transport.codec_arrays import (
    MAX_EXPANSION,
    TAG,
    Budget,
    array_from_wire,
    array_to_wire,
    as_half,
    exact_keys,
    ndarray_bytes,
    tensor_bytes,
    widen,
)
from como3r.transport.codec_compact import coded_from_wire, coded_to_wire
from como3r.transport.codec_planes import CODED
from como3r.transport.codec_registry import (
    BY_PATH,
    CHECKS,
    REGISTRY,
    RESOLVED,
    init_fields,
    register,
    resolve,
    type_hints,
)
from como3r.transport.codec_types import conforms, hint_name

DEFAULT_MAX_BYTES = 256 * 2**20
"""Default cap on the size of one encoded message (256 MiB)."""

MAX_DEPTH = 32
"""Deepest nesting of containers and dataclasses a message may have."""


# ----------------------------------------------------------------------------- encoding


def encode(
    message: Any,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    lossy: bool = False,
    exact: frozenset[str] = frozenset(),
) -> bytes:
    """Encode a registered dataclass instance.

    Args:
        message: the message.
        max_bytes: size cap of the encoding.
        lossy: send the half-precision fields (:func:`register`) in float16 and the coded
            ones in their compact codings, as the transports across machines do; otherwise
            the encoding is bit-exact.
        exact: with ``lossy``, fields (``"WireName.field"``, e.g.
            ``"KeyframePacket.encoding"``) whose whole value is encoded bit-exact all the
            same (an agent process on pipes: its keyframes coded as across machines, their
            encodings exact, as the single-process ingest hands them over).

    Raises:
        MessageError: unregistered type, unsupported value, or the encoding exceeds
            ``max_bytes``.
    """
    if not dataclasses.is_dataclass(message) or isinstance(message, type):
        raise MessageError(
            f"only registered dataclasses are messages, got {type(message).__name__}"
        )
    tree = _to_wire(message, type(message).__name__, 0, lossy, exact)
    recorder = _recorder(message)
    try:
        data = msgpack.packb(tree, use_bin_type=True)
    except (ValueError, TypeError, OverflowError) as exc:
        raise MessageError(f"cannot encode {type(message).__name__}: {exc}") from None
    if len(data) > max_bytes:
        raise MessageError(
            f"{type(message).__name__} encodes to {len(data)} bytes, "
            f"over the cap of {max_bytes} bytes"
        )
    if recorder is not None:  # only a message that leaves is counted
        sizes: dict[str, int] = {}
        _tree_parts(tree, "", sizes)
        recorder(sizes)
    return data


def _to_wire(
    value: Any, path: str, depth: int, lossy: bool, exact: frozenset[str] = frozenset()
) -> Any:
    if depth > MAX_DEPTH:
        raise MessageError(f"{path}: nested deeper than {MAX_DEPTH}")
    if value is None or isinstance(value, (bool, int, float, str, bytes)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Tensor):
        return array_to_wire("tensor", *tensor_bytes(value, path))
    if isinstance(value, np.ndarray):
        return array_to_wire("ndarray", *ndarray_bytes(value, path))
    if isinstance(value, list):
        return [_to_wire(v, f"{path}[{i}]", depth + 1, lossy, exact) for i, v in enumerate(value)]
    if isinstance(value, tuple):
        return {
            TAG: "tuple",
            "items": [
                _to_wire(v, f"{path}[{i}]", depth + 1, lossy, exact) for i, v in enumerate(value)
            ],
        }
    if isinstance(value, dict):
        items = [
            [_dict_key(k, path), _to_wire(v, f"{path}[{k!r}]", depth + 1, lossy, exact)]
            for k, v in value.items()
        ]
        return {TAG: "dict", "items": items}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _object_to_wire(value, path, depth, lossy, exact)
    raise MessageError(f"{path}: cannot encode a {type(value).__name__}")


def part_sizes(message: Any, *, lossy: bool = False) -> dict[str, int]:
    """Bytes of each field of ``message`` on the wire, as :func:`encode` writes them.

    A field holding a registered dataclass (not in a compact coding) is broken down into
    its own fields; every other field is one part, keyed by its dotted path
    (``"packet.encoding.tokens"``), its size the msgpack encoding of its wire form
    (compressed arrays included). The parts add up to the encoding's length less the few
    bytes of tags, names and versions around them. A sender learns them from the encode
    itself (:func:`record_parts`); this encodes again.

    Args:
        message: a registered dataclass instance.
        lossy: as in :func:`encode`.

    Raises:
        MessageError: as :func:`encode`.
    """
    if not dataclasses.is_dataclass(message) or isinstance(message, type):
        raise MessageError(
            f"only registered dataclasses are messages, got {type(message).__name__}"
        )
    sizes: dict[str, int] = {}
    _tree_parts(_to_wire(message, type(message).__name__, 0, lossy), "", sizes)
    return sizes


def _tree_parts(tree: dict[str, Any], prefix: str, sizes: dict[str, int]) -> None:
    """The part sizes of an object's wire form (:func:`part_sizes`)."""
    for name, value in tree["fields"].items():
        if isinstance(value, dict) and value.get(TAG) == "object":
            _tree_parts(value, f"{prefix}{name}.", sizes)
        else:
            sizes[f"{prefix}{name}"] = len(msgpack.packb(value, use_bin_type=True))


#: id of a message -> (a weak reference to it, its recorder); by identity, as messages
#: holding arrays are neither hashable nor comparable
_RECORDERS: dict[int, tuple[weakref.ref, Callable[[dict[str, int]], None]]] = {}
_RECORDERS_LOCK = threading.Lock()


def record_parts(message: Any, recorder: Callable[[dict[str, int]], None]) -> None:
    """Have the next :func:`encode` of ``message`` (this very object, by whichever link
    sends it) call ``recorder`` with its :func:`part_sizes`, taken from that encoding: the
    sender learns what each part weighs without encoding twice, and the receiver need not
    measure (it re-encoded every keyframe for it)."""
    key = id(message)

    def forget(_: weakref.ref) -> None:  # the message is gone without being encoded
        with _RECORDERS_LOCK:
            if key in _RECORDERS and _RECORDERS[key][0]() is None:
                del _RECORDERS[key]

    with _RECORDERS_LOCK:
        _RECORDERS[key] = (weakref.ref(message, forget), recorder)


def _recorder(message: Any) -> Callable[[dict[str, int]], None] | None:
    """The recorder :func:`record_parts` left for ``message`` (once), or None."""
    with _RECORDERS_LOCK:
        entry = _RECORDERS.get(id(message))
        if entry is None or entry[0]() is not message:
            return None
        del _RECORDERS[id(message)]
        return entry[1]


def _coded(coding: str | None, value: Any, owner: Any, lossy: bool) -> dict[str, Any] | None:
    """``value`` (a field of ``owner``) in its compact coding on the lossy wire, or None
    (no coding, an exact encode, or a value the coding does not fit)."""
    if coding is None or not lossy or value is None:
        return None
    return coded_to_wire(coding, value, owner)


def _dict_key(key: Any, path: str) -> str | int:
    if isinstance(key, bool) or not isinstance(key, (str, int)):
        raise MessageError(f"{path}: dict keys must be str or int, got {type(key).__name__}")
    return key


def _object_to_wire(
    value: Any, path: str, depth: int, lossy: bool, exact: frozenset[str]
) -> dict[str, Any]:
    cls = type(value)
    entry = BY_PATH.get(f"{cls.__module__}:{cls.__qualname__}")
    if entry is None:
        raise MessageError(f"{path}: type {cls.__qualname__} is not a registered message type")
    RESOLVED.setdefault(entry.name, cls)
    fields = {}
    for f in init_fields(cls):
        field_value = getattr(value, f.name)
        lossy_here = lossy and f"{entry.name}.{f.name}" not in exact
        coded = _coded(entry.coding(f.name), field_value, value, lossy_here)
        fields[f.name] = (
            coded
            if coded is not None
            else _field_to_wire(
                field_value,
                lossy_here and f.name in entry.half,
                f"{path}.{f.name}",
                depth + 1,
                lossy_here,
                exact,
            )
        )
    return {TAG: "object", "type": entry.name, "version": entry.version, "fields": fields}


def _field_to_wire(
    value: Any, half: bool, path: str, depth: int, lossy: bool, exact: frozenset[str]
) -> Any:
    """A field's wire form; a float32 array of a ``half`` field (or in a tuple that is the
    field) as float16 where it fits."""
    if half and isinstance(value, tuple):
        return {
            TAG: "tuple",
            "items": [
                _field_to_wire(v, True, f"{path}[{i}]", depth + 1, lossy, exact)
                for i, v in enumerate(value)
            ],
        }
    narrow = as_half(value) if half else None
    if narrow is None:
        return _to_wire(value, path, depth, lossy, exact)
    return {**_to_wire(narrow, path, depth, lossy, exact), "as": "float32"}


def as_received(value: Any) -> Any:
    """``value`` as :func:`decode` gives it back after a ``lossy`` :func:`encode`: a copy
    whose half-precision fields (:func:`register`) hold their float16-rounded values and
    whose coded fields (:mod:`.codec_compact`) their decoded codings."""
    if isinstance(value, (list, tuple)):
        return type(value)(as_received(v) for v in value)
    if isinstance(value, dict):
        return {k: as_received(v) for k, v in value.items()}
    if not dataclasses.is_dataclass(value) or isinstance(value, type):
        return value
    entry = BY_PATH.get(f"{type(value).__module__}:{type(value).__qualname__}")
    half = entry.half if entry is not None else frozenset()
    changes = {}
    for f in init_fields(type(value)):
        field_value = getattr(value, f.name)
        coded = _coded(entry.coding(f.name) if entry else None, field_value, value, True)
        if coded is not None:
            changes[f.name] = coded_from_wire(coded, f.name, Budget(2**62))
            continue
        changes[f.name] = (
            _half_received(field_value) if f.name in half else as_received(field_value)
        )
    return dataclasses.replace(value, **changes)


def _half_received(value: Any) -> Any:
    """A ``half`` field's value as :func:`decode` gives it back after a ``lossy`` encode."""
    if isinstance(value, tuple):
        return tuple(_half_received(v) for v in value)
    narrow = as_half(value)
    return as_received(value) if narrow is None else widen(narrow)


# ----------------------------------------------------------------------------- decoding


def decode(
    data: bytes,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
    expected: type | tuple[type, ...] | None = None,
) -> Any:
    """Decode and validate one message.

    Args:
        data: the encoded message.
        max_bytes: size cap; longer input is rejected before it is parsed.
        expected: the message class(es) acceptable here; None accepts any registered one.

    Raises:
        MessageError: naming what is wrong and where (``Type.field[index]...``).
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(f"a message is bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise MessageError(f"message of {len(data)} bytes exceeds the cap of {max_bytes} bytes")
    try:
        tree = msgpack.unpackb(data, raw=False, use_list=True, strict_map_key=True)
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise MessageError(f"not a valid message (malformed msgpack: {exc})") from None
    if not (isinstance(tree, dict) and tree.get(TAG) == "object"):
        raise MessageError("not a valid message (the top level is not a typed object)")
    message = _from_wire(tree, "message", 0, Budget(MAX_EXPANSION * max_bytes))
    if expected is not None and not isinstance(message, expected):
        names = [c.__name__ for c in (expected if isinstance(expected, tuple) else (expected,))]
        raise MessageError(f"expected a {' or '.join(names)} message, got {type(message).__name__}")
    return message


def _from_wire(value: Any, path: str, depth: int, budget: Budget) -> Any:
    if depth > MAX_DEPTH:
        raise MessageError(f"{path}: nested deeper than {MAX_DEPTH}")
    if value is None or isinstance(value, (bool, int, float, str, bytes)):
        return value
    if isinstance(value, list):
        return [_from_wire(v, f"{path}[{i}]", depth + 1, budget) for i, v in enumerate(value)]
    if not isinstance(value, dict):
        raise MessageError(f"{path}: unexpected wire value of type {type(value).__name__}")
    tag = value.get(TAG)
    if tag in ("ndarray", "tensor"):
        return array_from_wire(value, tag, path, budget)
    if tag == "tuple":
        items = exact_keys(value, ("items",), path)["items"]
        return tuple(
            _from_wire(v, f"{path}[{i}]", depth + 1, budget)
            for i, v in enumerate(_list(items, path))
        )
    if tag == "dict":
        items = _list(exact_keys(value, ("items",), path)["items"], path)
        return _dict_from_wire(items, path, depth, budget)
    if tag == "object":
        return _object_from_wire(value, path, depth, budget)
    if tag == CODED:
        return coded_from_wire(value, path, budget)
    raise MessageError(f"{path}: unknown wire tag {tag!r}")


def _list(value: Any, path: str) -> list:
    if not isinstance(value, list):
        raise MessageError(f"{path}: expected a list on the wire, got {type(value).__name__}")
    return value


def _dict_from_wire(items: list, path: str, depth: int, budget: Budget) -> dict:
    out: dict[Any, Any] = {}
    for item in items:
        if not (isinstance(item, list) and len(item) == 2):
            raise MessageError(f"{path}: a dict item is not a [key, value] pair")
        key = item[0]
        if isinstance(key, bool) or not isinstance(key, (str, int)) or key in out:
            raise MessageError(f"{path}: invalid or repeated dict key {key!r}")
        out[key] = _from_wire(item[1], f"{path}[{key!r}]", depth + 1, budget)
    return out


def _object_from_wire(value: dict, path: str, depth: int, budget: Budget) -> Any:
    exact_keys(value, ("type", "version", "fields"), path)
    name, version, fields = value["type"], value["version"], value["fields"]
    if not isinstance(name, str) or name not in REGISTRY:
        raise MessageError(f"{path}: unknown message type {name!r}")
    entry = REGISTRY[name]
    if isinstance(version, bool) or version != entry.version:
        raise MessageError(
            f"{path}: {name} version {version!r} is not the supported version {entry.version}"
        )
    cls = resolve(entry)
    path = name if path == "message" else path
    if not isinstance(fields, dict):
        raise MessageError(f"{path}: fields of {name} are not a map")
    expected_names = [f.name for f in init_fields(cls)]
    if set(fields) != set(expected_names):
        missing = sorted(set(expected_names) - set(fields))
        extra = sorted(map(str, set(fields) - set(expected_names)))
        raise MessageError(
            f"{path}: wrong fields for {name} (missing {missing}, unexpected {extra})"
        )
    hints = type_hints(cls)
    kwargs = {}
    for field_name in expected_names:
        field_path = f"{path}.{field_name}"
        decoded = _from_wire(fields[field_name], field_path, depth + 1, budget)
        if not conforms(decoded, hints[field_name]):
            raise MessageError(
                f"{field_path}: a {type(decoded).__name__} does not match the "
                f"declared type {hint_name(hints[field_name])}"
            )
        kwargs[field_name] = decoded
    if "version" in kwargs and kwargs["version"] != entry.version:
        raise MessageError(f"{path}.version: {kwargs['version']!r} is not {entry.version}")
    try:
        obj = cls(**kwargs)
        if name in CHECKS:
            CHECKS[name](obj)
    except (TypeError, ValueError, Como3rError) as exc:
        raise MessageError(f"{path}: invalid {name}: {exc}") from None
    return obj


#: Keyframe pointmaps and confidences travel in half precision across machines (``lossy``
#: encodes): on the demo scene (2 agents x 30 frames, 512x384, lockstep so that nothing
#: else differs) the merged ATE was 16.30 mm with them in float32 and 16.51 mm in float16,
#: on its seed-1 twin 13.667 and 13.661 mm (no systematic direction, within 1.3 %), for
#: 16 % fewer bytes per keyframe with the simulated prior.
_POINTMAP = ("X_hat", "C_hat")

#: MASt3R's encoder tokens travel in half precision across machines too (the receiver
#: decodes pairs from them). With the full-size network of seeded random weights at 512x384
#: (``benchmarks/token_precision.py``) the pair decoded from float16 tokens differs from the
#: float32 tokens' by 7e-6 (median) and 1.7e-5 (99th percentile) relative in the pointmaps,
#: 1.6e-6 / 8.8e-5 in the confidences: 30 times less than the float16 rounding the
#: pointmaps themselves travel with (4.9e-4). The released weights' sensitivity and the
#: merged ATE with MASt3R are not measured (no released weights where this was measured).
_TOKENS = ("tokens",)

#: A keyframe's retrieval features (descriptors and attention) travel in half precision
#: too: the coordinator's binary ASMK aggregates and binarises their residuals. On 17
#: keyframes of 2 agents (synthetic, simulated prior, 300 x 128 descriptors) every query's
#: hits and similarities were identical with float16 and float32 features, with the agents'
#: visual words and with the coordinator quantising itself; MASt3R's 300 x 1024 features
#: weigh 979 -> about 490 kB per keyframe (their released values are not measured).
_RETRIEVAL = ("retrieval",)


#: The keyframe's large parts in compact codings on the lossy wire (:mod:`.codec_compact`):
#: each at the precision its receiver reads.
_CODED = {
    "como3r.frontend.packets:KeyframePacket": {
        "X_hat": "pointmap",
        "C_hat": "confidence",
        "colors": "image",
        "retrieval": "retrieval",
        "sequential_ij": "matches",
        "sequential_ji": "matches",
    },
    "como3r.frontend.packets:PointmapRefresh": {"X_hat": "pointmap", "C_hat": "confidence"},
    "como3r.prior.retrieval:Aggregated": {"query_words": "ascending", "build_words": "ascending"},
}


def _register_payloads() -> None:
    """The payloads that cross the agent/coordinator boundary (C-Sec. B.1); pointmaps,
    their confidences, match confidences (:data:`_POINTMAP`), MASt3R's encoder tokens
    (:data:`_TOKENS`) and retrieval features (:data:`_RETRIEVAL`) in half precision."""
    for path, version, half in (
        # 2: retrieval_words; 3: compact codings, encoding None (the receiver encodes the
        # colours again); 4: pointmap rays against a fitted pinhole; 5: retrieval as an
        # Aggregated keyframe
        ("como3r.frontend.packets:KeyframePacket", 5, (*_POINTMAP, *_RETRIEVAL)),
        ("como3r.prior.retrieval:Aggregated", 1, ()),
        # 2: K; 3: codings; 4: pointmap rays against a fitted pinhole
        ("como3r.frontend.packets:PointmapRefresh", 4, _POINTMAP),
        ("como3r.frontend.packets:PoseUpdate", 2, ()),  # 2: focal
        ("como3r.frontend.pairs:DirectedMatches", 1, ("q",)),
        # 2: first_frame_focal, 3: rejected_directions
        ("como3r.frontend.agent:FrontendStats", 3, ()),
        # 2: filled, 3: texture, colours, 4: record
        ("como3r.prior.simulated_encoding:SimulatedEncoding", 4, ()),
        ("como3r.prior.simulated_record:SimulatedTruthRecord", 1, ()),
        ("como3r.prior.mast3r.prior:MASt3REncoding", 1, _TOKENS),
    ):
        register(path, version=version, half=half, coded=_CODED.get(path))


_register_payloads()
