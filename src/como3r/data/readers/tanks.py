"""Tanks and Temples sequences in the layout CoMo3R-SLAM evaluates on (Knapitsch et al.,
"Tanks and Temples: Benchmarking Large-Scale Scene Reconstruction", ToG 2017; CoMo3R-SLAM
Sec. 4 and B.4 use four outdoor scenes, Barn, Caterpillar, Ignatius and Truck, as monocular
RGB streams split into per-agent frame directories, and report ATE against the ground-truth
camera trajectory).

The paper names the frame directory and the ground-truth file but not their formats; this
reader assumes (and these are assumptions, not published formats):

* ``image/``: the frames, one image per frame, named by the frame id (``000001.jpg``; any
  name ending in the id's digits, e.g. ``frame_000001.png``). Frames are read in frame-id
  order; ids need not be contiguous (an agent's sub-sequence keeps the ids of the full
  stream). As for 7-Scenes, the dataset gives no timestamps: a frame's timestamp is its id
  divided by the frame rate (``fps``, ``input.frame_rate_hz``, 30 Hz by default).
* ``gt_traj.txt`` (optional): one line per frame, ``frame_id tx ty tz qx qy qz qw``, the
  camera-to-world pose of that frame in metres (TUM's line format with the frame id in the
  timestamp's place; ``#`` comments). Its poses are stamped ``frame_id / fps`` like the
  frames, so a run's trajectory and the ground truth line up in ``como3r eval``. A frame
  whose id has no line has no ground-truth pose.
* ``calib.txt`` (optional, como3r's agent layout): ``fx fy cx cy``; without it the input is
  uncalibrated, which is how CoMo3R-SLAM runs on these scenes by default.

There is no depth, so ``--prior simulated`` does not take this layout.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from como3r.data.agent_input import AgentInput
from como3r.data.input_files import common_image_size, read_calib
from como3r.data.readers.common import data_lines, numbered_images
from como3r.errors import InputError
from como3r.io.tum import Trajectory, parse_tum_line

EXPECTED = "image/ (frames named by frame id) and gt_traj.txt (frame_id tx ty tz qx qy qz qw)"
IMAGES = "image"
GROUNDTRUTH = "gt_traj.txt"
_ID = re.compile(r".*?(\d+)")


def matches(path: Path) -> bool:
    """A folder holding ``image/`` or ``gt_traj.txt`` is a Tanks and Temples sequence."""
    return (path / IMAGES).is_dir() or (path / GROUNDTRUTH).is_file()


def open_sequence(path: Path, fps: float) -> AgentInput:
    """Open a Tanks and Temples sequence folder (module docstring).

    Raises:
        InputError: no ``image/`` or no images in it, an image name without a frame id, two
            images of one id, images of different sizes, or a malformed ``gt_traj.txt`` /
            ``calib.txt`` (file and line named).
    """
    folder = path / IMAGES
    if not folder.is_dir():
        raise InputError(f"{path}: Tanks and Temples sequence has no {IMAGES}/ folder of frames")
    images, ids = numbered_images(folder, _ID, "000001")
    timestamps = ids.astype(np.float64) / fps
    groundtruth = None
    if (path / GROUNDTRUTH).is_file():
        groundtruth = read_groundtruth(path / GROUNDTRUTH, fps)[1]
    calib_file = path / "calib.txt"
    return AgentInput(
        root=path,
        name=path.resolve().name,
        num_frames=len(images),
        image_size=common_image_size(images),
        timestamps=timestamps,
        calib=read_calib(calib_file) if calib_file.is_file() else None,
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
        format="tanks",
    )


def ground_truth(path: Path, fps: float) -> tuple[Path, Trajectory]:
    """``gt_traj.txt``, stamped frame id / ``fps``."""
    gt_file = path / GROUNDTRUTH
    if not gt_file.is_file():
        raise InputError(f"{path}: Tanks and Temples sequence has no {GROUNDTRUTH}")
    return gt_file, read_groundtruth(gt_file, fps)[1]


def read_groundtruth(path: Path, fps: float) -> tuple[np.ndarray, Trajectory]:
    """``(M,)`` int64 frame ids of a ``gt_traj.txt`` and its poses stamped id / ``fps``.

    Raises:
        InputError: a line that is not 8 numbers ``frame_id tx ty tz qx qy qz qw`` with a
            unit quaternion (TUM's line check, which calls the id a timestamp), an id that
            is not a whole number or not larger than the one before, or no lines (file and
            line named).
    """
    rows: list[list[float]] = []
    for line_no, text in data_lines(path, "ground truth: frame_id tx ty tz qx qy qz qw lines"):
        row = parse_tum_line(text, path, line_no)
        assert row is not None  # a data line
        if row[0] != round(row[0]):
            raise InputError(
                f"{path}:{line_no}: frame id {row[0]!r} is not a whole number "
                "(expected 'frame_id tx ty tz qx qy qz qw')"
            )
        if rows and row[0] <= rows[-1][0]:
            raise InputError(
                f"{path}:{line_no}: frame ids are not strictly increasing "
                f"({int(rows[-1][0])} then {int(row[0])})"
            )
        rows.append(row)
    data = np.array(rows, dtype=np.float64)
    q = data[:, 4:8] / np.linalg.norm(data[:, 4:8], axis=1, keepdims=True)
    poses = np.concatenate([data[:, 1:4], q, np.ones((len(data), 1))], axis=1)
    ids = data[:, 0].astype(np.int64)
    return ids, Trajectory(ids / fps, torch.from_numpy(poses))
