"""Named arrays in one file, compressed losslessly: the ``.c3z`` files of an agent folder's
depth and surface maps (``como3r synth``) and of a run's keyframe data (manual:
docs/inputs.md, docs/outputs.md).

A float32 array comes back bit for bit, yet takes a fraction of its raw bytes where it is
smooth: each ``(H, W)`` plane (every channel of an ``(H, W, C)`` array) is stored as the
residuals of a prediction of its float32 bit patterns, the second difference along each row
(the row's first two values predicted from zeros) then the first difference down the
columns, all modulo 2**32 and zigzag-mapped so that small residuals of either sign are small
integers; their four byte planes (every value's lowest byte, then every second byte, ...)
go through Zstandard. On the 640x480 demo scene a depth map takes 0.11-0.15 MB of its 1.23 MB
and a surface map 0.32-0.45 MB of its 3.69 MB (``.npy``); a keyframe's noisy pointmap still
halves. Other dtypes are stored as their byte planes through Zstandard.

Layout (version 1), little-endian::

    b"como3rz1"                 8 bytes, the format and its version
    n                           uint32, bytes of the header
    header                      n bytes of JSON: {"arrays": [{"name", "dtype", "shape",
                                "coding": "float-rows" | "bytes", "sizes": [...]}, ...]}
    payload                     per array, per plane (one for "bytes"), one Zstandard frame
                                of the sizes listed
"""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

try:  # the standard library's from Python 3.14
    from compression import zstd
except ImportError:  # pragma: no cover - depends on the Python version
    from backports import zstd

from como3r.errors import InputError

SUFFIX = ".c3z"
MAGIC = b"como3rz1"
#: Zstandard level: 9 saves 3-5 % more on these maps and takes 5-10x the time
ZSTD_LEVEL = 3
#: a header longer than this is not one of ours (a few hundred bytes in practice)
MAX_HEADER = 1 << 16
#: the dtypes a file may hold
DTYPES = ("float32", "float64", "uint8", "uint16", "int16", "int32", "int64", "bool")


def _planes(values: np.ndarray) -> bytes:
    """The byte planes of ``values``' little-endian bytes (first bytes, then second, ...)."""
    flat = np.ascontiguousarray(values).reshape(-1)
    ints = flat.view(f"<u{flat.dtype.itemsize}")
    # shifts, not a transposed byte view: 4x faster on a 640x480 plane
    return b"".join((ints >> (8 * k)).astype(np.uint8).tobytes() for k in range(ints.itemsize))


def _unplanes(data: bytes, dtype: np.dtype, count: int) -> np.ndarray:
    """``count`` values of ``dtype`` from their byte planes."""
    raw = np.frombuffer(data, dtype=np.uint8).reshape(dtype.itemsize, count)
    ints = raw[0].astype(f"<u{dtype.itemsize}")
    for k in range(1, dtype.itemsize):
        ints |= raw[k].astype(ints.dtype) << (8 * k)
    return ints.view(dtype)


def predict_rows(plane: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 -> ``(H, W)`` uint32 zigzag residuals (module docstring)."""
    bits = np.ascontiguousarray(plane, dtype="<f4").view("<u4")
    along = np.diff(bits, n=2, axis=1, prepend=np.zeros((bits.shape[0], 2), dtype="<u4"))
    down = np.diff(along, axis=0, prepend=np.zeros((1, bits.shape[1]), dtype="<u4"))
    signed = down.view("<i4")
    return ((signed << 1) ^ (signed >> 31)).view("<u4")


def unpredict_rows(zigzag: np.ndarray) -> np.ndarray:
    """The ``(H, W)`` float32 plane :func:`predict_rows` made ``zigzag`` of, bit for bit."""
    z = zigzag.astype("<u4", copy=False)
    residual = (z >> 1) ^ (-(z & 1).view("<i4")).view("<u4")
    # every sum wraps modulo 2**32; the sums down the columns run along the rows of the
    # transpose, 2.5x faster than numpy's accumulation over the first axis
    down = np.ascontiguousarray(residual.T)
    np.cumsum(down, axis=1, dtype="<u4", out=down)
    along = np.ascontiguousarray(down.T)
    first = np.cumsum(along, axis=1, dtype="<u4")
    return np.cumsum(first, axis=1, dtype="<u4").view("<f4")


def _float_planes(array: np.ndarray) -> list[np.ndarray]:
    if array.ndim == 2:
        return [array]
    return [array[..., c] for c in range(array.shape[2])]


def write_packed(path: str | Path, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` (name -> array of a dtype in :data:`DTYPES`) to ``path``; float32
    arrays of 2 or 3 dimensions with a non-empty plane are predicted (module docstring)."""
    entries: list[dict[str, Any]] = []
    frames: list[bytes] = []
    for name, value in arrays.items():
        array = np.asarray(value)
        if array.dtype.name not in DTYPES:
            raise ValueError(f"write_packed: {name} has dtype {array.dtype}, not one of {DTYPES}")
        array = array.astype(array.dtype.newbyteorder("<"), copy=False)
        predicted = array.dtype == np.float32 and array.ndim in (2, 3) and array.size > 0
        if predicted:
            parts = [_planes(predict_rows(p)) for p in _float_planes(array)]
        else:
            parts = [_planes(array)]
        compressed = [zstd.compress(part, ZSTD_LEVEL) for part in parts]
        frames.extend(compressed)
        entries.append(
            {
                "name": name,
                "dtype": array.dtype.name,
                "shape": list(array.shape),
                "coding": "float-rows" if predicted else "bytes",
                "sizes": [len(c) for c in compressed],
            }
        )
    header = json.dumps({"arrays": entries}, separators=(",", ":")).encode()
    with open(path, "wb") as f:
        f.write(MAGIC + struct.pack("<I", len(header)) + header)
        for frame in frames:
            f.write(frame)


def read_packed_header(path: str | Path) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Name -> (dtype, shape) of each array in ``path``, from its header alone.

    Raises:
        InputError: not such a file, or a malformed header.
    """
    entries, _ = _header(Path(path))
    return {e["name"]: (np.dtype(e["dtype"]), tuple(e["shape"])) for e in entries}


def read_packed(path: str | Path) -> dict[str, np.ndarray]:
    """Every array :func:`write_packed` wrote to ``path``, as it was given.

    Raises:
        InputError: not such a file, truncated or corrupted (naming it).
    """
    path = Path(path)
    entries, offset = _header(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    arrays: dict[str, np.ndarray] = {}
    for entry in entries:
        dtype, shape = np.dtype(entry["dtype"]).newbyteorder("<"), tuple(entry["shape"])
        if entry["coding"] == "float-rows":
            plane_shape = shape[:2]
            expected = [4 * int(np.prod(plane_shape))] * (1 if len(shape) == 2 else shape[2])
        else:
            expected = [dtype.itemsize * int(np.prod(shape))]
        if len(entry["sizes"]) != len(expected):
            raise InputError(f"{path}: {entry['name']} lists {len(entry['sizes'])} parts")
        parts = []
        for size, raw_bytes in zip(entry["sizes"], expected):
            part = _decompress(path, data[offset : offset + size], raw_bytes, entry["name"])
            offset += size
            parts.append(part)
        if entry["coding"] == "float-rows":
            planes = [
                unpredict_rows(_unplanes(p, np.dtype("<u4"), raw // 4).reshape(plane_shape))
                for p, raw in zip(parts, expected)
            ]
            array = planes[0] if len(shape) == 2 else np.stack(planes, axis=-1)
        else:
            array = _unplanes(parts[0], dtype, int(np.prod(shape))).reshape(shape)
        arrays[entry["name"]] = array.astype(dtype.newbyteorder("="), copy=False)
    if offset != len(data):
        raise InputError(f"{path}: {len(data) - offset} bytes after its arrays")
    return arrays


def _decompress(path: Path, frame: bytes, expected: int, name: str) -> bytes:
    try:
        raw = zstd.ZstdDecompressor().decompress(frame, max_length=expected + 1)
    except zstd.ZstdError as exc:
        raise InputError(f"{path}: {name} is corrupted ({exc})") from None
    if len(raw) != expected:
        raise InputError(
            f"{path}: {name} is truncated or corrupted ({len(raw)} of {expected} bytes)"
        )
    return raw


def _header(path: Path) -> tuple[list[dict[str, Any]], int]:
    """The header's array entries, checked, and the payload's byte offset."""
    try:
        with open(path, "rb") as f:
            start = f.read(len(MAGIC) + 4)
            if len(start) < len(MAGIC) + 4 or not start.startswith(MAGIC):
                raise InputError(f"{path}: not a como3r packed-array file ({SUFFIX})")
            (length,) = struct.unpack("<I", start[len(MAGIC) :])
            if length > MAX_HEADER:
                raise InputError(f"{path}: header of {length} bytes is not one of a {SUFFIX}")
            text = f.read(length)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    try:
        entries = json.loads(text)["arrays"]
        for e in entries:
            ok = (
                isinstance(e["name"], str)
                and e["dtype"] in DTYPES
                and all(isinstance(n, int) and n >= 0 for n in e["shape"])
                and e["coding"] in ("float-rows", "bytes")
                and (
                    e["coding"] == "bytes"
                    or (e["dtype"] == "float32" and len(e["shape"]) in (2, 3))
                )
                and all(isinstance(n, int) and n >= 0 for n in e["sizes"])
            )
            if not ok:
                raise ValueError(f"bad entry {e}")
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: malformed {SUFFIX} header ({exc})") from None
    return entries, len(MAGIC) + 4 + length
