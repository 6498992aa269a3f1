"""The compressed blobs of the session store (:mod:`como3r.store.writer`): no pickle.

Two kinds, told apart by their first four bytes:

* **arrays** (``C3RA``): one or more arrays (pointmaps, confidences, poses, matches,
  retrieval features). Layout::

      b"C3RA" | u8 count | per array: u8 dtype code, u8 ndim, ndim x u64 dims (little-endian)
              | Zstandard frame of every array's bytes, byte-shuffled, one after the other

  Dtype codes index :data:`DTYPES` (the wire names of :data:`como3r.transport.codec_arrays.
  ARRAY_DTYPES`; append only). Byte-shuffling (all first bytes of the elements, then all
  second bytes, ...) groups the slowly varying exponent bytes of floats and the zero high
  bytes of indices: on a 512x384 float32 pointmap zlib then keeps 74 % of the bytes
  instead of 91 %, in two thirds of the time.
* **objects** (``C3RO``): a registered dataclass of :mod:`como3r.transport.codec` (a prior's
  :class:`~como3r.prior.base.Encoding`, an agent's final report, or since format version 5
  one of :mod:`.coded`'s arrays in the wire's compact codings),
  ``b"C3RO" | zstd(codec.encode(obj))`` (with ``lossy`` for the coded arrays); decoding
  validates it as a received message is validated.

Zstandard at the messages' level (:data:`como3r.transport.codec_arrays.ZSTD_LEVEL`) rather
than zlib (format version 2): on a shuffled 512x384 float32 pointmap it keeps 74.3 % of the bytes
against zlib level 1's 72.7 %, compressing in 2 ms instead of 45 and inflating in 1.4 ms
instead of 4.2 (one core); the demo's coordinator spent 7 s of its CPU in zlib's
compression and 6 s in its decompression (14 keyframes, paging included).

Whatever does not decode exactly (wrong magic, unknown dtype, sizes that disagree, a
compressed frame that is cut, longer or corrupted) raises :class:`~como3r.errors.StoreError`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from como3r.errors import MessageError, StoreError
from como3r.transport import codec, codec_arrays
from como3r.transport.codec_arrays import ZSTD_LEVEL, byte_planes, itemsize, zstd

ARRAYS_MAGIC = b"C3RA"
OBJECT_MAGIC = b"C3RO"

#: dtype code -> wire name (:data:`como3r.transport.codec_arrays.ARRAY_DTYPES`); part of the format
DTYPES = (
    "bool",
    "uint8",
    "int8",
    "int16",
    "int32",
    "int64",
    "float16",
    "float32",
    "float64",
    "bfloat16",
)
_CODE = {name: code for code, name in enumerate(DTYPES)}
_TORCH_NAME = {torch_dtype: name for name, (_, torch_dtype) in codec_arrays.ARRAY_DTYPES.items()}

#: Zstandard at the messages' level, with the frame's content checksum (XXH64) that zlib's
#: Adler-32 gave: a damaged blob is an error, not different numbers
ZSTD_OPTIONS = {
    zstd.CompressionParameter.compression_level: ZSTD_LEVEL,
    zstd.CompressionParameter.checksum_flag: 1,
}
MAX_ARRAYS = 16
MAX_BYTES = 2**34  # 16 GiB: the largest array set a blob may claim to hold

_HEAD = struct.Struct("<4sB")
_ARRAY = struct.Struct("<BB")
_DIM = struct.Struct("<Q")


def pack_arrays(*arrays: Tensor | np.ndarray) -> bytes:
    """One blob of ``arrays`` (tensors are read from the CPU, detached; shapes and dtypes
    are kept, bfloat16 included)."""
    if not 1 <= len(arrays) <= MAX_ARRAYS:
        raise ValueError(f"a blob holds 1 to {MAX_ARRAYS} arrays, got {len(arrays)}")
    header = [_HEAD.pack(ARRAYS_MAGIC, len(arrays))]
    body = zstd.ZstdCompressor(options=ZSTD_OPTIONS)
    chunks = []
    for array in arrays:
        name, shape, raw = _raw(array)
        header.append(_ARRAY.pack(_CODE[name], len(shape)))
        header.extend(_DIM.pack(n) for n in shape)
        chunks.append(body.compress(byte_planes(raw, itemsize(name))))
    chunks.append(body.flush())
    return b"".join(header + chunks)


def unpack_arrays(blob: bytes, what: str) -> list[Tensor]:
    """The arrays of a :func:`pack_arrays` blob, as CPU tensors.

    Args:
        blob: the blob.
        what: names the blob in errors (``"keyframe 12 X_hat"``).

    Raises:
        StoreError: the blob is not exactly such a blob.
    """
    data = memoryview(blob)
    if len(data) < _HEAD.size or bytes(data[:4]) != ARRAYS_MAGIC:
        raise StoreError(f"{what}: not an array blob")
    _, count = _HEAD.unpack_from(data)
    if not 1 <= count <= MAX_ARRAYS:
        raise StoreError(f"{what}: claims {count} arrays")
    offset, specs = _HEAD.size, []
    for _ in range(count):
        if offset + _ARRAY.size > len(data):
            raise StoreError(f"{what}: header cut short")
        code, ndim = _ARRAY.unpack_from(data, offset)
        offset += _ARRAY.size
        if (
            code >= len(DTYPES)
            or ndim > codec_arrays.MAX_NDIM
            or offset + ndim * _DIM.size > len(data)
        ):
            raise StoreError(f"{what}: bad array header (dtype code {code}, {ndim} dimensions)")
        shape = [_DIM.unpack_from(data, offset + k * _DIM.size)[0] for k in range(ndim)]
        offset += ndim * _DIM.size
        specs.append((DTYPES[code], shape))
    sizes = [math.prod(shape) * itemsize(name) for name, shape in specs]
    if sum(sizes) > MAX_BYTES:
        raise StoreError(f"{what}: claims {sum(sizes)} bytes")
    payload = _inflate(data[offset:], sum(sizes), what)
    arrays, start = [], 0
    for (name, shape), size in zip(specs, sizes):
        arrays.append(
            _array(
                name,
                shape,
                byte_planes(payload[start : start + size], itemsize(name), inverse=True),
                what,
            )
        )
        start += size
    return arrays


def pack_object(obj: Any) -> bytes:
    """One blob of a registered dataclass (:mod:`como3r.transport.codec`)."""
    return OBJECT_MAGIC + zstd.compress(
        codec.encode(obj, max_bytes=MAX_BYTES), options=ZSTD_OPTIONS
    )


def unpack_object(blob: bytes, expected: type | tuple[type, ...], what: str) -> Any:
    """The object of a :func:`pack_object` blob, validated by the codec.

    Raises:
        StoreError: not such a blob, or the codec rejects what it holds.
    """
    if bytes(blob[:4]) != OBJECT_MAGIC:
        raise StoreError(f"{what}: not an object blob")
    data = _inflate(memoryview(blob)[4:], None, what)
    try:
        return codec.decode(data, max_bytes=MAX_BYTES, expected=expected)
    except MessageError as exc:
        raise StoreError(f"{what}: {exc}") from None


# ------------------------------------------------------------------------------ helpers


def _raw(array: Tensor | np.ndarray) -> tuple[str, Sequence[int], bytes]:
    """Wire dtype name, shape and little-endian bytes of an array."""
    if isinstance(array, Tensor):
        name = _TORCH_NAME.get(array.dtype)
        if name is None:
            raise ValueError(f"tensor dtype {array.dtype} cannot be stored")
        tensor = array.detach().cpu().contiguous()
        bits = (tensor.view(torch.int16) if tensor.dtype == torch.bfloat16 else tensor).numpy()
        little = np.ascontiguousarray(bits, dtype=bits.dtype.newbyteorder("<"))
        return name, tuple(tensor.shape), little.tobytes()
    for name, (np_dtype, _) in codec_arrays.ARRAY_DTYPES.items():
        if np_dtype is not None and array.dtype.newbyteorder("=") == np_dtype.newbyteorder("="):
            return name, array.shape, np.ascontiguousarray(array, dtype=np_dtype).tobytes()
    raise ValueError(f"array dtype {array.dtype} cannot be stored")


def _inflate(data: memoryview, size: int | None, what: str) -> bytes:
    """The Zstandard frame ``data`` inflated; exactly ``size`` bytes when given."""
    inflater = zstd.ZstdDecompressor()
    try:
        out = inflater.decompress(data, max_length=MAX_BYTES if size is None else size + 1)
    except zstd.ZstdError as exc:
        raise StoreError(f"{what}: corrupted ({exc})") from None
    if not inflater.eof or inflater.unused_data:
        raise StoreError(f"{what}: corrupted (the compressed data is cut short or too long)")
    if size is not None and len(out) != size:
        raise StoreError(f"{what}: holds {len(out)} bytes, its header says {size}")
    return out


def _array(name: str, shape: list[int], raw: bytes, what: str) -> Tensor:
    np_dtype, torch_dtype = codec_arrays.ARRAY_DTYPES[name]
    if np_dtype is None:  # bfloat16: stored as its int16 bits
        return (
            torch.from_numpy(np.frombuffer(raw, "<i2").astype(np.int16))
            .view(torch_dtype)
            .reshape(shape)
        )
    if name == "bool" and raw and int(np.frombuffer(raw, np.uint8).max()) > 1:
        raise StoreError(f"{what}: bool array holds bytes other than 0 and 1")
    array = np.frombuffer(raw, np_dtype).astype(np_dtype.newbyteorder("="))
    return torch.from_numpy(array.reshape(shape))
