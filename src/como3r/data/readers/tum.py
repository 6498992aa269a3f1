"""TUM RGB-D sequences, read as published (Sturm et al., "A Benchmark for the Evaluation of
RGB-D SLAM Systems", IROS 2012).

A sequence folder (``rgbd_dataset_freiburg1_desk/`` as extracted from its ``.tgz``) holds
``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines, ``#`` comments), ``rgb/`` and
``depth/`` (640x480 PNGs) and ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, the
colour camera's optical centre and orientation in the motion-capture world frame, i.e.
camera-to-world as :func:`como3r.io.tum.read_tum` reads it). What this reader takes, after
the dataset's "File Formats" page
(https://vision.in.tum.de/data/datasets/rgbd-dataset/file_formats):

* frames: the ``rgb.txt`` images, each paired with the nearest unused ``depth.txt`` image
  by TUM's ``associate.py`` (candidate pairs closer than ``max_difference`` = 0.02 s, taken
  greedily by time difference, each image used once). The Kinect's two streams are not
  synchronised and drop frames, so with ``depth.txt`` present the frames are the associated
  pairs (rgb images without a depth partner are left out, with a warning); without
  ``depth.txt`` every ``rgb.txt`` image is a frame. Timestamps are the rgb ones.
* ``associations.txt`` (optional; not in the archives, but many users write one with
  ``associate.py rgb.txt depth.txt > associations.txt``, as ORB-SLAM's TUM examples ask,
  and some copies of the dataset carry one): lines ``rgb_timestamp rgb_file
  depth_timestamp depth_file`` (or depth first, told by the files' ``depth/`` folder). When
  present, its pairs are the frames, as the user associated them, and ``rgb.txt`` /
  ``depth.txt`` are not needed.
* depth: 16-bit PNG "scaled by a factor of 5000" (5000 = 1 m), 0 = no data; registered to
  the colour image by the OpenNI driver (1:1 pixel correspondence).
* ground truth: ``groundtruth.txt`` (optional: the benchmark's validation sequences publish
  none), the 100 Hz motion capture as published; each frame's pose is interpolated at its
  timestamp (:mod:`como3r.data.poses`: between samples at most 0.1 s apart; the capture
  usually starts a fraction of a second after the camera, and drops samples now and then:
  such frames have no pose).
* intrinsics: ``calib.txt`` (``fx fy cx cy``, the agent layout's file) in the folder if the
  user puts one there; otherwise the colour camera's calibration picked from the folder
  name (``rgbd_dataset_freiburg1_*`` etc.) as MASt3R-SLAM's ``TUMDataset`` does, values of
  the dataset's "Intrinsic Camera Calibration of the Kinect" page
  (https://vision.in.tum.de/data/datasets/rgbd-dataset/intrinsic_calibration): fr1 517.3
  516.5 318.6 255.3, fr2 520.9 521.0 325.1 249.7, fr3 535.4 539.2 320.1 247.6 (fx fy cx
  cy). fr1 and fr2 also publish radial-tangential distortion (``d0 .. d4``, OpenCV's ``k1 k2
  p1 p2 k3``): with their name-picked intrinsics, colour and depth are undistorted as they
  are read (:mod:`.undistort`), as MASt3R-SLAM's calibrated TUM runs undistort; fr3's
  images are published undistorted. A user's ``calib.txt`` has no distortion terms: its
  frames are read as they are. A folder name without freiburg1/2/3 and without
  ``calib.txt`` is uncalibrated (``--prior simulated`` and ``--calib`` then need a
  ``calib.txt``).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from como3r.data.agent_input import AgentInput
from como3r.data.input_files import check_map_header, common_image_size, parse_timestamp, read_calib
from como3r.data.readers.undistort import UndistortedInput
from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum

logger = logging.getLogger(__name__)

EXPECTED = (
    "rgb.txt (with rgb/) or associations.txt, optionally depth.txt (with depth/) and "
    "groundtruth.txt"
)
ASSOCIATIONS = "associations.txt"
#: TUM associate.py's default ``--max_difference`` [s]
MAX_DIFFERENCE = 0.02
#: "The depth images are scaled by a factor of 5000"; 0 means missing value
DEPTH_UNITS_PER_METRE = 5000.0
#: colour-camera ``(fx, fy, cx, cy)`` of the Kinects of freiburg 1, 2 and 3 (module docstring)
INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
}
#: their radial-tangential distortion ``(k1, k2, p1, p2, k3)`` (``d0 .. d4`` of the same page)
DISTORTION = {
    1: (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    2: (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    3: (0.0, 0.0, 0.0, 0.0, 0.0),
}


def matches(path: Path) -> bool:
    """A folder holding ``rgb.txt`` or ``associations.txt`` is a TUM sequence."""
    return (path / "rgb.txt").is_file() or (path / ASSOCIATIONS).is_file()


def camera_from_name(
    name: str,
) -> tuple[tuple[float, float, float, float] | None, tuple[float, ...]]:
    """The freiburg 1/2/3 colour intrinsics and distortion for a folder named
    ``..freiburgK..``; ``(None, ())`` for another name."""
    match = re.search(r"freiburg([123])(?!\d)", name)
    if match is None:
        return None, ()
    kinect = int(match.group(1))
    return INTRINSICS[kinect], DISTORTION[kinect]


def read_file_list(path: Path) -> list[tuple[int, float, str]]:
    """``(line number, timestamp, file name)`` of each entry of ``rgb.txt`` / ``depth.txt``.

    Raises:
        InputError: an unreadable file, a malformed line, non-increasing timestamps or no
            entries; the message names the line.
    """
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read file list ({exc})") from None
    rows: list[tuple[int, float, str]] = []
    for line_no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].replace(",", " ").replace("\t", " ").strip()
        if not text:
            continue
        parts = text.split()
        if len(parts) != 2:
            raise InputError(f"{path}:{line_no}: expected 'timestamp filename', got {text!r}")
        stamp = parse_timestamp(parts[0], path, line_no)
        if rows and stamp <= rows[-1][1]:
            raise InputError(
                f"{path}:{line_no}: timestamps are not strictly increasing "
                f"({rows[-1][1]!r} then {stamp!r})"
            )
        rows.append((line_no, stamp, parts[1]))
    if not rows:
        raise InputError(f"{path}: no 'timestamp filename' entries")
    return rows


def associate(
    first: np.ndarray, second: np.ndarray, max_difference: float = MAX_DIFFERENCE
) -> list[tuple[int, int]]:
    """TUM ``associate.py``: one-to-one pairs of two timestamp lists.

    Every pair closer than ``max_difference`` is a candidate; candidates are taken in order
    of increasing time difference, each index of either list at most once.

    Args:
        first: ``(N,)`` increasing timestamps; second: ``(M,)`` increasing timestamps.

    Returns:
        ``(i, j)`` index pairs sorted by ``i``.
    """
    candidates = []
    lo = np.searchsorted(second, first - max_difference, side="left")
    hi = np.searchsorted(second, first + max_difference, side="right")
    for i in range(len(first)):
        for j in range(int(lo[i]), int(hi[i])):
            difference = abs(float(first[i]) - float(second[j]))
            if difference < max_difference:
                candidates.append((difference, i, j))
    candidates.sort()
    used_first, used_second, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def open_sequence(path: Path, fps: float) -> AgentInput:
    """Open a TUM RGB-D sequence folder (module docstring); ``fps`` is recorded only.

    Raises:
        InputError: a malformed list, a listed file that is missing or unreadable, images of
            different sizes, depth that is not 16-bit or not the image size, no rgb image
            with a depth partner, or a malformed ``groundtruth.txt`` / ``calib.txt``.
    """
    if (path / ASSOCIATIONS).is_file():
        rgb, depth_rows = read_associations(path / ASSOCIATIONS)
        _check_listed(path, path / ASSOCIATIONS, rgb)
        _check_listed(path, path / ASSOCIATIONS, depth_rows)
        frames = list(range(len(rgb)))
        depth_files = [path / name for _, _, name in depth_rows]
    else:
        rgb, frames, depth_files = _associate_lists(path)
    image_paths = tuple(path / rgb[i][2] for i in frames)
    image_size = common_image_size(image_paths)
    for depth_file in depth_files:
        check_map_header(depth_file, image_size, "depth")
    timestamps = np.array([rgb[i][1] for i in frames], dtype=np.float64)

    groundtruth = (
        read_tum(path / "groundtruth.txt") if (path / "groundtruth.txt").is_file() else None
    )
    calib_file = path / "calib.txt"
    name = path.resolve().name
    calib, distortion = (
        (read_calib(calib_file), ()) if calib_file.is_file() else camera_from_name(name)
    )
    if calib is None:
        logger.info("%s: no calib.txt and no freiburg1/2/3 in the folder name: uncalibrated", path)
    return UndistortedInput(
        root=path,
        name=name,
        num_frames=len(frames),
        image_size=image_size,
        timestamps=timestamps,
        calib=calib,
        groundtruth=groundtruth,
        odometry=None,
        has_depth=bool(depth_files),
        has_surface=False,
        fps=float(fps),
        stems=tuple(p.stem for p in image_paths),
        image_paths=image_paths,
        video=None,
        depth_paths=tuple(depth_files),
        surface_paths=(),
        format="tum",
        depth_units_per_metre=DEPTH_UNITS_PER_METRE,
        depth_invalid=(0,),
        distortion=distortion,
    )


def read_associations(
    path: Path,
) -> tuple[list[tuple[int, float, str]], list[tuple[int, float, str]]]:
    """The rgb and depth entries ``(line number, timestamp, file name)`` of an
    ``associations.txt``, pair by pair in rgb-time order.

    Raises:
        InputError: an unreadable file, a line that is not ``timestamp file timestamp
            file``, non-increasing rgb timestamps or no entries; the message names the line.
    """
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read associations ({exc})") from None
    rgb: list[tuple[int, float, str]] = []
    depth: list[tuple[int, float, str]] = []
    for line_no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].replace(",", " ").replace("\t", " ").strip()
        if not text:
            continue
        parts = text.split()
        if len(parts) != 4:
            raise InputError(
                f"{path}:{line_no}: expected 'rgb_timestamp rgb_file "
                f"depth_timestamp depth_file', got {text!r}"
            )
        first = (line_no, parse_timestamp(parts[0], path, line_no), parts[1])
        second = (line_no, parse_timestamp(parts[2], path, line_no), parts[3])
        if parts[1].startswith("depth") and not parts[3].startswith("depth"):
            first, second = second, first  # written as associate.py depth.txt rgb.txt
        if rgb and first[1] <= rgb[-1][1]:
            raise InputError(
                f"{path}:{line_no}: rgb timestamps are not strictly increasing "
                f"({rgb[-1][1]!r} then {first[1]!r})"
            )
        rgb.append(first)
        depth.append(second)
    if not rgb:
        raise InputError(f"{path}: no 'rgb_timestamp rgb_file depth_timestamp depth_file' entries")
    return rgb, depth


def _associate_lists(path: Path) -> tuple[list[tuple[int, float, str]], list[int], list[Path]]:
    """``rgb.txt``'s entries, the indices of those that are frames and their depth files
    (empty without ``depth.txt``), paired as TUM's ``associate.py`` pairs them."""
    rgb_list = path / "rgb.txt"
    rgb = read_file_list(rgb_list)
    _check_listed(path, rgb_list, rgb)
    frames = list(range(len(rgb)))
    depth_files: list[Path] = []
    depth_list = path / "depth.txt"
    if depth_list.is_file():
        depth = read_file_list(depth_list)
        pairs = associate(np.array([s for _, s, _ in rgb]), np.array([s for _, s, _ in depth]))
        if not pairs:
            raise InputError(
                f"{depth_list}: no depth image within {MAX_DIFFERENCE} s of any "
                f"image of {rgb_list.name}"
            )
        if len(pairs) < len(rgb):
            logger.warning(
                "%s: %d of %d rgb images have no depth image within %g s "
                "(TUM associate.py); they are left out",
                path,
                len(rgb) - len(pairs),
                len(rgb),
                MAX_DIFFERENCE,
            )
        frames = [i for i, _ in pairs]
        depth_rows = [depth[j] for _, j in pairs]
        _check_listed(path, depth_list, depth_rows)
        depth_files = [path / name for _, _, name in depth_rows]
    return rgb, frames, depth_files


def ground_truth(path: Path) -> tuple[Path, Trajectory]:
    """``groundtruth.txt`` of a TUM sequence folder, as published (100 Hz motion capture)."""
    gt_file = path / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(
            f"{path}: TUM sequence has no groundtruth.txt (the benchmark's "
            "validation sequences publish none)"
        )
    return gt_file, read_tum(gt_file)


def _check_listed(path: Path, list_file: Path, rows: list[tuple[int, float, str]]) -> None:
    """Every file a list names exists (a cheap check before any header is read)."""
    for line_no, _, name in rows:
        if not (path / name).is_file():
            raise InputError(f"{path / name}: missing (listed in {list_file}:{line_no})")
