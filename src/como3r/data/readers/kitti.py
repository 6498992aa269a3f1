"""KITTI odometry sequences, read as published (Geiger et al., "Are we ready for Autonomous
Driving? The KITTI Vision Benchmark Suite", CVPR 2012; the layout and file formats are the
development kit's ``readme.txt`` of ``data_odometry_*.zip``).

The archives extract to ``dataset/sequences/XX/`` and ``dataset/poses/XX.txt`` (sequences
00-10 only); the images come in two downloads, each with ``times.txt`` and ``calib.txt``:
``data_odometry_gray.zip`` (``image_0/`` and ``image_1/``, the left and right grey cameras,
22 GB) and ``data_odometry_color.zip`` (``image_2/`` and ``image_3/``, colour, 65 GB). Many
users have only the grey one. The input is a sequence folder ``dataset/sequences/XX``;
what this reader takes:

* frames: the left camera of the download present, colour first: ``image_2/NNNNNN.png``
  (cam2), else ``image_0/NNNNNN.png`` (cam0, 8-bit grey, read as three equal channels);
  rectified, in frame-number order; frame ``k`` is the ``k``-th line of ``times.txt``
  (seconds since the sequence start), which is the frame's timestamp. A subset of the images
  may be present (frame numbers index the lines, so a folder of links to some frames keeps
  their times and poses).
* intrinsics: that camera's line of ``calib.txt``, ``P2:`` or ``P0:`` (12 numbers, the 3x4
  projection matrix ``Kc [I | tc]`` of rectified camera c): ``fx = Pc[0,0]``,
  ``fy = Pc[1,1]``, ``cx = Pc[0,2]``, ``cy = Pc[1,2]``. The images are rectified: no
  distortion.
* ground truth (optional): ``poses/XX.txt`` beside ``sequences/`` (``XX`` the sequence
  folder's name), one line per line of ``times.txt``: 12 numbers, a row-major 3x4 matrix
  that takes a point from the left grey camera's (cam0's) frame at frame ``k`` to cam0's
  frame at frame 0, the world frame. For image_0 these are the frames' poses (``t0 = 0``).
  For image_2 this reader moves each pose by the camera offset: ``t2 = K2^-1 P2[:, 3]`` is
  cam0's origin in cam2's coordinates (about ``(0.06, 0, 0)`` m: cam2 sits 6 cm left of
  cam0), hence ``T_W,cam2 = T_W,cam0 [I | -t2]``. The KITTI devkit evaluates cam0's poses
  as they are; the offset changes positions by at most the 6 cm lever arm (nothing after a
  Sim(3) alignment for a pure translation, a few centimetres while turning). Without the
  file (test sequences 11-21) the input has no ground truth and ``como3r eval`` says where
  it looked.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from como3r.data.agent_input import AgentInput
from como3r.data.input_files import common_image_size, parse_timestamp
from como3r.data.readers.common import data_lines, numbered_images, parse_numbers, rigid_poses
from como3r.errors import InputError
from como3r.io.tum import Trajectory

logger = logging.getLogger(__name__)

EXPECTED = (
    "image_2/ (colour) or image_0/ (grey) and times.txt (with calib.txt; poses in "
    "../../poses/XX.txt)"
)
#: the left cameras' image folders and their calib.txt rows, in the order they are taken
CAMERAS = (("image_2", 2), ("image_0", 0))
_NUMBER = re.compile(r"(\d+)")


def matches(path: Path) -> bool:
    """A folder holding ``times.txt`` and ``image_2/`` or ``image_0/`` is a KITTI odometry
    sequence."""
    return (path / "times.txt").is_file() and any((path / f).is_dir() for f, _ in CAMERAS)


def camera(path: Path) -> tuple[str, int]:
    """The image folder and camera number the sequence is read from: ``image_2`` (colour)
    where present, else ``image_0`` (grey); ``image_2`` when neither is (ground truth
    alone, as ``como3r eval`` reads it, is then image_2's)."""
    return next(((f, c) for f, c in CAMERAS if (path / f).is_dir()), CAMERAS[0])


def poses_file(path: Path) -> Path:
    """``dataset/poses/XX.txt`` of the sequence folder ``dataset/sequences/XX``."""
    folder = Path(os.path.abspath(path))
    return folder.parent.parent / "poses" / f"{folder.name}.txt"


def open_sequence(path: Path, fps: float) -> AgentInput:
    """Open a KITTI odometry sequence folder (module docstring); ``fps`` is recorded only.

    Raises:
        InputError: no images, an image not named by its frame number, a frame without a
            ``times.txt`` line, images of different sizes, a malformed ``times.txt``,
            ``calib.txt`` or poses file (file and line named).
    """
    folder, number = camera(path)
    images, numbers = numbered_images(path / folder, _NUMBER, "000000")
    times = read_times(path / "times.txt")
    if numbers[-1] >= len(times):
        raise InputError(
            f"{images[-1]}: frame {numbers[-1]} has no line in "
            f"{path / 'times.txt'} ({len(times)} lines)"
        )
    calib, offset = read_calib(path / "calib.txt", number)
    groundtruth = None
    gt_file = poses_file(path)
    if gt_file.is_file():
        groundtruth = camera_trajectory(gt_file, times, offset)
    else:
        logger.info("%s: no %s: no ground truth", path, gt_file)
    return AgentInput(
        root=path,
        name=Path(os.path.abspath(path)).name,
        num_frames=len(images),
        image_size=common_image_size(images),
        timestamps=times[numbers],
        calib=calib,
        groundtruth=groundtruth,
        odometry=None,
        has_depth=False,
        has_surface=False,
        fps=float(fps),
        stems=tuple(p.stem for p in images),
        image_paths=images,
        video=None,
        depth_paths=(),
        surface_paths=(),
        format="kitti",
    )


def ground_truth(path: Path) -> tuple[Path, Trajectory]:
    """``poses/XX.txt`` as the trajectory of the camera the sequence is read from
    (:func:`camera`), stamped by ``times.txt``."""
    gt_file = poses_file(path)
    if not gt_file.is_file():
        raise InputError(
            f"{path}: no ground truth for KITTI sequence "
            f"{Path(os.path.abspath(path)).name}: expected {gt_file} (KITTI "
            "publishes poses for sequences 00-10 only)"
        )
    _, offset = read_calib(path / "calib.txt", camera(path)[1])
    return gt_file, camera_trajectory(gt_file, read_times(path / "times.txt"), offset)


def read_times(path: Path) -> np.ndarray:
    """``(N,)`` float64 seconds, one per line of ``times.txt``, strictly increasing.

    Raises:
        InputError: a missing file, a line that is not one number, non-increasing times or
            no lines (file and line named).
    """
    stamps: list[float] = []
    for line_no, text in data_lines(path, "times of the KITTI sequence"):
        parts = text.split()
        if len(parts) != 1:
            raise InputError(f"{path}:{line_no}: expected one timestamp, got {len(parts)} values")
        stamp = parse_timestamp(parts[0], path, line_no)
        if stamps and stamp <= stamps[-1]:
            raise InputError(
                f"{path}:{line_no}: timestamps are not strictly increasing "
                f"({stamps[-1]!r} then {stamp!r})"
            )
        stamps.append(stamp)
    return np.array(stamps, dtype=np.float64)


def read_calib(path: Path, number: int = 2) -> tuple[tuple[float, float, float, float], np.ndarray]:
    """``((fx, fy, cx, cy), tc)`` of ``calib.txt``'s ``Pc`` line (``c = number``: 2 the
    left colour camera, 0 the left grey one); ``tc`` ``(3,)`` metres is cam0's origin in
    camera c's coordinates (module docstring; zero for cam0).

    Raises:
        InputError: a missing file, no ``Pc:`` line, or one that is not a 3x4 projection
            matrix ``K [I | t]`` (file and line named).
    """
    key = f"P{number}"
    for line_no, text in data_lines(path, "calibration of the KITTI sequence"):
        parts = text.split()
        if parts[0] != f"{key}:":
            continue
        where = f"{path}:{line_no}"
        P = parse_numbers(parts[1:], 12, where, f"{key}: 3x4 projection matrix").reshape(3, 4)
        K = P[:, :3]
        fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        if fx <= 0 or fy <= 0 or K[0, 1] != 0 or K[1, 0] != 0 or list(K[2]) != [0, 0, 1]:
            raise InputError(
                f"{where}: {key} is not a projection matrix K [I | t] with K = "
                "[[fx 0 cx] [0 fy cy] [0 0 1]], fx, fy > 0"
            )
        return (fx, fy, cx, cy), np.linalg.solve(K, P[:, 3])
    what = "colour" if number == 2 else "grey"
    raise InputError(f"{path}: no '{key}:' line (the left {what} camera's 3x4 projection matrix)")


def camera_trajectory(path: Path, times: np.ndarray, offset: np.ndarray) -> Trajectory:
    """Camera c's poses of a ``poses/XX.txt`` (cam0's), one per ``times`` entry.

    Args:
        path: the poses file. times: ``(N,)`` seconds. offset: ``(3,)`` ``tc`` of
            :func:`read_calib`.

    Raises:
        InputError: a line that is not 12 finite numbers or not rigid, or a count other
            than N (file and line named).
    """
    lines = [(n, text.split()) for n, text in data_lines(path, "poses of the KITTI sequence")]
    if len(lines) != len(times):
        raise InputError(
            f"{path}: {len(lines)} poses for {len(times)} lines of times.txt; "
            "expected one per frame"
        )
    matrices = np.stack(
        [
            parse_numbers(parts, 12, f"{path}:{line_no}", "3x4 camera-to-world matrix, row-major")
            for line_no, parts in lines
        ]
    ).reshape(-1, 3, 4)
    matrices[:, :, 3] -= matrices[:, :, :3] @ offset
    T_WC = rigid_poses(matrices, [f"{path}:{line_no}" for line_no, _ in lines])
    return Trajectory(times.copy(), T_WC)
