"""Compact codings of a keyframe's large parts on the lossy wire (across machines;
:func:`como3r.transport.codec.encode` with ``lossy``), each at the precision its receiver
reads (manual: docs/architecture.md, "Processes and messages").

A field registered with a coding (:func:`~como3r.transport.codec_registry.register`,
``coded``) travels as ``{"#": "coded", "coding": name, ...}`` in a lossy encode and is
decoded back to the value's own type; where a value does not fit its coding (a pointmap
with a zero or non-finite point, a confidence that is not positive) it travels as before
(float16 where the field is a half-precision one). The exact encode never uses them (what
the coordinator sends on pipes; an agent process sends in them: :mod:`.pipes`).

* ``"pointmap"``: an ``(H, W, 3)`` float32 pointmap as the range along each point's ray,
  ``log2`` quantised in steps of ``2^-LOG_RANGE_BITS``, and the ray's direction in
  octahedral coordinates quantised in steps of ``2^-OCT_BITS``: a point moves by at most
  :data:`POINTMAP_RELATIVE_ERROR` of its range (1.72e-3; float16 xyz: up to 4.9e-4 per
  coordinate; the simulated prior's per-pixel range noise is 5e-3). Where a pinhole camera's
  rays fit the directions (a calibrated or self-calibrated keyframe's lie on them), the
  direction codes travel less those of the fitted pinhole (four numbers), mostly zeros.
  Each integer plane is predicted from its neighbours (:data:`~.codec_planes.PREDICTORS`,
  the best per plane) and the residuals compressed.
* ``"confidence"``: an ``(H, W)`` positive float32 confidence as ``log2`` quantised in steps
  of ``2^-CONFIDENCE_BITS``, within :data:`CONFIDENCE_RELATIVE_ERROR` relative (its
  receivers weigh residuals by it: global BA, depth refinement); predicted and compressed
  likewise.
* ``"matches"``: a :class:`~como3r.frontend.pairs.DirectedMatches` as the receiver reads it
  (:mod:`como3r.optim.factors`: matches where ``valid``, ``q`` zero elsewhere): the valid
  mask (bits), each valid match's index exactly, as its column and row offsets from its
  own pixel (each as its difference to the previous valid match's, the two differences in
  one byte where both are small: :func:`~.codec_planes.pack_steps`), and each valid ``q``
  ``log2`` quantised (:data:`MATCH_Q_BITS`; as it is or as differences, whichever is
  smaller). Invalid pixels come back matched to themselves with ``q`` 0.
* ``"inter_matches"``: ``"matches"`` with ``q`` in finer steps (:data:`INTER_MATCH_Q_BITS`,
  carried as ``q_bits``): an inter-agent edge's in the session store.
* ``"image"``: an ``(H, W, 3)`` uint8 image, lossless (the coordinator re-encodes the
  network's input from it) in WebP's lossless mode (:data:`WEBP_METHOD`); the header's
  size is checked against the declared shape before the pixels are decoded.
* ``"retrieval"`` and ``"ascending"``: a keyframe's retrieval features or its ASMK
  aggregate, and ascending word ids (:mod:`~.codec_retrieval`).
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
from como3r.transport.codec_arrays import TAG, Budget, exact_keys, zstd
from como3r.transport.codec_planes import (
    CODED,
    ZSTD_LEVEL,
    as_kind,
    as_numpy,
    coded_header,
    float32_or_none,
    inflate,
    kind_of,
    pack_ints,
    pack_plane,
    pack_steps,
    unpack_ints,
    unpack_plane,
    unpack_steps,
)
from como3r.transport.codec_registry import CHECKS, REGISTRY, resolve
from como3r.transport.codec_retrieval import (
    ascending_decode,
    ascending_encode,
    retrieval_decode,
    retrieval_encode,
)
from como3r.transport.codec_reuse import recall, remember

LOG_RANGE_BITS = 8
"""A point's range travels as ``round(log2(range) * 2^LOG_RANGE_BITS)``: its quantisation
error (uniform, RMS ``2^-8 / sqrt(12)`` in ``log2``: 7.8e-4 of the range) adds 2.4 % to the
variance of the simulated prior's per-pixel range noise (0.5 %), for 1 bit per pixel less
than ``2^-9`` steps (about 21 kB of a 512x384 pointmap). Merged ATE of
``tests/transport/test_lossy_run.py``'s scene lossy against exact: +0.018 % (``2^-7``
steps: +0.94 %)."""

OCT_BITS = 12
"""A ray's octahedral coordinates (in [-1, 1]) travel as ``round(u * 2^OCT_BITS)``: a
direction within 3.6e-4 rad (0.14 px at 512 px across 75 deg), a quarter of the range's
quantisation. Uncalibrated (no pinhole to code the rays against: ``tracking.self_calibration
=false``) the directions are a third of a pointmap's bytes; ``2^-14`` steps cost 11 kB more per
pointmap and as much per refresh at 512x384 (``benchmarks/message_sizes.py``: 164.2 and
217.2 kB against 153.0 and 206.1). Merged ATE of
``tests/transport/test_lossy_run.py``'s scene lossy against exact, uncalibrated: -0.30 %
(``2^-14``: -0.22 %), self-calibrated -0.11 % (-0.07 %)."""

LEGACY_OCT_BITS = 14
"""The direction step of pointmaps coded without ``oct_bits`` in their body (packets and
session stores written before it was: store formats 5 and 6)."""

POINTMAP_RELATIVE_ERROR = 1.72e-3
"""Bound on ``|X' - X| / |X|`` of a pointmap after the ``"pointmap"`` coding: the range's
quantisation (``2^(2^-9) - 1 = 1.36e-3``) plus the direction's (at most 3.6e-4 rad: half a
step of 2^-12 across the octahedral map's largest stretch)."""

CONFIDENCE_BITS = 0
"""A confidence travels as ``round(log2(C) * 2^CONFIDENCE_BITS)``: in whole powers of two.
Measured (``tests/transport/test_lossy_run.py``'s scene, merged ATE lossy against exact,
with ranges in ``2^-8`` and match ``q`` in ``2^-1`` steps): +0.018 % with confidences in
``2^-1`` steps and in ``2^0`` steps alike (+0.035 % with everything in the earlier, finer
steps); ``2^0`` steps take 23 kB off a 512x384 keyframe's confidences and as much off its
refresh."""

CONFIDENCE_RELATIVE_ERROR = 2 ** (2.0 ** -(CONFIDENCE_BITS + 1)) - 1
"""Bound on ``|C' - C| / C`` after the ``"confidence"`` coding (41 %: a weight of the global
BA's and the depth refinement's residuals; MASt3R's confidence varies by far more between two views of the same point, the simulated
prior's by a factor of about 2 between neighbouring pixels)."""

MATCH_Q_BITS = 1
"""A valid match's confidence ``q`` travels as ``round(log2(q) * 2^MATCH_Q_BITS)``, within
``2^(2^-2) - 1 = 19 %`` relative (it weighs the match's residual, C-Eq. 17). The global BA
is more sensitive to it than to the confidences: in whole powers of two (41 %) the merged
ATE of ``tests/transport/test_lossy_run.py``'s scene moved by +1.25 % (+0.018 % in
``2^-1`` steps)."""

INTER_MATCH_Q_BITS = 3
"""The ``"inter_matches"`` coding's ``q`` steps: ``2^-3`` in ``log2``, within
``2^(2^-4) - 1 = 4.4 %`` relative. An inter-agent edge's matches (a verification's, which
the session store keeps coded and the coordinator goes on from) weigh more than a
sequential edge's: on ``tests/transport/test_lossy_run.py``'s scene the merged ATE moved
by +1.16 % with their ``q`` in :data:`MATCH_Q_BITS` steps, by -0.01 % in these (0.00 %
with every valid index coded and ``q`` exact)."""

WEBP_METHOD = 3
"""WebP's lossless effort (0: fastest). On 4 synthetic 512x384 keyframes (CPU time of a
loaded core): method 0 211 kB in 14 ms, 2 190 kB in 62 ms, 3 185 kB in 79 ms, 6 182 kB in
315 ms; earlier, PNG (OpenCV, level 3) 267 kB in 58 ms, the byte planes with Zstandard
400 kB."""

WEBP_EFFORT = 50
"""WebP's lossless ``quality`` (the encoder's effort at the chosen method)."""

WEBP_MAX_SIDE = 16383
"""WebP's largest image side; a larger image travels uncoded."""

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


def _pinhole_fit(X: np.ndarray) -> list[float] | None:
    """``[a, b, c, d]`` of the pinhole rays ``(a u + b, c v + d, 1)`` closest (least squares
    in ``x/z`` and ``y/z``) to the float64 ``(H, W, 3)`` points ``X`` in front of the camera
    (pixel ``(v, u)``: row, column), or None where fewer than half are."""
    front = X[..., 2] > 0
    if front.sum() * 2 < front.size or X.shape[0] < 2 or X.shape[1] < 2:
        return None
    v, u = np.nonzero(front)
    if u.min() == u.max() or v.min() == v.max():  # one column or row: no line to fit
        return None
    z = X[..., 2][front]
    slopes = (X[..., 0][front] / z, X[..., 1][front] / z)
    if not (np.isfinite(slopes[0]).all() and np.isfinite(slopes[1]).all()):
        return None
    params = [*_line(u.astype(np.float64), slopes[0]), *_line(v.astype(np.float64), slopes[1])]
    return params if all(np.isfinite(params)) and max(map(abs, params)) < 1e6 else None


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Slope and intercept of the least-squares line through ``(x, y)`` (``x`` not all
    equal), in closed form: numpy's ``polyfit`` took 6 times as long (34 against 5 ms on a
    512x384 pointmap), a sixth of the pointmap's encode. Only the coded bytes depend on the
    fit: a decode adds the pinhole's codes back to the residual codes it subtracted."""
    dx = x - x.mean()
    slope = float(dx @ (y - y.mean()) / (dx @ dx))
    return slope, float(y.mean() - slope * x.mean())


def _pinhole_codes(
    params: list[float], shape: tuple[int, int], bits: int = OCT_BITS
) -> tuple[np.ndarray, np.ndarray]:
    """The quantised octahedral coordinates of the pinhole rays ``params``
    (:func:`_pinhole_fit`) on an ``(H, W)`` grid: two int64 ``(H, W)`` planes. Elementwise
    IEEE arithmetic only (no reductions), so that sender and receiver compute the same codes;
    the octahedral map of a ray with ``z = 1`` is its ``(x, y) / (|x| + |y| + 1)``, within
    [-1, 1] for any finite parameters."""
    a, b, c, d = params
    x = np.broadcast_to(a * np.arange(shape[1], dtype=np.float64) + b, shape)
    y = np.broadcast_to((c * np.arange(shape[0], dtype=np.float64) + d)[:, None], shape)
    l1 = np.abs(x) + np.abs(y) + 1.0
    return (
        np.rint(x / l1 * 2**bits).astype(np.int64),
        np.rint(y / l1 * 2**bits).astype(np.int64),
    )


def _pointmap_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    X = float32_or_none(value, 3, 3)
    if X is None:
        return None
    X64 = X.astype(np.float64)
    r = np.linalg.norm(X64, axis=-1)
    if not (np.isfinite(X64).all() and (r > 1e-30).all()):
        return None
    oct_ = np.rint(_octahedral(X64 / r[..., None]) * 2**OCT_BITS).astype(np.int64)
    directions = [oct_[..., 0], oct_[..., 1]]
    # rays close to a pinhole camera's (a calibrated or self-calibrated keyframe's are on
    # its rays exactly): their codes less the fitted pinhole's are mostly 0
    pinhole = _pinhole_fit(X64)
    planes = [pack_plane(p) for p in directions]
    if pinhole is not None:
        predicted = _pinhole_codes(pinhole, (X.shape[0], X.shape[1]))
        less = [pack_plane(p - q) for p, q in zip(directions, predicted)]
        if all(p is not None for p in less) and _size(less) < _size(planes):
            planes = less
        else:
            pinhole = None
    planes.insert(0, pack_plane(np.rint(np.log2(r) * 2**LOG_RANGE_BITS).astype(np.int64)))
    if any(p is None for p in planes):
        return None
    return {
        "kind": kind_of(value),
        "shape": list(X.shape),
        "planes": planes,
        "pinhole": pinhole,
        "oct_bits": OCT_BITS,
    }


def _size(planes: list[dict[str, Any] | None]) -> float:
    """Bytes of packed planes (infinite where one did not pack)."""
    return sum(float("inf") if p is None else len(p["zstd"]) for p in planes)


def _pointmap_decode(body: dict, path: str, budget: Budget) -> Any:
    # stores of formats 5 and 6 hold pointmaps coded before their step was written down
    stated = ("oct_bits",) if isinstance(body, dict) and "oct_bits" in body else ()
    kind, shape = coded_header(body, ("planes", "pinhole", *stated), 3, path)
    planes, pinhole = body["planes"], body["pinhole"]
    bits = body.get("oct_bits", LEGACY_OCT_BITS)
    if not (isinstance(bits, int) and not isinstance(bits, bool) and 8 <= bits <= 20):
        raise MessageError(f"{path}: coded pointmap's direction step 2^-{bits!r}")
    if shape[2] != 3 or not (isinstance(planes, list) and len(planes) == 3):
        raise MessageError(f"{path}: a coded pointmap is (H, W, 3) in three planes")
    log_r, u, v = (unpack_plane(p, (shape[0], shape[1]), path, budget) for p in planes)
    if pinhole is not None:
        if not (
            isinstance(pinhole, list)
            and len(pinhole) == 4
            and all(isinstance(x, float) and abs(x) < 1e6 for x in pinhole)
        ):
            raise MessageError(f"{path}: coded pointmap's pinhole is not 4 finite numbers")
        pu, pv = _pinhole_codes(pinhole, (shape[0], shape[1]), bits)
        u, v = u + pu, v + pv
    if (
        max(np.abs(u).max(initial=0), np.abs(v).max(initial=0)) > 2**bits
        or np.abs(log_r).max(initial=0) > 120 * 2**LOG_RANGE_BITS
    ):
        raise MessageError(f"{path}: coded pointmap values out of range")
    r = np.exp2(log_r / 2**LOG_RANGE_BITS)
    direction = _from_octahedral(np.stack([u, v], -1) / 2**bits)
    return as_kind((direction * r[..., None]).astype(np.float32), kind)


# ------------------------------------------------------------------ confidence


def _log_plane(values: np.ndarray, bits: int) -> np.ndarray:
    return np.rint(np.log2(values.astype(np.float64)) * 2**bits).astype(np.int64)


def _confidence_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    C = float32_or_none(value, 2)
    if C is None or not (np.isfinite(C).all() and (C > 0).all()):
        return None
    plane = pack_plane(_log_plane(C, CONFIDENCE_BITS))
    return (
        None if plane is None else {"kind": kind_of(value), "shape": list(C.shape), "plane": plane}
    )


def _confidence_decode(body: dict, path: str, budget: Budget) -> Any:
    kind, shape = coded_header(body, ("plane",), 2, path)
    q = unpack_plane(body["plane"], (shape[0], shape[1]), path, budget)
    if np.abs(q).max(initial=0) > 120 * 2**CONFIDENCE_BITS:
        raise MessageError(f"{path}: coded confidence values out of range")
    return as_kind(np.exp2(q / 2**CONFIDENCE_BITS).astype(np.float32), kind)


# ------------------------------------------------------------------ matches


def _matches_encode(
    value: Any, owner: Any = None, q_bits: int = MATCH_Q_BITS
) -> dict[str, Any] | None:
    names = ("idx", "valid", "q")
    if type(value).__name__ != "DirectedMatches" or not all(
        isinstance(getattr(value, n, None), Tensor) for n in names
    ):
        return None
    idx, valid, q = (as_numpy(getattr(value, n)) for n in names)
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
    steps = pack_steps(np.diff(columns, prepend=np.int64(0)), np.diff(rows, prepend=np.int64(0)))
    # q as it is or as steps, whichever is smaller (noisy: often as it is)
    log_q = _log_plane(kept, q_bits)
    as_is, as_steps = pack_ints(log_q), pack_ints(np.diff(log_q, prepend=np.int64(0)))
    if steps is None or as_is is None or as_steps is None:
        return None
    q_steps = len(as_steps["zstd"]) < len(as_is["zstd"])
    return {
        "count": int(idx.shape[0]),
        "width": width,
        "valid": zstd.compress(np.packbits(valid).tobytes(), level=ZSTD_LEVEL),
        "steps": steps,
        "q": as_steps if q_steps else as_is,
        "q_steps": q_steps,
        **({} if q_bits == MATCH_Q_BITS else {"q_bits": q_bits}),
    }


def _inter_matches_encode(value: Any, owner: Any = None) -> dict[str, Any] | None:
    return _matches_encode(value, owner, INTER_MATCH_Q_BITS)


def _matches_decode(body: dict, path: str, budget: Budget) -> Any:
    fine = body.get("coding") == "inter_matches"
    keys = ("coding", "count", "width", "valid", "steps", "q", "q_steps")
    exact_keys(body, (*keys, "q_bits") if fine else keys, path)
    q_bits = body["q_bits"] if fine else MATCH_Q_BITS
    if q_bits not in range(9) or isinstance(q_bits, bool):
        raise MessageError(f"{path}: coded matches' q_bits {q_bits!r} not in 0..8")
    count, width, bits = body["count"], body["width"], body["valid"]
    if not isinstance(body["q_steps"], bool):
        raise MessageError(f"{path}: coded matches' q_steps is not a bool")
    for name, n in (("count", count), ("width", width)):
        if not (isinstance(n, int) and not isinstance(n, bool) and 0 <= n < 2**32):
            raise MessageError(f"{path}: coded matches {name} {n!r}")
    if width < 1 or count % width:
        raise MessageError(f"{path}: coded matches of {count} pixels in rows of {width}")
    if not isinstance(bits, bytes):
        raise MessageError(f"{path}: coded matches' valid mask is not bytes")
    size = (count + 7) // 8
    budget.take(size, path)
    mask = inflate(bits, size, path, "coded valid mask", f"{size} bytes")
    valid = np.unpackbits(np.frombuffer(mask, np.uint8), count=count).astype(bool)
    pixels = np.flatnonzero(valid)
    columns, rows = (
        np.cumsum(s) for s in unpack_steps(body["steps"], len(pixels), f"{path}.steps", budget)
    )
    log_q = unpack_ints(body["q"], len(pixels), f"{path}.q", budget)
    log_q = np.cumsum(log_q) if body["q_steps"] else log_q
    idx = np.arange(count, dtype=np.int64)
    idx[pixels] += rows * width + columns
    if np.abs(log_q).max(initial=0) > 120 * 2**q_bits:
        raise MessageError(f"{path}: coded match confidences out of range")
    q = np.zeros(count, np.float32)
    q[pixels] = np.exp2(log_q / 2**q_bits)
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
    kind, shape = coded_header(body, ("webp",), 3, path)
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


# ------------------------------------------------------------------ registry

Encoder = Callable[[Any, Any], "dict[str, Any] | None"]
Decoder = Callable[[dict, str, Budget], Any]

CODINGS: dict[str, tuple[Encoder, Decoder]] = {
    "pointmap": (_pointmap_encode, _pointmap_decode),
    "confidence": (_confidence_encode, _confidence_decode),
    "matches": (_matches_encode, _matches_decode),
    "inter_matches": (_inter_matches_encode, _matches_decode),
    "image": (_image_encode, _image_decode),
    "retrieval": (retrieval_encode, retrieval_decode),
    "ascending": (ascending_encode, ascending_decode),
}
"""Coding name -> (encoder: value -> wire body or None where it does not fit, decoder)."""


def coded_to_wire(coding: str, value: Any, owner: Any = None) -> dict[str, Any] | None:
    """``value`` (a field of ``owner``) in ``coding`` as its wire map, or None where it does
    not fit the coding; inside :func:`~.codec_reuse.reusing`, the map it was decoded from
    where it is unchanged since."""
    wire = recall(coding, value)
    if wire is not None:
        return wire
    body = CODINGS[coding][0](value, owner)
    return None if body is None else {TAG: CODED, "coding": coding, **body}


def coded_from_wire(value: dict, path: str, budget: Budget) -> Any:
    """The value of a coded wire map (:class:`MessageError` where it is malformed)."""
    coding = value.get("coding")
    if not isinstance(coding, str) or coding not in CODINGS:
        raise MessageError(f"{path}: unknown coding {coding!r}")
    try:
        decoded = CODINGS[coding][1](value, path, budget)
    except (ValueError, TypeError, OverflowError) as exc:
        raise MessageError(f"{path}: malformed {coding} coding: {exc}") from None
    remember(decoded, coding, value)
    return decoded
