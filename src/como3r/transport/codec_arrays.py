"""Arrays on the wire (:mod:`como3r.transport.codec`): the dtype allow-list, byte planes and
Zstandard, half precision.

An ``np.ndarray`` or ``torch.Tensor`` travels as ``{"#": "ndarray" | "tensor", "dtype": name,
"shape": [...], "data": raw little-endian bytes}``, its dtype from :data:`ARRAY_DTYPES`
(tensors come back on the CPU, detached); an array of :data:`COMPRESS_MIN_BYTES` or more has
``"zstd"`` instead of ``"data"``: its bytes split into byte planes (every element's first
byte, then every second byte, ...) and compressed with Zstandard at level
:data:`ZSTD_LEVEL`. A float32 array of a half-precision field in a ``lossy`` encode travels
as float16 with ``"as": "float32"``. Decoding checks the dtype, the shape against the byte
count, and that compressed bytes decompress to exactly their shape's bytes within the
message's :class:`Budget`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:  # the standard library's from Python 3.14
    from compression import zstd
except ImportError:  # pragma: no cover - depends on the Python version
    from backports import zstd
import torch
from torch import Tensor

from como3r.errors import MessageError

TAG = "#"

MAX_NDIM = 8
"""Most dimensions an array may have."""

MAX_ELEMENTS = 2**40
"""Bound on the product of an array's non-zero dimensions (also for empty arrays, whose
other dimensions could otherwise be arbitrarily large)."""

COMPRESS_MIN_BYTES = 4096
"""Arrays of at least this many bytes travel compressed (byte planes + Zstandard)."""

ZSTD_LEVEL = 1
"""Zstandard level of compressed arrays (level 3 gains under 1 % on these payloads and
takes 1.3-1.5x the time)."""

MAX_EXPANSION = 8
"""A message's compressed arrays may decompress to at most this many times its size cap."""

ARRAY_DTYPES: dict[str, tuple[np.dtype | None, torch.dtype]] = {
    "bool": (np.dtype(np.bool_), torch.bool),
    "uint8": (np.dtype("<u1"), torch.uint8),
    "int8": (np.dtype("<i1"), torch.int8),
    "uint32": (np.dtype("<u4"), torch.uint32),  # packed bits (asmk's binary words)
    "int16": (np.dtype("<i2"), torch.int16),
    "int32": (np.dtype("<i4"), torch.int32),
    "int64": (np.dtype("<i8"), torch.int64),
    "float16": (np.dtype("<f2"), torch.float16),
    "float32": (np.dtype("<f4"), torch.float32),
    "float64": (np.dtype("<f8"), torch.float64),
    "bfloat16": (None, torch.bfloat16),  # tensors only: numpy has no bfloat16
}
"""Allow-list of array dtypes: wire name -> (little-endian numpy dtype, torch dtype)."""

_TORCH_NAMES = {torch_dtype: name for name, (_, torch_dtype) in ARRAY_DTYPES.items()}
_NUMPY_NAMES = {
    np_dtype.newbyteorder("="): name
    for name, (np_dtype, _) in ARRAY_DTYPES.items()
    if np_dtype is not None
}


class Budget:
    """The bytes the compressed arrays of one message may still decompress to."""

    def __init__(self, nbytes: int) -> None:
        self.left = nbytes

    def take(self, nbytes: int, path: str) -> None:
        if nbytes > self.left:
            raise MessageError(
                f"{path}: compressed arrays would decompress to more than "
                f"{MAX_EXPANSION} times the message size cap"
            )
        self.left -= nbytes


def exact_keys(value: dict, keys: tuple[str, ...], path: str) -> dict:
    if set(value) != {TAG, *keys}:
        raise MessageError(
            f"{path}: a {value.get(TAG)!r} has keys {sorted(map(str, value))}, "
            f"expected {sorted([TAG, *keys])}"
        )
    return value


def widen(narrow: Tensor | np.ndarray) -> Tensor | np.ndarray:
    return narrow.float() if isinstance(narrow, Tensor) else narrow.astype(np.float32)


def as_half(value: Any) -> Tensor | np.ndarray | None:
    """``value`` in float16 if it is a float32 array that float16 holds without overflow."""
    if isinstance(value, Tensor) and value.dtype == torch.float32:
        wide = value.detach().cpu()
        narrow = wide.half()
        return narrow if torch.equal(torch.isinf(narrow), torch.isinf(wide)) else None
    if isinstance(value, np.ndarray) and value.dtype == np.float32:
        narrow_array = value.astype(np.float16)
        return narrow_array if np.array_equal(np.isinf(narrow_array), np.isinf(value)) else None
    return None


def tensor_bytes(value: Tensor, path: str) -> tuple[str, list[int], bytes]:
    name = _TORCH_NAMES.get(value.dtype)
    if name is None:
        raise MessageError(f"{path}: tensor dtype {value.dtype} is not allowed on the wire")
    tensor = value.detach().cpu().contiguous()
    raw = tensor.view(torch.int16) if tensor.dtype == torch.bfloat16 else tensor
    return name, list(tensor.shape), raw.numpy().tobytes()


def ndarray_bytes(value: np.ndarray, path: str) -> tuple[str, list[int], bytes]:
    name = _NUMPY_NAMES.get(value.dtype.newbyteorder("="))
    if name is None:
        raise MessageError(f"{path}: array dtype {value.dtype} is not allowed on the wire")
    little = np.ascontiguousarray(value, dtype=ARRAY_DTYPES[name][0])
    return name, list(value.shape), little.tobytes()


def array_to_wire(kind: str, dtype: str, shape: list[int], data: bytes) -> dict[str, Any]:
    if len(data) < COMPRESS_MIN_BYTES:
        return {TAG: kind, "dtype": dtype, "shape": shape, "data": data}
    packed = zstd.compress(byte_planes(data, itemsize(dtype)), level=ZSTD_LEVEL)
    return {TAG: kind, "dtype": dtype, "shape": shape, "zstd": packed}


def itemsize(dtype: str) -> int:
    """Bytes per element of wire dtype ``dtype`` (a key of :data:`ARRAY_DTYPES`)."""
    return torch.empty(0, dtype=ARRAY_DTYPES[dtype][1]).element_size()


def byte_planes(raw: bytes, itemsize: int, inverse: bool = False) -> bytes:
    """``raw`` as byte planes: every element's first byte, then every second byte, ...
    (``inverse``: planes back to elements)."""
    if itemsize == 1 or not raw:
        return raw
    return (
        np.frombuffer(raw, np.uint8)
        .reshape((itemsize, -1) if inverse else (-1, itemsize))
        .T.tobytes()
    )


def array_from_wire(value: dict, kind: str, path: str, budget: Budget) -> np.ndarray | Tensor:
    body = "zstd" if "zstd" in value else "data"
    widen = "as" in value
    exact_keys(value, ("dtype", "shape", body, *(("as",) if widen else ())), path)
    name, shape = _array_header(value, kind, path)
    data = value[body]
    if not isinstance(data, bytes):
        raise MessageError(f"{path}: array data is not bytes")
    size = math.prod(shape) * itemsize(name)
    if body == "zstd":
        budget.take(size, path)
        data = _inflate(data, size, itemsize(name), path)
    if size != len(data):
        raise MessageError(
            f"{path}: {len(data)} bytes do not hold a {name} array of shape "
            f"{tuple(shape)} ({size} bytes)"
        )
    if name == "bool" and data and max(data) > 1:
        raise MessageError(f"{path}: bool array holds bytes other than 0 and 1")
    np_dtype, torch_dtype = ARRAY_DTYPES[name]
    if np_dtype is None:
        bits = np.frombuffer(data, dtype="<i2").astype(np.int16)
        return torch.from_numpy(bits).view(torch_dtype).reshape(shape)
    array = np.frombuffer(data, dtype=np_dtype).reshape(shape).astype(np_dtype.newbyteorder("="))
    if widen:
        if (value["as"], name) != ("float32", "float16"):
            raise MessageError(
                f"{path}: a {name} array cannot travel as {value['as']!r} (only float16 as float32)"
            )
        array = array.astype(np.float32)
    return torch.from_numpy(array) if kind == "tensor" else array


def _array_header(value: dict, kind: str, path: str) -> tuple[str, list[int]]:
    """An array's checked dtype name and shape."""
    name, shape = value["dtype"], value["shape"]
    if not isinstance(name, str) or name not in ARRAY_DTYPES:
        raise MessageError(
            f"{path}: dtype {name!r} is not allowed (allowed: {', '.join(ARRAY_DTYPES)})"
        )
    if ARRAY_DTYPES[name][0] is None and kind == "ndarray":
        raise MessageError(f"{path}: dtype {name} is only allowed for tensors")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
        or math.prod(max(n, 1) for n in shape) > MAX_ELEMENTS
    ):
        raise MessageError(
            f"{path}: shape {shape!r} is not a list of at most {MAX_NDIM} "
            f"non-negative integers spanning at most {MAX_ELEMENTS} elements"
        )
    return name, shape


def _inflate(packed: bytes, size: int, itemsize: int, path: str) -> bytes:
    """The array bytes of a compressed array: exactly ``size`` bytes, or an error."""
    inflater = zstd.ZstdDecompressor()
    try:
        planes = inflater.decompress(packed, max_length=size)
    except zstd.ZstdError as exc:
        raise MessageError(f"{path}: compressed array data is not valid ({exc})") from None
    if len(planes) != size or not inflater.eof or inflater.unused_data:
        raise MessageError(
            f"{path}: compressed array data does not decompress to the {size} bytes of its shape"
        )
    return byte_planes(planes, itemsize, inverse=True)
