"""Compact codings of a keyframe's large parts on the lossy wire (across machines;
:func:`como3r.transport.codec.encode` with ``lossy``), each at the precision its receiver
reads (manual: docs/architecture.md, "Processes and messages").

A field registered with a coding (:func:`~como3r.transport.codec_registry.register`,
``coded``) travels as ``{"#": "coded", "coding": name, ...}`` in a lossy encode and is
decoded back to the value's own type; where a value does not fit its coding (a pointmap
with a zero or non-finite point, a confidence that is not positive) it travels as before
(float16 where the field is a half-precision one). The exact encode (pipes on one machine)
never uses them.

* ``"pointmap"``: an ``(H, W, 3)`` float32 pointmap as the range along each point's ray,
  ``log2`` quantised in steps of ``2^-LOG_RANGE_BITS``, and the ray's direction in
  octahedral coordinates quantised in steps of ``2^-OCT_BITS``: a point moves by at most
  :data:`POINTMAP_RELATIVE_ERROR` of its range (7.8e-4; float16 xyz: up to 4.9e-4 per
  coordinate; MASt3R's own error is about 1e-3). Each integer plane is predicted from its neighbours
  (:data:`PREDICTORS`, the best per plane) and the residuals compressed.
* ``"confidence"``: an ``(H, W)`` positive float32 confidence as ``log2`` quantised in steps
  of ``2^-CONFIDENCE_BITS``, within :data:`CONFIDENCE_RELATIVE_ERROR` relative (its
  receivers weigh residuals by it: global BA, depth refinement); predicted and compressed
  likewise.
* ``"matches"``: a :class:`~como3r.frontend.pairs.DirectedMatches` as the receiver reads it
  (:mod:`como3r.optim.factors`: matches where ``valid``, ``q`` zero elsewhere): the valid
  mask (bits), each valid match's index exactly, as its column and row offsets from its
  own pixel (each as its difference to the previous valid match's), and each valid ``q``
  ``log2`` quantised (:data:`MATCH_Q_BITS`). Invalid pixels come back matched to
  themselves with ``q`` 0.
* ``"image"``: an ``(H, W, 3)`` uint8 image, lossless (the coordinator re-encodes the
  network's input from it) in WebP's lossless mode (:data:`WEBP_METHOD`); the header's
  size is checked against the declared shape before the pixels are decoded.
* ``"retrieval"``: a keyframe's ``(descriptors (N, d), attention (N,))`` float32: every
  descriptor in 8 bits with its own scale (its largest magnitude over 127), the attention
  in float16. The coordinator's binary ASMK keeps only the signs of per-word residual sums
  (:mod:`como3r.prior.retrieval`); on 17 keyframes of 2 synthetic agents (simulated prior,
  300 x 128; ``benchmarks/retrieval_precision.py``) every query's hits were the same as with
  float32 features, with the agents' words and with the coordinator quantising, their
  similarities within 4.4e-4.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from como3r.errors import MessageError
from como3r.transport.codec_arrays import (
    TAG,
    Budget,
    exact_keys,
    zstd,
)
from como3r.transport.codec_registry import CHECKS, REGISTRY, resolve

CODED = "coded"
"""The wire tag of a coded value."""

LOG_RANGE_BITS = 9
"""A point's range travels as ``round(log2(range) * 2^LOG_RANGE_BITS)``."""

OCT_BITS = 14
"""A ray's octahedral coordinates (in [-1, 1]) travel as ``round(u * 2^OCT_BITS)``."""

POINTMAP_RELATIVE_ERROR = 7.8e-4
"""Bound on ``|X' - X| / |X|`` of a pointmap after the ``"pointmap"`` coding: the range's
quantisation (``2^(2^-10) - 1 = 6.8e-4``; MASt3R's own error is about 1e-3) plus the direction's (at most 9e-5 rad: half a
step of 2^-14 across the octahedral map's largest stretch)."""

CONFIDENCE_BITS = 2
"""A confidence travels as ``round(log2(C) * 2^CONFIDENCE_BITS)``."""

CONFIDENCE_RELATIVE_ERROR = 2 ** (2.0 ** -(CONFIDENCE_BITS + 1)) - 1
"""Bound on ``|C' - C| / C`` after the ``"confidence"`` coding (9.1 %: a BA weight; MASt3R's
confidence varies by far more between two views of the same point)."""

MATCH_Q_BITS = 2
"""A valid match's confidence ``q`` travels as ``round(log2(q) * 2^MATCH_Q_BITS)``, within
``2^(2^-3) - 1 = 9.1 %`` relative (it weighs the match's residual, C-Eq. 17)."""

WEBP_METHOD = 0
"""WebP's lossless effort (0: fastest): 218 kB for a synthetic 512x384 frame in 55 ms, where
method 4 takes 290 ms for 189 kB; PNG (OpenCV, level 3) 267 kB in 58 ms, the byte planes with
Zstandard 400 kB."""

WEBP_EFFORT = 50
"""WebP's lossless ``quality`` (the encoder's effort at the chosen method)."""

WEBP_MAX_SIDE = 16383
"""WebP's largest image side; a larger image travels uncoded."""

ZSTD_LEVEL = 3
"""Zstandard level of the coded planes (small integers: level 3 is 3-8 % smaller than 1
and fast enough at these sizes)."""


# ------------------------------------------------------------------ integer planes


def _predict(values: np.ndarray, predictor: str) -> np.ndarray:
    """Residuals of int64 ``(H, W)`` ``values`` under ``predictor`` (outside counts as 0):
    ``"none"``, ``"left"`` (``x[i, j-1]``), ``"up"`` (``x[i-1, j]``) or ``"lorenzo"``
    (``x[i-1, j] + x[i, j-1] - x[i-1, j-1]``); :func:`_unpredict` inverts each exactly."""
    out = values.copy()
    if predictor in ("up", "lorenzo"):
        out[1:] -= values[:-1]
    if predictor in ("left", "lorenzo"):
        rows = out.copy()
        out[:, 1:] -= rows[:, :-1]
    return out


def _unpredict(residuals: np.ndarray, predictor: str) -> np.ndarray:
    out = residuals
    if predictor in ("left", "lorenzo"):
        out = np.cumsum(out, axis=1)
    if predictor in ("up", "lorenzo"):
        out = np.cumsum(out, axis=0)
    return out


PREDICTORS = ("none", "left", "up", "lorenzo")
"""Each integer plane travels under the one of these that compresses it most (smooth
planes: ``lorenzo``; noisy ones: ``left`` or ``up``)."""


def pack_plane(values: np.ndarray) -> dict[str, Any] | None:
    """An int64 ``(H, W)`` plane's residuals under the predictor (:data:`PREDICTORS`) whose
    middle quarter of rows compresses smallest, :func:`pack_ints`; None where a residual
    needs more than 4 bytes. (Compressing the whole plane under each took 2.5 times as long;
    the smallest sum of magnitudes, or every fourth row, chose worse: pointmaps 6 % larger.)"""
    residuals = {p: _predict(values, p) for p in PREDICTORS}
    rows = values.shape[0]
    trials = {p: pack_ints(r[3 * rows // 8 : 5 * rows // 8 + 1]) for p, r in residuals.items()}
    fits = [p for p in PREDICTORS if trials[p] is not None]
    if not fits:
        return None
    predictor = min(fits, key=lambda p: len(trials[p]["zstd"]))  # type: ignore[index]
    packed = pack_ints(residuals[predictor])
    return None if packed is None else {"predictor": predictor, **packed}


def unpack_plane(body: Any, shape: tuple[int, int], path: str, budget: Budget) -> np.ndarray:
    """The int64 ``shape`` plane of a :func:`pack_plane` body, or :class:`MessageError`."""
    if not isinstance(body, dict) or body.get("predictor") not in PREDICTORS:
        raise MessageError(f"{path}: a packed plane without a known predictor")
    ints = {k: v for k, v in body.items() if k != "predictor"}
    count = shape[0] * shape[1]
    return _unpredict(unpack_ints(ints, count, path, budget).reshape(shape), body["predictor"])


def pack_ints(values: np.ndarray) -> dict[str, Any] | None:
    """int64 ``values`` zigzag-mapped to the narrowest of 1, 2 or 4 bytes, as byte planes,
    compressed; None where one needs more than 4 bytes."""
    flat = values.astype(np.int64).ravel()
    zig = ((flat << 1) ^ (flat >> 63)).astype(np.uint64)
    top = int(zig.max()) if zig.size else 0
    width = next((w for w in (1, 2, 4) if top < 1 << (8 * w)), None)
    if width is None:
        return None
    raw = zig.astype(f"<u{width}").tobytes()
    planes = np.frombuffer(raw, np.uint8).reshape(-1, width).T.tobytes() if width > 1 else raw
    return {"width": width, "zstd": zstd.compress(planes, level=ZSTD_LEVEL)}


def unpack_ints(body: Any, count: int, path: str, budget: Budget) -> np.ndarray:
    """The ``count`` int64 values of a :func:`pack_ints` body, or :class:`MessageError`."""
    if not isinstance(body, dict):
        raise MessageError(f"{path}: packed integers are not a map")
    exact_keys({TAG: None, **body}, ("width", "zstd"), path)
    width, packed = body["width"], body["zstd"]
    if width not in (1, 2, 4) or isinstance(width, bool) or not isinstance(packed, bytes):
        raise MessageError(f"{path}: packed integers of width {width!r}")
    size = count * width
    budget.take(size, path)
    planes = _inflate(packed, size, path, "packed integers", f"the {size} bytes of {count} values")
    raw = np.frombuffer(planes, np.uint8).reshape(width, -1).T.tobytes() if width > 1 else planes
    zig = np.frombuffer(raw, f"<u{width}").astype(np.int64)
    return (zig >> 1) ^ -(zig & 1)


# ------------------------------------------------------------------ helpers


def _inflate(packed: bytes, size: int, path: str, what: str, expected: str) -> bytes:
    """Exactly ``size`` bytes from one whole Zstandard frame (never more: the budget was
    taken for them), or a :class:`MessageError` naming ``what`` and the ``expected`` size."""
    inflater = zstd.ZstdDecompressor()
    try:
        raw = inflater.decompress(packed, max_length=size)
    except zstd.ZstdError as exc:
        raise MessageError(f"{path}: {what}: not Zstandard ({exc})") from None
    if len(raw) != size or not inflater.eof or inflater.unused_data:
        raise MessageError(f"{path}: {what}: not {expected}")
    return raw


def _numpy(value: Any) -> np.ndarray:
    return value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)


def _kind(value: Any) -> str:
    return "tensor" if isinstance(value, Tensor) else "ndarray"


def _as_kind(array: np.ndarray, kind: str) -> Any:
    return torch.from_numpy(np.ascontiguousarray(array)) if kind == "tensor" else array


def _header(body: dict, keys: tuple[str, ...], ndim: int, path: str) -> tuple[str, list[int]]:
    """A coded body's checked keys, ``kind`` and ``shape`` of ``ndim`` non-negative sizes."""
    exact_keys(body, ("coding", "kind", "shape", *keys), path)
    kind, shape = body["kind"], body["shape"]
    if kind not in ("tensor", "ndarray"):
        raise MessageError(f"{path}: coded kind {kind!r}")
    if not (
        isinstance(shape, list)
        and len(shape) == ndim
        and all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n < 2**24 for n in shape)
    ):
        raise MessageError(f"{path}: coded shape {shape!r} is not {ndim} sizes")
    return kind, shape


def _float32(value: Any, ndim: int, last: int | None = None) -> np.ndarray | None:
    if not isinstance(value, (Tensor, np.ndarray)) or value.dtype not in (
        torch.float32,
        np.float32,
    ):
        return None
    array = _numpy(value)
    if array.ndim != ndim or (last is not None and array.shape[-1] != last):
        return None
    return array


# ------------------------------------------------------------------ pointmap


def _octahedral(unit: np.ndarray) -> np.ndarray:
    """``(..., 3)`` unit vectors -> ``(..., 2)`` octahedral coordinates in [-1, 1]."""
    p = unit[..., :2] / np.abs(unit).sum(-1, keepdims=True)
    sign = np.where(p >= 0, 1.0, -1.0)
    folded = (1 - np.abs(p[..., ::-1])) * sign
    return np.where(unit[..., 2:] < 0, folded, p)


def _from_octahedral(p: np.ndarray) -> np.ndarray:
    """``(..., 2)`` octahedral coordinates -> ``(..., 3)`` unit vectors."""
    z = 1 - np.abs(p).sum(-1)
    t = np.clip(-z, 0, None)[..., None]
    xy = p - np.where(p >= 0, t, -t)
    v = np.concatenate([xy, z[..., None]], -1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _pointmap_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    X = _float32(value, 3, 3)
    if X is None:
        return None
    X64 = X.astype(np.float64)
    r = np.linalg.norm(X64, axis=-1)
    if not (np.isfinite(X64).all() and (r > 1e-30).all()):
        return None
    oct_ = np.rint(_octahedral(X64 / r[..., None]) * 2**OCT_BITS).astype(np.int64)
    planes = [
        pack_plane(np.rint(np.log2(r) * 2**LOG_RANGE_BITS).astype(np.int64)),
        pack_plane(oct_[..., 0]),
        pack_plane(oct_[..., 1]),
    ]
    if any(p is None for p in planes):
        return None
    return {"kind": _kind(value), "shape": list(X.shape), "planes": planes}


def _pointmap_decode(body: dict, path: str, budget: Budget) -> Any:
    kind, shape = _header(body, ("planes",), 3, path)
    planes = body["planes"]
    if shape[2] != 3 or not (isinstance(planes, list) and len(planes) == 3):
        raise MessageError(f"{path}: a coded pointmap is (H, W, 3) in three planes")
    log_r, u, v = (unpack_plane(p, (shape[0], shape[1]), path, budget) for p in planes)
    if (
        max(np.abs(u).max(initial=0), np.abs(v).max(initial=0)) > 2**OCT_BITS
        or np.abs(log_r).max(initial=0) > 120 * 2**LOG_RANGE_BITS
    ):
        raise MessageError(f"{path}: coded pointmap values out of range")
    r = np.exp2(log_r / 2**LOG_RANGE_BITS)
    direction = _from_octahedral(np.stack([u, v], -1) / 2**OCT_BITS)
    return _as_kind((direction * r[..., None]).astype(np.float32), kind)


# ------------------------------------------------------------------ confidence


def _log_plane(values: np.ndarray, bits: int) -> np.ndarray:
    return np.rint(np.log2(values.astype(np.float64)) * 2**bits).astype(np.int64)


def _confidence_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    C = _float32(value, 2)
    if C is None or not (np.isfinite(C).all() and (C > 0).all()):
        return None
    plane = pack_plane(_log_plane(C, CONFIDENCE_BITS))
    return None if plane is None else {"kind": _kind(value), "shape": list(C.shape), "plane": plane}


def _confidence_decode(body: dict, path: str, budget: Budget) -> Any:
    kind, shape = _header(body, ("plane",), 2, path)
    q = unpack_plane(body["plane"], (shape[0], shape[1]), path, budget)
    if np.abs(q).max(initial=0) > 120 * 2**CONFIDENCE_BITS:
        raise MessageError(f"{path}: coded confidence values out of range")
    return _as_kind(np.exp2(q / 2**CONFIDENCE_BITS).astype(np.float32), kind)


# ------------------------------------------------------------------ matches


def _matches_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    names = ("idx", "valid", "q")
    if type(value).__name__ != "DirectedMatches" or not all(
        isinstance(getattr(value, n, None), Tensor) for n in names
    ):
        return None
    idx, valid, q = (_numpy(getattr(value, n)) for n in names)
    if not (
        idx.ndim == 1
        and idx.dtype == np.int64
        and valid.dtype == np.bool_
        and valid.shape == idx.shape == q.shape
        and q.dtype == np.float32
    ):
        return None
    pixels = np.flatnonzero(valid)
    kept = q[pixels].astype(np.float64)
    if not (np.isfinite(kept).all() and (kept > 0).all()):
        return None
    # the row length of the keyframe: offsets split into columns and rows, each close to
    # its predecessor's (smooth flow) where a linear offset jumps by a row at every step
    width = int(owner.X_hat.shape[1]) if hasattr(owner, "X_hat") else 1
    width = width if idx.shape[0] % max(width, 1) == 0 and width > 0 else 1
    columns = (idx[pixels] % width) - (pixels % width)
    rows = (idx[pixels] // width) - (pixels // width)
    parts = [
        pack_ints(np.diff(columns, prepend=np.int64(0))),
        pack_ints(np.diff(rows, prepend=np.int64(0))),
        pack_ints(np.diff(_log_plane(kept, MATCH_Q_BITS), prepend=np.int64(0))),
    ]
    if any(p is None for p in parts):
        return None
    return {
        "count": int(idx.shape[0]),
        "width": width,
        "valid": zstd.compress(np.packbits(valid).tobytes(), level=ZSTD_LEVEL),
        "columns": parts[0],
        "rows": parts[1],
        "q": parts[2],
    }


def _matches_decode(body: dict, path: str, budget: Budget) -> Any:
    exact_keys(body, ("coding", "count", "width", "valid", "columns", "rows", "q"), path)
    count, width, bits = body["count"], body["width"], body["valid"]
    for name, n in (("count", count), ("width", width)):
        if not (isinstance(n, int) and not isinstance(n, bool) and 0 <= n < 2**32):
            raise MessageError(f"{path}: coded matches {name} {n!r}")
    if width < 1 or count % width:
        raise MessageError(f"{path}: coded matches of {count} pixels in rows of {width}")
    if not isinstance(bits, bytes):
        raise MessageError(f"{path}: coded matches' valid mask is not bytes")
    size = (count + 7) // 8
    budget.take(size, path)
    mask = _inflate(bits, size, path, "coded valid mask", f"{size} bytes")
    valid = np.unpackbits(np.frombuffer(mask, np.uint8), count=count).astype(bool)
    pixels = np.flatnonzero(valid)
    columns, rows, log_q = (
        np.cumsum(unpack_ints(body[k], len(pixels), f"{path}.{k}", budget))
        for k in ("columns", "rows", "q")
    )
    idx = np.arange(count, dtype=np.int64)
    idx[pixels] += rows * width + columns
    if np.abs(log_q).max(initial=0) > 120 * 2**MATCH_Q_BITS:
        raise MessageError(f"{path}: coded match confidences out of range")
    q = np.zeros(count, np.float32)
    q[pixels] = np.exp2(log_q / 2**MATCH_Q_BITS)
    cls = resolve(REGISTRY["DirectedMatches"])
    matches = cls(torch.from_numpy(idx), torch.from_numpy(valid), torch.from_numpy(q))
    if "DirectedMatches" in CHECKS:
        try:
            CHECKS["DirectedMatches"](matches)
        except (ValueError, MessageError) as exc:
            raise MessageError(f"{path}: invalid coded matches: {exc}") from None
    return matches


# ------------------------------------------------------------------ image


def _image_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    if not (
        isinstance(value, np.ndarray)
        and value.dtype == np.uint8
        and value.ndim == 3
        and value.shape[2] == 3
        and 0 < min(value.shape[:2])
        and max(value.shape[:2]) <= WEBP_MAX_SIDE
    ):
        return None
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(value), "RGB").save(
        buffer, "WEBP", lossless=True, method=WEBP_METHOD, quality=WEBP_EFFORT
    )
    return {"kind": "ndarray", "shape": list(value.shape), "webp": buffer.getvalue()}


def _image_decode(body: dict, path: str, budget: Budget) -> Any:
    kind, shape = _header(body, ("webp",), 3, path)
    data = body["webp"]
    if kind != "ndarray" or shape[2] != 3 or not isinstance(data, bytes):
        raise MessageError(f"{path}: a coded image is an (H, W, 3) ndarray in WebP bytes")
    budget.take(shape[0] * shape[1] * 3, path)
    try:
        with Image.open(io.BytesIO(data), formats=["WEBP"]) as image:
            # the header first: a size other than the declared one is never decoded
            if image.size != (shape[1], shape[0]) or image.mode not in ("RGB", "RGBA"):
                raise MessageError(
                    f"{path}: coded image is {image.mode} {image.size}, "
                    f"declared {shape[1]}x{shape[0]} RGB"
                )
            pixels = np.asarray(image.convert("RGB"))
    except (OSError, SyntaxError, Image.DecompressionBombError) as exc:
        raise MessageError(f"{path}: coded image is not a valid WebP ({exc})") from None
    return np.ascontiguousarray(pixels, dtype=np.uint8)


# ------------------------------------------------------------------ retrieval


def _retrieval_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    if not (isinstance(value, tuple) and len(value) == 2):
        return None
    descriptors, attention = _float32(value[0], 2), _float32(value[1], 1)
    if descriptors is None or attention is None or not np.isfinite(descriptors).all():
        return None
    if not (np.isfinite(attention).all() and np.abs(attention).max(initial=0) < 65504):
        return None
    scale = np.abs(descriptors).max(axis=1) / 127
    scale = np.where(scale > 0, scale, 1).astype(np.float32)
    q = np.rint(descriptors / scale[:, None]).astype(np.int8)
    return {
        "kind": _kind(value[0]),
        "shape": list(descriptors.shape),
        "q": zstd.compress(q.tobytes(), level=ZSTD_LEVEL),
        "scale": scale.tobytes(),
        "attention": attention.astype(np.float16).tobytes(),
    }


def _retrieval_decode(body: dict, path: str, budget: Budget) -> Any:
    kind, (n, d) = _header(body, ("q", "scale", "attention"), 2, path)
    packed, scale, attention = body["q"], body["scale"], body["attention"]
    if not all(isinstance(b, bytes) for b in (packed, scale, attention)):
        raise MessageError(f"{path}: coded retrieval features are not bytes")
    if len(scale) != 4 * n or len(attention) != 2 * n:
        raise MessageError(f"{path}: coded retrieval scales or attention are not {n} values")
    budget.take(n * d, path)
    raw = _inflate(packed, n * d, path, "coded descriptors", f"{n} x {d} bytes")
    scales = np.frombuffer(scale, "<f4").astype(np.float32)
    if not np.isfinite(scales).all():
        raise MessageError(f"{path}: coded descriptor scales are not finite")
    q = np.frombuffer(raw, np.int8).reshape(n, d).astype(np.float32)
    descriptors = q * scales[:, None]
    weights = np.frombuffer(attention, "<f2").astype(np.float32)
    return (_as_kind(descriptors, kind), _as_kind(weights, kind))


# ------------------------------------------------------------------ registry

Encoder = Callable[[Any, Any], "dict[str, Any] | None"]
Decoder = Callable[[dict, str, Budget], Any]

CODINGS: dict[str, tuple[Encoder, Decoder]] = {
    "pointmap": (_pointmap_encode, _pointmap_decode),
    "confidence": (_confidence_encode, _confidence_decode),
    "matches": (_matches_encode, _matches_decode),
    "image": (_image_encode, _image_decode),
    "retrieval": (_retrieval_encode, _retrieval_decode),
}
"""Coding name -> (encoder: value -> wire body or None where it does not fit, decoder)."""


def coded_to_wire(coding: str, value: Any, owner: Any = None) -> dict[str, Any] | None:
    """``value`` (a field of ``owner``) in ``coding`` as its wire map, or None where it does
    not fit the coding."""
    body = CODINGS[coding][0](value, owner)
    return None if body is None else {TAG: CODED, "coding": coding, **body}


def coded_from_wire(value: dict, path: str, budget: Budget) -> Any:
    """The value of a coded wire map (:class:`MessageError` where it is malformed)."""
    coding = value.get("coding")
    if not isinstance(coding, str) or coding not in CODINGS:
        raise MessageError(f"{path}: unknown coding {coding!r}")
    try:
        return CODINGS[coding][1](value, path, budget)
    except (ValueError, TypeError, OverflowError) as exc:
        raise MessageError(f"{path}: malformed {coding} coding: {exc}") from None
