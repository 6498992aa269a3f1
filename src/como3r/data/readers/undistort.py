"""Inputs whose camera has lens distortion, seen through the pinhole camera of the same
intrinsics: readers that know a radial-tangential distortion (EuRoC's ``sensor.yaml``, a ROS
``CameraInfo``, TUM RGB-D's freiburg 1 and 2 Kinects) undo it as each frame is read, with
OpenCV's ``initUndistortRectifyMap`` (``K`` kept) and ``remap``: colour bilinearly, depth
by nearest neighbour (an interpolated depth would invent points between a foreground and
its background)."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import cv2
import numpy as np

from como3r.data.agent_input import AgentInput, Frame


@dataclass(frozen=True, eq=False)
class UndistortedInput(AgentInput):
    """An :class:`AgentInput` whose images and depth maps are undistorted as they are read
    (same ``K``).

    Attributes:
        distortion: OpenCV radial-tangential ``(k1, k2, p1, p2[, k3])`` of ``calib``.
    """

    distortion: tuple[float, ...] = ()

    @property
    def frames_are_files(self) -> bool:
        """The files are the distorted images (see :class:`AgentInput`)."""
        return super().frames_are_files and not any(self.distortion)

    def load_frame(self, i: int) -> Frame:
        frame = super().load_frame(i)
        return dataclasses.replace(frame, image=undistort(frame.image, self.calib, self.distortion))

    def load_depth(self, i: int) -> np.ndarray:
        """``(H, W)`` float32 metric depth of frame ``i`` on the undistorted pixels."""
        return undistort(
            super().load_depth(i), self.calib, self.distortion, interpolation=cv2.INTER_NEAREST
        )


def undistort(
    image: np.ndarray,
    calib: tuple[float, float, float, float] | None,
    distortion: tuple[float, ...],
    interpolation: int = cv2.INTER_LINEAR,
) -> np.ndarray:
    """``(H, W[, C])`` image of a radial-tangential camera, as seen by the pinhole camera of
    the same ``calib`` ``(fx, fy, cx, cy)`` (outside the distorted image: 0); unchanged
    without distortion."""
    if calib is None or not any(distortion):
        return image
    height, width = image.shape[:2]
    map_x, map_y = _undistort_maps(calib, distortion, (width, height))
    return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT)


@functools.lru_cache(maxsize=8)
def _undistort_maps(
    calib: tuple[float, float, float, float], distortion: tuple[float, ...], size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W)`` float32 source x and y of each undistorted pixel."""
    fx, fy, cx, cy = calib
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return cv2.initUndistortRectifyMap(
        K, np.array(distortion, dtype=np.float64), None, K, size, cv2.CV_32FC1
    )
