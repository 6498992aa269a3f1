"""The parsers and header checks of an input's files that every reader shares: timestamps
(as text or as image names), ``calib.txt``, image sizes and depth or surface map headers, and
the association of two timestamp series. Each failure is an :class:`InputError` naming the
file (and line).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from como3r.data.agent_input import DEPTH_PNG_MODES, load_npy, packed_member
from como3r.errors import InputError
from como3r.io.packed_arrays import SUFFIX as PACKED_SUFFIX
from como3r.io.packed_arrays import read_packed_header

_SECONDS_NAME = re.compile(r"[1-9]\d{8,9}(\.\d+)?")


_NANOSECONDS_NAME = re.compile(r"[1-9]\d{17,18}")


def timestamps_from_names(stems: tuple[str, ...], folder: Path) -> np.ndarray | None:
    """``(N,)`` float64 seconds when every image name is a Unix timestamp, else None.

    A name of 9-10 digits (not starting with 0) with an optional fraction is seconds (TUM:
    ``1305031102.175304``); one of 18-19 digits is nanoseconds (EuRoC, ROS image dumps:
    ``1403636579763555584``). Zero-padded frame numbers (``000001``) are neither. All names
    must be of one kind.

    Raises:
        InputError: the names are timestamps but two are equal (sorted by name, they must
            increase strictly).
    """
    if not stems:
        return None
    if all(_SECONDS_NAME.fullmatch(s) for s in stems):
        timestamps = np.array([float(s) for s in stems], dtype=np.float64)
    elif all(_NANOSECONDS_NAME.fullmatch(s) for s in stems):
        timestamps = np.array([int(s) for s in stems], dtype=np.float64) * 1e-9
    else:
        return None
    order = np.argsort(timestamps, kind="stable")
    timestamps = timestamps[order]
    repeated = np.flatnonzero(np.diff(timestamps) <= 0)
    if repeated.size:
        first = [stems[order[k]] for k in (repeated[0], repeated[0] + 1)]
        raise InputError(
            f"{folder}: images {first[0]} and {first[1]} are named by timestamp "
            "but name the same instant"
        )
    if not np.array_equal(order, np.arange(len(stems))):
        raise InputError(
            f"{folder}: images are named by timestamp but their names do not sort "
            "in time (pad the names to one number of digits, or add timestamps.txt)"
        )
    return timestamps


def associate_timestamps(stamps: np.ndarray, reference: np.ndarray, tolerance: float) -> np.ndarray:
    """Nearest reference stamp for each stamp, within ``tolerance`` seconds.

    Args:
        stamps: ``(N,)`` query timestamps.
        reference: ``(M,)`` strictly increasing timestamps, M >= 1.
        tolerance: largest accepted time difference (inclusive).

    Returns:
        ``(N,)`` int64 index into ``reference``, -1 where nothing is close enough.
    """
    after = np.searchsorted(reference, stamps)
    left = np.clip(after - 1, 0, len(reference) - 1)
    right = np.clip(after, 0, len(reference) - 1)
    nearest = np.where(
        np.abs(reference[left] - stamps) <= np.abs(reference[right] - stamps), left, right
    )
    return np.where(np.abs(reference[nearest] - stamps) <= tolerance, nearest, -1).astype(np.int64)


def read_calib(path: Path) -> tuple[float, float, float, float]:
    """``fx fy cx cy`` from the one data line of ``calib.txt`` (``#`` starts a comment)."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read calibration ({exc})") from None
    data = [(n, t) for n, line in enumerate(lines, 1) if (t := line.split("#", 1)[0].strip())]
    if len(data) != 1:
        raise InputError(f"{path}: expected one line 'fx fy cx cy', found {len(data)} lines")
    line_no, text = data[0]
    parts = text.replace(",", " ").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{path}:{line_no}: not a number in {text!r}") from None
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"{path}:{line_no}: expected 4 finite numbers 'fx fy cx cy', got {text!r}")
    fx, fy, cx, cy = values
    if fx <= 0 or fy <= 0:
        raise InputError(f"{path}:{line_no}: focal lengths must be positive, got fx={fx} fy={fy}")
    return fx, fy, cx, cy


def common_image_size(images: tuple[Path, ...]) -> tuple[int, int]:
    """``(W, H)`` shared by all images, from their headers only."""
    size = image_header(images[0], "image")[0]
    for image in images[1:]:
        other = image_header(image, "image")[0]
        if other != size:
            raise InputError(
                f"{image}: image is {other[0]}x{other[1]}, but {images[0].name} is "
                f"{size[0]}x{size[1]}; all images of an agent must have one size"
            )
    return size


def image_header(path: Path, kind: str) -> tuple[tuple[int, int], str]:
    """``((W, H), mode)`` of an image file without decoding its pixels."""
    try:
        with Image.open(path) as image:
            return image.size, image.mode
    except UnidentifiedImageError:
        raise InputError(f"{path}: cannot read {kind} (not an image in a known format)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read {kind} ({exc})") from None


def parse_timestamp(token: str, path: Path, line_no: int) -> float:
    """A finite timestamp [s] from a text file's token, or :class:`InputError` naming the
    file and line."""
    try:
        stamp = float(token)
    except ValueError:
        raise InputError(f"{path}:{line_no}: not a timestamp: {token!r}") from None
    if not math.isfinite(stamp):
        raise InputError(f"{path}:{line_no}: non-finite timestamp {token!r}")
    return stamp


def check_map_header(path: Path, image_size: tuple[int, int], kind: str) -> None:
    width, height = image_size
    if path.suffix.lower() == ".png":
        size, mode = image_header(path, f"{kind} map")
        if mode not in DEPTH_PNG_MODES:
            raise InputError(f"{path}: depth PNG must be 16-bit single channel, got mode {mode}")
        if size != image_size:
            raise InputError(
                f"{path}: {kind} map is {size[0]}x{size[1]}, images are {width}x{height}"
            )
        return
    expected = (height, width) if kind == "depth" else (height, width, 3)
    if path.suffix.lower() == PACKED_SUFFIX:
        dtype, shape = packed_member(read_packed_header(path), path, kind)
    else:
        array = load_npy(path, kind, mmap=True)
        dtype, shape = array.dtype, array.shape
    if shape != expected or dtype.kind != "f":
        raise InputError(
            f"{path}: {kind} map has shape {shape} dtype {dtype}, expected float {expected}"
        )
