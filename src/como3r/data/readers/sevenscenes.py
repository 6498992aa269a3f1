"""Microsoft 7-Scenes sequences, read as published (Shotton et al., "Scene Coordinate
Regression Forests for Camera Relocalization in RGB-D Images", CVPR 2013; dataset page
http://research.microsoft.com/en-us/projects/7-scenes/, not reachable from where this was
written: the layout and values below are as the shared excerpt's README
(``7scenes_redkitchen_tsdf50``) and RTAB-Map's "Benchmark SLAM" wiki page quote them).

A sequence folder (``redkitchen/seq-01/`` as extracted from ``seq-01.zip``) holds, per frame
``NNNNNN``: ``frame-NNNNNN.color.png`` (640x480 RGB; ``.color.jpg`` accepted too),
``frame-NNNNNN.depth.png`` (640x480 16-bit, millimetres, 65535 = invalid) and
``frame-NNNNNN.pose.txt`` (4x4 camera-to-world matrix, metres). What this reader takes:

* frames: every ``frame-NNNNNN.color.*`` in frame-number order. The dataset has no
  timestamps; a frame's timestamp is its frame number divided by the frame rate (``fps``,
  30 Hz by default: the Kinect's rate), as MASt3R-SLAM and CoMo3R take the frame number for
  the timestamp (MASt3R-SLAM's ``SevenScenesDataset`` uses the index itself; dividing by the
  rate only makes the unit seconds).
* depth: the ``.depth.png`` files (all or none), 1000 per metre; 0 and 65535 are invalid
  (the release uses 65535, re-encodings such as andyzeng/tsdf-fusion's excerpt use 0).
  **Depth is not registered to colour** (RTAB-Map's wiki: "The depth images are not
  registered with the RGB images"): a depth pixel and the colour pixel at the same
  coordinates may see different points (offsets up to about 10-15 px at depth edges in the
  excerpt). It is used as is, as if registered.
* ground truth: the ``.pose.txt`` files (all or none), checked to be rigid.
* intrinsics: ``calib.txt`` (``fx fy cx cy``), else ``camera-intrinsics.txt`` (a 3x3 matrix,
  as andyzeng/tsdf-fusion ships it) in the frames folder or beside it, else the dataset's
  documented 585, 585, 320, 240 (fx fy cx cy; the depth camera's values, used for colour too
  as MASt3R-SLAM does).

The path given may be the frames folder itself or a folder whose only sub-folder of frames
it is (``7scenes_redkitchen_tsdf50/rgbd-frames/``); a scene folder holding several
``seq-XX`` folders is refused with their names.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from como3r.data.agent_input import AgentInput
from como3r.data.input_files import check_map_header, common_image_size, read_calib
from como3r.data.readers.common import parse_numbers, rigid_poses
from como3r.errors import InputError
from como3r.io.tum import Trajectory

EXPECTED = "frame-NNNNNN.color.png|jpg files (with .depth.png and .pose.txt)"
#: the dataset's documented intrinsics (fx, fy, cx, cy)
DEFAULT_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
DEPTH_UNITS_PER_METRE = 1000.0
DEPTH_INVALID = (0, 65535)
_FILE = re.compile(r"frame-(\d+)\.(color\.png|color\.jpg|depth\.png|pose\.txt)", re.I)
_COLOUR = re.compile(r"frame-\d+\.color\.(png|jpg)", re.I)


def matches(path: Path, subfolders: bool = True) -> bool:
    """``path`` (or, with ``subfolders``, one of its sub-folders) holds colour frames."""
    if not path.is_dir():
        return False
    return _has_colour(path) or (subfolders and bool(_frame_folders(path)))


def locate(path: Path) -> Path:
    """The folder holding the frames: ``path`` or its only sub-folder of frames.

    Raises:
        InputError: no frames, or several sub-folders of frames (a scene folder).
    """
    if _has_colour(path):
        return path
    found = _frame_folders(path)
    if len(found) == 1:
        return found[0]
    if not found:
        raise InputError(
            f"{path}: not a 7-Scenes sequence: expected {EXPECTED} in it or in one sub-folder"
        )
    names = ", ".join(p.name for p in found[:4]) + (", ..." if len(found) > 4 else "")
    raise InputError(
        f"{path}: holds {len(found)} 7-Scenes sequences ({names}); give one of them as the input"
    )


def open_sequence(path: Path, fps: float) -> AgentInput:
    """Open a 7-Scenes sequence (module docstring).

    Raises:
        InputError: a frame number with two colour images, depth or pose files for some
            frames but not all (or without a colour image), images of different sizes,
            depth that is not 16-bit or not the image size, a malformed or non-rigid pose,
            or a malformed intrinsics file.
    """
    folder = locate(path)
    numbers, colour, depth, pose = _scan(folder)
    image_size = common_image_size(colour)
    for depth_file in depth:
        check_map_header(depth_file, image_size, "depth")
    timestamps = numbers.astype(np.float64) / fps
    groundtruth = None
    if pose:
        groundtruth = Trajectory(timestamps.copy(), read_poses(pose))
    return AgentInput(
        root=path,
        name=path.resolve().name,
        num_frames=len(numbers),
        image_size=image_size,
        timestamps=timestamps,
        calib=intrinsics(folder),
        groundtruth=groundtruth,
        odometry=None,
        has_depth=bool(depth),
        has_surface=False,
        fps=float(fps),
        stems=tuple(_stem(p) for p in colour),
        image_paths=colour,
        video=None,
        depth_paths=depth,
        surface_paths=(),
        format="7scenes",
        depth_units_per_metre=DEPTH_UNITS_PER_METRE,
        depth_invalid=DEPTH_INVALID,
    )


def ground_truth(path: Path, fps: float) -> tuple[Path, Trajectory]:
    """The ``.pose.txt`` poses of a sequence, stamped frame number / ``fps``."""
    folder = locate(path)
    numbers, _, _, pose = _scan(folder)
    if not pose:
        raise InputError(f"{folder}: 7-Scenes sequence has no frame-NNNNNN.pose.txt files")
    return folder, Trajectory(numbers.astype(np.float64) / fps, read_poses(pose))


def read_poses(files: tuple[Path, ...]) -> torch.Tensor:
    """``(N, 8)`` float64 poses ``T_WC`` (t, q_xyzw, s = 1) of 4x4 camera-to-world files.

    Raises:
        InputError: a file that is not 16 finite numbers or not a rigid transform.
    """
    return rigid_poses(np.stack([_read_matrix(f, 4) for f in files]), files)


def intrinsics(folder: Path) -> tuple[float, float, float, float]:
    """``calib.txt``, else ``camera-intrinsics.txt``, in ``folder`` or beside it, else
    :data:`DEFAULT_INTRINSICS`."""
    places = [folder, folder.parent]
    for name in ("calib.txt", "camera-intrinsics.txt"):
        for place in places:
            if (place / name).is_file():
                if name == "calib.txt":
                    return read_calib(place / name)
                return _intrinsics_matrix(place / name)
    return DEFAULT_INTRINSICS


def _intrinsics_matrix(path: Path) -> tuple[float, float, float, float]:
    K = _read_matrix(path, 3)
    if not (np.allclose(K[2], [0.0, 0.0, 1.0]) and K[1, 0] == 0 and K[0, 1] == 0):
        raise InputError(
            f"{path}: expected a 3x3 intrinsics matrix [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew)"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{path}: focal lengths must be positive")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def _read_matrix(path: Path, n: int) -> np.ndarray:
    """An ``(n, n)`` float64 matrix of whitespace-separated numbers."""
    try:
        parts = path.read_text().split()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    values = parse_numbers(parts, n * n, str(path), f"{n}x{n} matrix")
    return values.reshape(n, n)


def _scan(folder: Path) -> tuple[np.ndarray, tuple[Path, ...], tuple[Path, ...], tuple[Path, ...]]:
    """``(frame numbers, colour, depth, pose files)`` of a frames folder, in frame order;
    depth and pose are empty or one per frame."""
    files: dict[str, dict[int, Path]] = {"color": {}, "depth": {}, "pose": {}}
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        match = _FILE.fullmatch(entry.name)
        if match is None or not entry.is_file():
            continue
        number, kind = int(match.group(1)), match.group(2).split(".")[0].lower()
        if number in files[kind]:
            raise InputError(
                f"{folder / entry.name}: frame {number} has two {kind} files "
                f"(also {files[kind][number].name})"
            )
        files[kind][number] = folder / entry.name
    numbers = sorted(files["color"])
    for kind, suffix in (("depth", "depth.png"), ("pose", "pose.txt")):
        extra = sorted(set(files[kind]) - set(numbers))
        if extra:
            stem = _stem(files[kind][extra[0]])
            raise InputError(
                f"{files[kind][extra[0]]}: no colour image {stem}.color.png|jpg for it"
            )
        if files[kind] and len(files[kind]) != len(numbers):
            missing = next(n for n in numbers if n not in files[kind])
            stem = _stem(files["color"][missing])
            raise InputError(
                f"{folder / f'{stem}.{suffix}'}: missing ({len(files[kind])} "
                f"{kind} files for {len(numbers)} colour images; all or none)"
            )
    return (
        np.array(numbers, dtype=np.int64),
        tuple(files["color"][n] for n in numbers),
        tuple(files["depth"][n] for n in numbers) if files["depth"] else (),
        tuple(files["pose"][n] for n in numbers) if files["pose"] else (),
    )


def _stem(path: Path) -> str:
    """``frame-NNNNNN`` of any of a frame's files."""
    return path.name.split(".", 1)[0]


def _has_colour(folder: Path) -> bool:
    try:
        with os.scandir(folder) as entries:
            return any(_COLOUR.fullmatch(e.name) for e in entries)
    except OSError:
        return False


def _frame_folders(path: Path) -> list[Path]:
    try:
        subs = sorted(p for p in path.iterdir() if p.is_dir())
    except OSError:
        return []
    return [p for p in subs if _has_colour(p)]
