"""What every reader returns: :class:`AgentInput`, one agent's validated input, whose frames
are decoded lazily as :class:`Frame` (image, optional depth and surface maps, ground-truth
pose), and the decoders of image, video, depth and surface files they use.

The readers (:mod:`como3r.data.readers`) check every header up front; the decoders here check
the pixels when a frame is loaded.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from como3r.data.poses import missing_pose_summary, poses_at
from como3r.errors import InputError
from como3r.io.packed_arrays import SUFFIX as PACKED_SUFFIX
from como3r.io.packed_arrays import read_packed
from como3r.io.tum import Trajectory

T = TypeVar("T")

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
        capture = open_capture(self.video)
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
            capture = open_capture(self.video)
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


def open_capture(video: Path) -> cv2.VideoCapture:
    # FFmpeg would print its own diagnostics to stderr next to our one-line InputError;
    # a user who wants them sets the variable themselves.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        capture.release()
        raise InputError(f"{video}: cannot open video")
    return capture


def load_npy(path: Path, kind: str, mmap: bool = False) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: cannot read {kind} map ({exc})") from None


def load_float_map(path: Path, kind: str) -> np.ndarray:
    """The float map of a ``.npy`` file, or the array named ``kind`` of a ``.c3z`` file
    (:mod:`como3r.io.packed_arrays`, as ``como3r synth`` writes them): the same values."""
    if path.suffix.lower() != PACKED_SUFFIX:
        return load_npy(path, kind)
    return packed_member(read_packed(path), path, kind)


def packed_member(members: Mapping[str, T], path: Path, kind: str) -> T:
    """``members[kind]`` of the ``.c3z`` file ``path`` (its arrays, or their headers).

    Raises:
        InputError: the file holds no array of that name.
    """
    if kind not in members:
        raise InputError(f"{path}: holds no {kind!r} array (it holds {', '.join(members)})")
    return members[kind]


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
        depth = np.asarray(load_float_map(path, "depth"), dtype=np.float32)
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        if np.any(depth < 0):
            raise InputError(f"{path}: depth map has negative values")
    if depth.shape != (image_size[1], image_size[0]):
        raise InputError(f"{path}: depth map has shape {depth.shape}, expected {image_size[::-1]}")
    return depth


def _load_surface(path: Path, image_size: tuple[int, int]) -> np.ndarray:
    """``(H, W, 3)`` float32 appearance keys."""
    surface = np.asarray(load_float_map(path, "surface"), dtype=np.float32)
    if surface.shape != (image_size[1], image_size[0], 3):
        raise InputError(
            f"{path}: surface map has shape {surface.shape}, "
            f"expected {(image_size[1], image_size[0], 3)}"
        )
    return surface
