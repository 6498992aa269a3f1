"""Agent inputs: one robot's camera stream and its optional side files (README,
"Agent input"), and :func:`open_agent`, which opens any supported input.

:func:`open_agent` detects the layout of the path it is given (:mod:`como3r.data.readers`):
a TUM RGB-D sequence folder, a 7-Scenes sequence folder, or como3r's own agent layout
described here; ``format`` forces one. Every reader returns the same :class:`AgentInput`.

An agent input (the ``agent`` format) is a folder with ``rgb/`` (images sorted by name) or a
video file (the file itself, or a folder holding exactly one video and no ``rgb/``), plus
optionally:

* ``timestamps.txt``: one float per line, or ``timestamp filename`` lines as in TUM's
  ``rgb.txt`` (then the file names pair with the images by stem); otherwise the image
  names when every one is a timestamp (:func:`timestamps_from_names`: Unix seconds such as
  TUM's ``1305031102.175304.png``, or Unix nanoseconds such as EuRoC's and ROS image dumps'
  ``1403636579763555584.png``); otherwise ``timestamp = index / fps``;
* ``groundtruth.txt`` and ``odometry.txt``: TUM trajectories (:func:`como3r.io.tum.read_tum`);
* ``calib.txt``: ``fx fy cx cy`` on one line, in pixels of the original images;
* ``depth/<stem>.png`` (16-bit, 5000 per metre as in TUM) or ``depth/<stem>.npy``
  (float32 metres);
* ``surface/<stem>.npy``: float32 ``(H, W, 3)`` appearance keys (texture id, s, t).

For a video the frame stems are the zero-padded indices ``000000, 000001, ...`` and the side
files live in the folder that holds the video.

:func:`open_agent` does every cheap check up front (existence, counts, all text files, image
and map headers), so a bad input fails before any SLAM work starts; pixels are decoded lazily
by :meth:`AgentInput.load_frame` and :meth:`AgentInput.frames`, which check them in turn.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from como3r.data.poses import missing_pose_summary, poses_at
from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")
DEPTH_PNG_PER_METRE = 5000.0
"""TUM RGB-D convention: a 16-bit depth PNG stores 5000 units per metre."""
DEPTH_PNG_MODES = ("I;16", "I;16B", "I;16L", "I")


@dataclass(frozen=True, eq=False)
class Frame:
    """One decoded frame of an agent input.

    Attributes:
        index: position of the frame in the agent's stream.
        timestamp: seconds.
        stem: file stem that pairs image, depth and surface maps.
        image: ``(H, W, 3)`` uint8 RGB at the original resolution.
        depth: ``(H, W)`` float32 metric depth (z) in metres, 0 = invalid; or None.
        surface: ``(H, W, 3)`` float32 appearance keys; or None.
        T_WC_gt: ``(8,)`` float64 ground-truth pose (t, q_xyzw, s = 1) at the frame's
            timestamp (:func:`como3r.data.poses.poses_at`); None when the agent has no
            ground truth or none within the gap rule.
    """

    index: int
    timestamp: float
    stem: str
    image: np.ndarray
    depth: np.ndarray | None = None
    surface: np.ndarray | None = None
    T_WC_gt: Tensor | None = None


@dataclass(frozen=True, eq=False)
class AgentInput:
    """A validated agent input; frames are decoded lazily.

    Attributes:
        root: the path the input was opened from (folder or video file).
        name: folder name, or the video's stem for a bare video file.
        num_frames: number of frames N.
        image_size: ``(W, H)`` of the original images.
        timestamps: ``(N,)`` float64 seconds, strictly increasing.
        calib: ``(fx, fy, cx, cy)`` in original pixels, or None (uncalibrated).
        groundtruth: ground-truth trajectory at its own rate (as the dataset publishes it:
            100 Hz motion capture in TUM RGB-D, one pose per frame in KITTI), or None.
        odometry: metric odometry (decentralized mode), or None.
        has_depth: every frame has a depth map.
        has_surface: every frame has a surface (appearance key) map.
        fps: frame rate used for default timestamps.
        stems: ``(N,)`` frame stems.
        image_paths: ``(N,)`` image files; empty for a video.
        video: the video file, or None for an image folder.
        depth_paths: ``(N,)`` depth files, empty without depth.
        surface_paths: ``(N,)`` surface files, empty without surface maps.
        format: the layout the input was read as (``agent``, ``tum``, ``7scenes``).
        depth_units_per_metre: what a 16-bit depth PNG stores per metre (5000 in TUM and
            the agent layout, 1000 in 7-Scenes); ``.npy`` depth is in metres.
        depth_invalid: raw 16-bit depth values that mean "no measurement" (read as 0).
        gt_poses: ``(N, 8)`` float64 ground-truth pose at each frame's timestamp, a NaN row
            for a frame without one (:func:`como3r.data.poses.poses_at`: interpolated
            between samples at most :data:`como3r.data.poses.MAX_GAP` apart); computed
            from ``groundtruth`` when not given.
    """

    root: Path
    name: str
    num_frames: int
    image_size: tuple[int, int]
    timestamps: np.ndarray
    calib: tuple[float, float, float, float] | None
    groundtruth: Trajectory | None
    odometry: Trajectory | None
    has_depth: bool
    has_surface: bool
    fps: float
    stems: tuple[str, ...] = field(repr=False)
    image_paths: tuple[Path, ...] = field(repr=False)
    video: Path | None = field(repr=False)
    depth_paths: tuple[Path, ...] = field(repr=False)
    surface_paths: tuple[Path, ...] = field(repr=False)
    format: str = "agent"
    depth_units_per_metre: float = DEPTH_PNG_PER_METRE
    depth_invalid: tuple[int, ...] = (0,)
    gt_poses: Tensor | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.gt_poses is None:  # frozen: set once, here
            object.__setattr__(self, "gt_poses", poses_at(self.timestamps, self.groundtruth))

    @property
    def has_gt_pose(self) -> np.ndarray:
        """``(N,)`` bool: the frame has a ground-truth pose (:attr:`gt_poses`)."""
        assert self.gt_poses is not None
        return torch.isfinite(self.gt_poses).all(dim=1).numpy()

    def missing_gt_warning(self) -> str | None:
        """One line counting the frames without a ground-truth pose and where they are
        (before the first sample, after the last, in gaps), or None when every frame has
        one or there is no ground truth at all."""
        has = self.has_gt_pose
        if self.groundtruth is None or has.all():
            return None
        where = missing_pose_summary(self.timestamps, self.groundtruth, has)
        return (
            f"{self.root}: {int((~has).sum())} of {self.num_frames} frames have no "
            f"ground-truth pose ({where})"
        )

    def __len__(self) -> int:
        return self.num_frames

    @property
    def frames_are_files(self) -> bool:
        """The image files hold the frames as :meth:`load_frame` returns them (up to the
        colour conversion), so a copy of a file is a copy of its frame (:mod:`.split` links
        them); False for a video, and for readers that change the pixels (EuRoC undistorts)."""
        return self.video is None

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self) -> Iterator[Frame]:
        """Every frame in order, decoded lazily (a video is decoded sequentially)."""
        if self.video is None:
            for i in range(self.num_frames):
                yield self.load_frame(i)
            return
        capture = _open_capture(self.video)
        try:
            for i in range(self.num_frames):
                ok, bgr = capture.read()
                if not ok:
                    logger.warning(
                        "%s: video ended after %d of %d frames", self.video, i, self.num_frames
                    )
                    return
                yield self._assemble(i, self._video_image(bgr, i))
        finally:
            capture.release()

    def load_frame(self, i: int) -> Frame:
        """Decode frame ``i`` (random access; a video seeks to it)."""
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range for {self.num_frames} frames")
        if self.video is None:
            image = _load_image(self.image_paths[i], self.image_size)
        else:
            capture = _open_capture(self.video)
            try:
                capture.set(cv2.CAP_PROP_POS_FRAMES, i)
                ok, bgr = capture.read()
            finally:
                capture.release()
            if not ok:
                raise InputError(f"{self.video}: cannot decode frame {i}")
            image = self._video_image(bgr, i)
        return self._assemble(i, image)

    def gt_for_frames(self) -> tuple[np.ndarray, Trajectory]:
        """Ground truth associated with frames.

        Returns:
            ``(M,)`` int64 indices of the frames that have a ground-truth pose, and a
            trajectory of those M poses stamped with the frames' timestamps (so it lines
            up with an estimated trajectory written per frame). Empty without ground truth.
        """
        frames = np.flatnonzero(self.has_gt_pose).astype(np.int64)
        assert self.gt_poses is not None
        return frames, Trajectory(
            self.timestamps[frames].copy(), self.gt_poses[torch.from_numpy(frames)].clone()
        )

    def load_depth(self, i: int) -> np.ndarray:
        """``(H, W)`` float32 metric depth of frame ``i``, 0 where invalid."""
        return _load_depth(
            self.depth_paths[i], self.image_size, self.depth_units_per_metre, self.depth_invalid
        )

    def _video_image(self, bgr: np.ndarray, i: int) -> np.ndarray:
        height, width = bgr.shape[:2]
        if (width, height) != self.image_size:
            raise InputError(
                f"{self.video}: frame {i} is {width}x{height}, the first frame is "
                f"{self.image_size[0]}x{self.image_size[1]}"
            )
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _assemble(self, i: int, image: np.ndarray) -> Frame:
        depth = self.load_depth(i) if self.has_depth else None
        surface = (
            _load_surface(self.surface_paths[i], self.image_size) if self.has_surface else None
        )
        assert self.gt_poses is not None
        row = self.gt_poses[i]
        T_WC_gt = row.clone() if bool(torch.isfinite(row).all()) else None
        return Frame(i, float(self.timestamps[i]), self.stems[i], image, depth, surface, T_WC_gt)


def open_agent(
    path: str | Path, fps: float = 30.0, format: str = "auto", topic: str = ""
) -> AgentInput:
    """Open and validate an input: an agent folder or video, a dataset sequence folder
    (TUM RGB-D, 7-Scenes, EuRoC MAV, KITTI odometry, Tanks and Temples) or a ROS log
    (:mod:`como3r.data.readers`).

    Args:
        path: agent folder, video file, dataset sequence folder, ``.bag`` file or ROS 2 bag
            folder.
        fps: frame rate for default timestamps (``index / fps``; 7-Scenes and Tanks and
            Temples: frame number / fps). A video without ``timestamps.txt`` uses its own frame
            rate when the container reports one.
        format: ``auto`` (detect from the folder's layout) or one of
            :data:`como3r.data.readers.FORMATS`.
        topic: a ROS log's image topic (:mod:`como3r.data.readers.rosbag`); empty: its
            only one. Refused for other inputs.

    Raises:
        InputError: naming the offending file, for any missing, empty, unreadable or
            inconsistent part of the input, a folder of no known layout, a ``format``
            the folder does not match, or a ``topic`` that is not a ROS log's image topic.
    """
    from como3r.data.readers import open_input  # the readers build on this module

    return open_input(path, fps=fps, format=format, topic=topic)


@contextlib.contextmanager
def quiet_reading() -> Iterator[None]:
    """Open inputs without the readers' warnings (frames left out, ...): for a second
    opening of an input whose first opening in the run says them (the command line's check,
    an agent process), so each is said once."""
    data_logger = logging.getLogger("como3r.data")
    level = data_logger.level
    data_logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        data_logger.setLevel(level)


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


def open_agent_folder(path: str | Path, fps: float = 30.0) -> AgentInput:
    """Open and validate an input in como3r's own agent layout (folder or video file);
    arguments and errors as :func:`open_agent`."""
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

    depth_paths = _pair_maps(folder / "depth", stems, (".png", ".npy"), image_size, "depth")
    surface_paths = _pair_maps(folder / "surface", stems, (".npy",), image_size, "surface")
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


def _load_image(path: Path, size: tuple[int, int]) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB."""
    try:
        with Image.open(path) as image:
            rgb = np.array(image.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot decode image ({exc})") from None
    if (rgb.shape[1], rgb.shape[0]) != size:
        raise InputError(
            f"{path}: image is {rgb.shape[1]}x{rgb.shape[0]}, expected {size[0]}x{size[1]}"
        )
    return rgb


def _open_capture(video: Path) -> cv2.VideoCapture:
    # FFmpeg would print its own diagnostics to stderr next to our one-line InputError;
    # a user who wants them sets the variable themselves.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        capture.release()
        raise InputError(f"{video}: cannot open video")
    return capture


def _probe_video(video: Path) -> tuple[int, tuple[int, int], float | None]:
    """(frame count, ``(W, H)``, container frame rate or None) of a video."""
    capture = _open_capture(video)
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
    array = _load_npy(path, kind, mmap=True)
    if array.shape != expected or array.dtype.kind != "f":
        raise InputError(
            f"{path}: {kind} map has shape {array.shape} dtype {array.dtype}, "
            f"expected float {expected}"
        )


def _load_npy(path: Path, kind: str, mmap: bool = False) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: cannot read {kind} map ({exc})") from None


def _load_depth(
    path: Path,
    image_size: tuple[int, int],
    units_per_metre: float = DEPTH_PNG_PER_METRE,
    invalid: tuple[int, ...] = (0,),
) -> np.ndarray:
    """``(H, W)`` float32 metres; 0 marks invalid pixels (non-finite values and the PNG
    values in ``invalid`` become 0)."""
    if path.suffix.lower() == ".png":
        try:
            with Image.open(path) as image:
                raw = np.asarray(image)
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot decode depth map ({exc})") from None
        depth = raw.astype(np.float32) / np.float32(units_per_metre)
        depth[np.isin(raw, invalid)] = 0.0
    else:
        depth = np.asarray(_load_npy(path, "depth"), dtype=np.float32)
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        if np.any(depth < 0):
            raise InputError(f"{path}: depth map has negative values")
    if depth.shape != (image_size[1], image_size[0]):
        raise InputError(f"{path}: depth map has shape {depth.shape}, expected {image_size[::-1]}")
    return depth


def _load_surface(path: Path, image_size: tuple[int, int]) -> np.ndarray:
    """``(H, W, 3)`` float32 appearance keys."""
    surface = np.asarray(_load_npy(path, "surface"), dtype=np.float32)
    if surface.shape != (image_size[1], image_size[0], 3):
        raise InputError(
            f"{path}: surface map has shape {surface.shape}, "
            f"expected {(image_size[1], image_size[0], 3)}"
        )
    return surface
