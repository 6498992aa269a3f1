"""EuRoC MAV sequences in the ASL folder format, read as published (Burri et al., "The EuRoC
micro aerial vehicle datasets", IJRR 2016; the layout is the dataset's "ASL dataset format":
https://projects.asl.ethz.ch/datasets/doku.php?id=kmavvisualinertialdatasets).

A sequence (``MH_01_easy/`` as extracted from ``MH_01_easy.zip``) holds ``mav0/`` with one
folder per sensor. What this reader takes (the left camera, ``cam0``, only):

* frames: ``mav0/cam0/data.csv`` (``#timestamp [ns],filename`` then ``ns,name.png`` lines),
  the images in ``mav0/cam0/data/`` (752x480 8-bit grey, made 3-channel RGB); timestamps are
  the nanoseconds of ``data.csv`` in seconds.
* intrinsics and distortion: ``mav0/cam0/sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``,
  ``camera_model: pinhole``, ``distortion_model: radial-tangential`` with
  ``distortion_coefficients: [k1, k2, p1, p2]`` (OpenCV's order; a fifth, k3, is accepted).
  Every frame is undistorted when it is read (OpenCV ``initUndistortRectifyMap`` + bilinear
  ``remap``, the same ``K`` before and after, pixels that fall outside the image black), so
  the frames are pinhole images of ``fu fv cu cv``, which is the input's calibration
  (``AgentInput.calib``; a ``calib.txt`` is not read). Other camera or distortion models
  (TUM-VI's ``equidistant``) are refused by name.
* ground truth (optional): ``mav0/state_groundtruth_estimate0/data.csv``:
  ``timestamp [ns], p_RS_R x y z [m], q_RS w x y z, ...`` (velocities and biases follow and
  are ignored), the pose of the body frame B (the IMU) in the world frame R at 200 Hz. The
  camera's pose is ``T_WC = T_WB T_BS`` with ``T_BS`` of ``cam0/sensor.yaml``: the camera's
  pose in the body frame (it maps camera coordinates to body coordinates). Each frame's pose is
  interpolated at its timestamp (:mod:`como3r.data.poses`); ``como3r eval`` reads the whole
  200 Hz camera trajectory. The Vicon / Leica raw measurements (``vicon0``,
  ``leica0``) are not read.

The path given may be the sequence folder or its ``mav0`` folder.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from como3r.data.agent_input import AgentInput
from como3r.data.input_files import common_image_size
from como3r.data.readers.common import data_lines, parse_numbers, rigid_poses
from como3r.data.readers.tum import read_file_list
from como3r.data.readers.undistort import UndistortedInput
from como3r.errors import InputError
from como3r.geometry.lie import sim3_compose
from como3r.io.tum import Trajectory

logger = logging.getLogger(__name__)

EXPECTED = "mav0/cam0/data.csv (with mav0/cam0/data/ and mav0/cam0/sensor.yaml)"
GROUNDTRUTH = Path("state_groundtruth_estimate0") / "data.csv"
#: a ground-truth quaternion whose norm is further than this from 1 is refused
QUATERNION_TOLERANCE = 1e-2
_GT_COLUMNS = "timestamp [ns], p_RS_R x y z, q_RS w x y z"


@dataclass(frozen=True)
class Camera:
    """What ``cam0/sensor.yaml`` says of the camera.

    Attributes:
        calib: ``(fu, fv, cu, cv)`` pixels.
        distortion: OpenCV radial-tangential ``(k1, k2, p1, p2[, k3])``.
        T_BS: ``(8,)`` float64 pose of the camera in the body frame (t, q_xyzw, s = 1).
        resolution: ``(W, H)`` the file states, or None.
    """

    calib: tuple[float, float, float, float]
    distortion: tuple[float, ...]
    T_BS: torch.Tensor
    resolution: tuple[int, int] | None


def locate(path: Path) -> Path | None:
    """The ``mav0`` folder of a sequence: ``path/mav0`` or ``path`` itself, or None."""
    for folder in (path / "mav0", path):
        if (folder / "cam0" / "data.csv").is_file() or (folder / GROUNDTRUTH).is_file():
            return folder
    return None


def matches(path: Path) -> bool:
    """A folder holding ``mav0/cam0/data.csv`` (or ground truth), or that ``mav0`` itself."""
    return path.is_dir() and locate(path) is not None


def open_sequence(path: Path, fps: float) -> AgentInput:
    """Open a EuRoC sequence (module docstring); ``fps`` is recorded only.

    Raises:
        InputError: no ``cam0``, a malformed ``data.csv`` / ``sensor.yaml`` / ground truth
            (file and line named), a listed image that is missing, images of different sizes
            or of another size than ``sensor.yaml`` states.
    """
    mav0 = _mav0(path)
    cam0 = mav0 / "cam0"
    listing = cam0 / "data.csv"
    if not listing.is_file():
        raise InputError(f"{path}: EuRoC sequence has no {listing.relative_to(path)}")
    rows = read_file_list(listing)
    for line_no, _, name in rows:
        if not (cam0 / "data" / name).is_file():
            raise InputError(f"{cam0 / 'data' / name}: missing (listed in {listing}:{line_no})")
    image_paths = tuple(cam0 / "data" / name for _, _, name in rows)
    image_size = common_image_size(image_paths)
    camera = read_sensor(cam0 / "sensor.yaml")
    if camera.resolution is not None and camera.resolution != image_size:
        raise InputError(
            f"{cam0 / 'sensor.yaml'}: resolution {list(camera.resolution)} but "
            f"the images are {image_size[0]}x{image_size[1]}"
        )
    timestamps = np.array([stamp for _, stamp, _ in rows], dtype=np.float64) * 1e-9
    groundtruth = None
    if (mav0 / GROUNDTRUTH).is_file():
        groundtruth = camera_trajectory(mav0 / GROUNDTRUTH, camera.T_BS)
    return UndistortedInput(
        root=path,
        name=_name(path, mav0),
        num_frames=len(rows),
        image_size=image_size,
        timestamps=timestamps,
        calib=camera.calib,
        groundtruth=groundtruth,
        odometry=None,
        has_depth=False,
        has_surface=False,
        fps=float(fps),
        stems=tuple(p.stem for p in image_paths),
        image_paths=image_paths,
        video=None,
        depth_paths=(),
        surface_paths=(),
        format="euroc",
        distortion=camera.distortion,
    )


def ground_truth(path: Path) -> tuple[Path, Trajectory]:
    """The camera trajectory ``T_WB T_BS`` of the whole 200 Hz ground-truth estimate."""
    mav0 = _mav0(path)
    gt_file = mav0 / GROUNDTRUTH
    if not gt_file.is_file():
        raise InputError(f"{path}: EuRoC sequence has no {gt_file.relative_to(path)}")
    return gt_file, camera_trajectory(gt_file, read_sensor(mav0 / "cam0" / "sensor.yaml").T_BS)


def camera_trajectory(path: Path, T_BS: torch.Tensor) -> Trajectory:
    """Poses ``T_WC = T_WB T_BS`` of a ground-truth ``data.csv`` (body poses ``T_WB``).

    Args:
        path: ``state_groundtruth_estimate0/data.csv``.
        T_BS: ``(8,)`` float64 camera pose in the body frame.

    Raises:
        InputError: a line of fewer than 8 numbers or with a quaternion not of norm 1,
            timestamps not strictly increasing, or no rows (file and line named).
    """
    numbers: list[tuple[float, np.ndarray]] = []
    for line_no, text in data_lines(path, f"EuRoC ground truth: {_GT_COLUMNS}, ..."):
        parts = [p.strip() for p in text.split(",")]
        where = f"{path}:{line_no}"
        if len(parts) < 8:
            raise InputError(
                f"{where}: expected at least 8 comma-separated numbers "
                f"({_GT_COLUMNS}), got {len(parts)}"
            )
        row = parse_numbers(parts[:8], 8, where, _GT_COLUMNS)
        stamp = int(parts[0]) if parts[0].isdigit() else row[0]
        if numbers and stamp <= numbers[-1][0]:
            raise InputError(
                f"{where}: timestamps are not strictly increasing ({numbers[-1][0]} then {stamp})"
            )
        norm = float(np.linalg.norm(row[4:8]))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise InputError(f"{where}: quaternion q_RS norm {norm:.4f} is not 1")
        numbers.append((stamp, row))
    data = np.stack([row for _, row in numbers])
    q_xyzw = data[:, [5, 6, 7, 4]] / np.linalg.norm(data[:, 4:8], axis=1, keepdims=True)
    T_WB = torch.from_numpy(np.concatenate([data[:, 1:4], q_xyzw, np.ones((len(data), 1))], axis=1))
    stamps = np.array([stamp for stamp, _ in numbers], dtype=np.float64) * 1e-9
    return Trajectory(stamps, sim3_compose(T_WB, T_BS.expand_as(T_WB)))


def read_sensor(path: Path) -> Camera:
    """The camera model of a ``cam0/sensor.yaml`` (module docstring).

    Raises:
        InputError: a missing or unparsable file, a missing key, a value of the wrong form,
            another camera or distortion model, or a ``T_BS`` that is not rigid; the message
            names the file and the key's line.
    """
    if not path.is_file():
        raise InputError(f"{path}: missing (the camera's intrinsics, distortion and T_BS)")
    try:
        text = path.read_text()
        document = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise InputError(f"{where}: not valid YAML ({getattr(exc, 'problem', exc)})") from None
    if not isinstance(document, dict):
        raise InputError(f"{path}: expected a YAML mapping of sensor fields")

    def field(key: str, required: bool = True) -> tuple[str, Any]:
        match = re.search(rf"^\s*{key}\s*:", text, re.M)
        where = f"{path}:{text.count(chr(10), 0, match.start()) + 1}" if match else str(path)
        if required and key not in document:
            raise InputError(f"{path}: no {key!r} entry")
        return where, document.get(key)

    for key, accepted in (("camera_model", "pinhole"), ("distortion_model", "radial-tangential")):
        where, value = field(key, required=False)
        if value is not None and value != accepted:
            raise InputError(f"{where}: {key} {value!r} is not supported (only {accepted})")
    where, value = field("intrinsics")
    fu, fv, cu, cv = (float(v) for v in _numbers(value, (4,), where, "intrinsics: fu fv cu cv"))
    if fu <= 0 or fv <= 0:
        raise InputError(f"{where}: focal lengths must be positive, got fu={fu} fv={fv}")
    where, value = field("distortion_coefficients")
    distortion = _numbers(value, (4, 5), where, "distortion_coefficients: k1 k2 p1 p2 [k3]")
    where, value = field("T_BS")
    data = value.get("data") if isinstance(value, dict) else value
    matrix = _numbers(data, (16,), where, "T_BS data: a 4x4 matrix").reshape(1, 4, 4)
    T_BS = rigid_poses(matrix, [f"{where}: T_BS"], "camera-to-body")[0]
    where, value = field("resolution", required=False)
    resolution = None
    if value is not None:
        width, height = _numbers(value, (2,), where, "resolution: width height")
        resolution = (int(width), int(height))
    return Camera((fu, fv, cu, cv), tuple(float(d) for d in distortion), T_BS, resolution)


def _numbers(value: Any, counts: tuple[int, ...], where: str, what: str) -> np.ndarray:
    """A YAML list of ``counts`` finite numbers (one of them) as float64."""
    tokens = [str(v) for v in value] if isinstance(value, list) else [str(value)]
    count = len(tokens) if len(tokens) in counts else counts[0]
    return parse_numbers(tokens, count, where, what)


def _mav0(path: Path) -> Path:
    mav0 = locate(path)
    if mav0 is None:
        raise InputError(f"{path}: not a EuRoC sequence: expected {EXPECTED}")
    return mav0


def _name(path: Path, mav0: Path) -> str:
    """The sequence's name: the folder holding ``mav0`` (``MH_01_easy``)."""
    folder = mav0.resolve()
    return folder.parent.name if folder.name == "mav0" else path.resolve().name
