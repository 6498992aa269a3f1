"""como3r's own layout (the ``agent`` format; manual: docs/inputs.md, "Agent input"): one
robot's camera stream and its optional side files.

An agent input is a folder with ``rgb/`` (images sorted by name) or a video file (the file
itself, or a folder holding exactly one video and no ``rgb/``), plus optionally:

* ``timestamps.txt``: one float per line, or ``timestamp filename`` lines as in TUM's
  ``rgb.txt`` (then the file names pair with the images by stem); otherwise the image
  names when every one is a timestamp
  (:func:`~como3r.data.input_files.timestamps_from_names`: Unix seconds such as TUM's
  ``1305031102.175304.png``, or Unix nanoseconds such as EuRoC's and ROS image dumps'
  ``1403636579763555584.png``); otherwise ``timestamp = index / fps``;
* ``groundtruth.txt`` and ``odometry.txt``: TUM trajectories (:func:`como3r.io.tum.read_tum`);
* ``calib.txt``: ``fx fy cx cy`` on one line, in pixels of the original images;
* ``depth/<stem>.png`` (16-bit, 5000 per metre as in TUM), ``depth/<stem>.npy`` (float32
  metres) or ``depth/<stem>.c3z`` (the same float32 metres compressed losslessly, array
  ``depth``: :mod:`como3r.io.packed_arrays`, as ``como3r synth`` writes them);
* ``surface/<stem>.npy`` or ``surface/<stem>.c3z`` (array ``surface``): float32
  ``(H, W, 3)`` appearance keys (texture id, s, t).

For a video the frame stems are the zero-padded indices ``000000, 000001, ...`` and the side
files live in the folder that holds the video.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from como3r.data.agent_input import IMAGE_SUFFIXES, VIDEO_SUFFIXES, AgentInput, open_capture
from como3r.data.input_files import (
    check_map_header,
    common_image_size,
    parse_timestamp,
    read_calib,
    timestamps_from_names,
)
from como3r.errors import InputError
from como3r.io.packed_arrays import SUFFIX as PACKED_SUFFIX
from como3r.io.tum import Trajectory, read_tum


def open_agent_folder(path: str | Path, fps: float = 30.0) -> AgentInput:
    """Open and validate an input in como3r's own agent layout (folder or video file);
    arguments and errors as :func:`~como3r.data.agent.open_agent`."""
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: agent input does not exist")
    folder, video = _locate_source(path)
    if video is None:
        image_paths = _list_images(folder / "rgb")
        stems = tuple(p.stem for p in image_paths)
        image_size = common_image_size(image_paths)
    else:
        num_frames, image_size, video_fps = _probe_video(video)
        image_paths = ()
        stems = tuple(f"{i:06d}" for i in range(num_frames))
        fps = video_fps or fps

    timestamps_file = folder / "timestamps.txt"
    named = None if video is not None else timestamps_from_names(stems, folder / "rgb")
    if timestamps_file.is_file():
        timestamps = _read_timestamps(timestamps_file, stems, by_name=video is None)
    elif named is not None:
        timestamps = named
    else:
        timestamps = np.arange(len(stems), dtype=np.float64) / fps

    groundtruth = _optional_trajectory(folder / "groundtruth.txt")

    depth_paths = _pair_maps(
        folder / "depth", stems, (".png", ".npy", PACKED_SUFFIX), image_size, "depth"
    )
    surface_paths = _pair_maps(
        folder / "surface", stems, (".npy", PACKED_SUFFIX), image_size, "surface"
    )
    calib_file = folder / "calib.txt"
    return AgentInput(
        root=path,
        name=video.stem if path.is_file() else path.resolve().name,
        num_frames=len(stems),
        image_size=image_size,
        timestamps=timestamps,
        calib=read_calib(calib_file) if calib_file.is_file() else None,
        groundtruth=groundtruth,
        odometry=_optional_trajectory(folder / "odometry.txt"),
        has_depth=bool(depth_paths),
        has_surface=bool(surface_paths),
        fps=float(fps),
        stems=stems,
        image_paths=image_paths,
        video=video,
        depth_paths=depth_paths,
        surface_paths=surface_paths,
    )


def _locate_source(path: Path) -> tuple[Path, Path | None]:
    """(folder holding the side files, video file or None for an rgb/ folder)."""
    if path.is_file():
        if path.suffix.lower() not in VIDEO_SUFFIXES:
            raise InputError(
                f"{path}: not a video file (expected one of {', '.join(VIDEO_SUFFIXES)}) "
                "or an agent folder"
            )
        return path.parent, path
    if (path / "rgb").is_dir():
        return path, None
    videos = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        hint = ""
        if any(p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
            hint = f" (its images belong in {path / 'rgb'}/)"
        raise InputError(f"{path}: agent folder has no rgb/ folder and no video file{hint}")
    if len(videos) > 1:
        names = ", ".join(p.name for p in videos)
        raise InputError(f"{path}: agent folder holds {len(videos)} videos ({names}); expected one")
    return path, videos[0]


def _list_images(rgb: Path) -> tuple[Path, ...]:
    images = sorted(
        (p for p in rgb.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: p.name,
    )
    if not images:
        raise InputError(f"{rgb}: no images ({', '.join(IMAGE_SUFFIXES)})")
    seen: dict[str, Path] = {}
    for image in images:
        if image.stem in seen:
            raise InputError(f"{image}: same stem as {seen[image.stem].name}; stems must be unique")
        seen[image.stem] = image
    return tuple(images)


def _probe_video(video: Path) -> tuple[int, tuple[int, int], float | None]:
    """(frame count, ``(W, H)``, container frame rate or None) of a video."""
    capture = open_capture(video)
    try:
        ok, first = capture.read()
        if not ok:
            raise InputError(f"{video}: cannot decode the first video frame")
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            # Containers without a frame count in their header: count by demuxing.
            count = 1
            while capture.grab():
                count += 1
        rate = capture.get(cv2.CAP_PROP_FPS)
    finally:
        capture.release()
    height, width = first.shape[:2]
    return count, (width, height), rate if math.isfinite(rate) and rate > 0 else None


def _read_timestamps(path: Path, stems: tuple[str, ...], by_name: bool) -> np.ndarray:
    """``(N,)`` timestamps from ``timestamps.txt``, in frame order.

    Lines are ``timestamp`` or ``timestamp filename`` (TUM ``rgb.txt``). With file names and
    an image folder, each line is paired with the image of the same stem.
    """
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read timestamps ({exc})") from None
    rows: list[tuple[int, float, str | None]] = []
    for line_no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.split()
        if len(parts) > 2:
            raise InputError(
                f"{path}:{line_no}: expected 'timestamp' or 'timestamp filename', got {text!r}"
            )
        stamp = parse_timestamp(parts[0], path, line_no)
        rows.append((line_no, stamp, parts[1] if len(parts) == 2 else None))
    if len({name is None for _, _, name in rows}) > 1:
        raise InputError(f"{path}: mixes 'timestamp' and 'timestamp filename' lines")
    if len(rows) != len(stems):
        raise InputError(f"{path}: {len(rows)} timestamps for {len(stems)} frames")
    if by_name and rows and rows[0][2] is not None:
        rows = _order_by_stem(path, rows, stems)
    stamps = np.array([stamp for _, stamp, _ in rows], dtype=np.float64)
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        bad = int(np.argmax(steps <= 0)) + 1
        raise InputError(
            f"{path}:{rows[bad][0]}: timestamps are not strictly increasing "
            f"({float(stamps[bad - 1])!r} then {float(stamps[bad])!r})"
        )
    return stamps


def _order_by_stem(
    path: Path, rows: list[tuple[int, float, str | None]], stems: tuple[str, ...]
) -> list[tuple[int, float, str | None]]:
    by_stem: dict[str, tuple[int, float, str | None]] = {}
    for row in rows:
        stem = Path(str(row[2])).stem
        if stem in by_stem:
            raise InputError(f"{path}:{row[0]}: image {row[2]!r} is listed twice")
        by_stem[stem] = row
    for stem in stems:
        if stem not in by_stem:
            raise InputError(f"{path}: no timestamp for image {stem!r}")
    return [by_stem[stem] for stem in stems]


def _optional_trajectory(path: Path) -> Trajectory | None:
    return read_tum(path) if path.is_file() else None


def _pair_maps(
    folder: Path,
    stems: tuple[str, ...],
    suffixes: tuple[str, ...],
    image_size: tuple[int, int],
    kind: str,
) -> tuple[Path, ...]:
    """One map file per frame stem from ``folder`` (empty if the folder does not exist)."""
    if not folder.is_dir():
        return ()
    by_stem: dict[str, Path] = {}
    for candidate in sorted(folder.iterdir()):
        if not (candidate.is_file() and candidate.suffix.lower() in suffixes):
            continue
        if candidate.stem in by_stem:
            first = by_stem[candidate.stem].name
            raise InputError(f"{candidate}: {kind} map given twice (also {first})")
        by_stem[candidate.stem] = candidate
    paths = []
    for stem in stems:
        if stem not in by_stem:
            expected = " or ".join(f"{stem}{s}" for s in suffixes)
            raise InputError(f"{folder / stem}: {kind} map missing for frame {stem!r} ({expected})")
        check_map_header(by_stem[stem], image_size, kind)
        paths.append(by_stem[stem])
    return tuple(paths)
