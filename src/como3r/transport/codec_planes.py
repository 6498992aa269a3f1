"""Integer planes and the shared helpers of the compact codings
(:mod:`.codec_compact`): a plane of small integers (quantised log ranges, octahedral ray
coordinates, log confidences, match offsets) travels as its residuals under the neighbour
predictor that compresses it most (:data:`PREDICTORS`), zigzag-mapped to the narrowest of
1, 2 or 4 bytes, as byte planes, compressed with Zstandard; decoding checks every size
against the message's :class:`~.codec_arrays.Budget`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from como3r.errors import MessageError
from como3r.transport.codec_arrays import TAG, Budget, exact_keys, zstd

ZSTD_LEVEL = 6
"""Zstandard level of the coded planes (small integers: level 3 is 3-8 % smaller than 1;
on a 512x384 keyframe's pointmaps, confidences and matches level 6 is 2.7 % smaller than 3
for 30 % more time, 9 and 12 no smaller, 19 6.5 % smaller in 13 times the time)."""


# ------------------------------------------------------------------ integer planes


def predict(values: np.ndarray, predictor: str) -> np.ndarray:
    """Residuals of int64 ``(H, W)`` ``values`` under ``predictor`` (outside counts as 0):
    ``"none"``, ``"left"`` (``x[i, j-1]``), ``"up"`` (``x[i-1, j]``) or ``"lorenzo"``
    (``x[i-1, j] + x[i, j-1] - x[i-1, j-1]``); :func:`unpredict` inverts each exactly."""
    out = values.copy()
    if predictor in ("up", "lorenzo"):
        out[1:] -= values[:-1]
    if predictor in ("left", "lorenzo"):
        rows = out.copy()
        out[:, 1:] -= rows[:, :-1]
    return out


def unpredict(residuals: np.ndarray, predictor: str) -> np.ndarray:
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
    residuals = {p: predict(values, p) for p in PREDICTORS}
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
    return unpredict(unpack_ints(ints, count, path, budget).reshape(shape), body["predictor"])


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
    planes = inflate(packed, size, path, "packed integers", f"the {size} bytes of {count} values")
    raw = np.frombuffer(planes, np.uint8).reshape(width, -1).T.tobytes() if width > 1 else planes
    zig = np.frombuffer(raw, f"<u{width}").astype(np.int64)
    return (zig >> 1) ^ -(zig & 1)


# ------------------------------------------------------------------ helpers


def inflate(packed: bytes, size: int, path: str, what: str, expected: str) -> bytes:
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


def as_numpy(value: Any) -> np.ndarray:
    return value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)


def kind_of(value: Any) -> str:
    return "tensor" if isinstance(value, Tensor) else "ndarray"


def as_kind(array: np.ndarray, kind: str) -> Any:
    return torch.from_numpy(np.ascontiguousarray(array)) if kind == "tensor" else array


CODED = "coded"
"""The wire tag of a coded value."""


def coded_header(body: dict, keys: tuple[str, ...], ndim: int, path: str) -> tuple[str, list[int]]:
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


def float32_or_none(value: Any, ndim: int, last: int | None = None) -> np.ndarray | None:
    if not isinstance(value, (Tensor, np.ndarray)) or value.dtype not in (
        torch.float32,
        np.float32,
    ):
        return None
    array = as_numpy(value)
    if array.ndim != ndim or (last is not None and array.shape[-1] != last):
        return None
    return array


# ------------------------------------------------------------------ paired steps

STEP_RADIX = 15
"""Two small steps (zigzag-mapped, each under this) travel as one byte ``a * 15 + b``."""

_ESCAPE = STEP_RADIX * STEP_RADIX
"""The byte of a pair that does not fit; both steps then travel in :func:`pack_ints`."""


def pack_steps(first: np.ndarray, second: np.ndarray) -> dict[str, Any] | None:
    """Two int64 ``(n,)`` step sequences (a match's column and row steps): one byte per pair
    where both are small (their joint distribution compresses 5-6 % better than each
    alone), the escaped pairs' steps in :func:`pack_ints`; None where one needs more than
    4 bytes."""
    zig = [(s << 1) ^ (s >> 63) for s in (first.astype(np.int64), second.astype(np.int64))]
    fits = (zig[0] < STEP_RADIX) & (zig[1] < STEP_RADIX)
    pairs = np.where(fits, zig[0] * STEP_RADIX + zig[1], _ESCAPE).astype(np.uint8)
    escaped = [pack_ints(s[~fits]) for s in (first, second)]
    if escaped[0] is None or escaped[1] is None:
        return None
    return {
        "pairs": zstd.compress(pairs.tobytes(), level=ZSTD_LEVEL),
        "first": escaped[0],
        "second": escaped[1],
    }


def unpack_steps(body: Any, count: int, path: str, budget: Budget) -> tuple[np.ndarray, np.ndarray]:
    """The two int64 ``(count,)`` step sequences of a :func:`pack_steps` body, or
    :class:`MessageError`."""
    if not isinstance(body, dict):
        raise MessageError(f"{path}: packed steps are not a map")
    exact_keys({TAG: None, **body}, ("pairs", "first", "second"), path)
    if not isinstance(body["pairs"], bytes):
        raise MessageError(f"{path}: packed step pairs are not bytes")
    budget.take(count, path)
    raw = inflate(body["pairs"], count, path, "packed step pairs", f"{count} bytes")
    pairs = np.frombuffer(raw, np.uint8).astype(np.int64)
    if (pairs > _ESCAPE).any():
        raise MessageError(f"{path}: packed step pairs beyond {_ESCAPE}")
    fits = pairs < _ESCAPE
    escaped = int((~fits).sum())
    out = []
    for zig, key in ((pairs // STEP_RADIX, "first"), (pairs % STEP_RADIX, "second")):
        steps = (zig >> 1) ^ -(zig & 1)
        steps[~fits] = unpack_ints(body[key], escaped, f"{path}.{key}", budget)
        out.append(steps)
    return out[0], out[1]
