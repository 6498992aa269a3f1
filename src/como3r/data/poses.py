"""Ground-truth poses at image times, from ground truth at its own rate.

Motion capture and the camera are separate clocks: TUM RGB-D's mocap runs at 100 Hz and
starts a fraction of a second after the Kinect, EuRoC's at 200 Hz, and every real system
drops samples now and then. Readers return the ground truth as published; this module
gives each frame the pose at its timestamp:

* a ground-truth sample within :data:`EXACT_TOLERANCE` of the frame is its pose (datasets
  that publish one pose per frame: KITTI, 7-Scenes, Tanks and Temples, synthetic scenes);
* otherwise, between the two samples around the frame when they are at most
  :data:`MAX_GAP` apart: position linearly, orientation by SLERP, at the frame's fraction
  of the way (the common "interpolate the pose at the image time" of RGB-D benchmarks);
* otherwise (before the first sample, after the last, or inside a longer gap) the frame has
  no pose: a NaN row. Whatever needs a pose per frame (the simulated prior) skips such
  frames; evaluation associates timestamps as evo does and leaves them out too.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from como3r.io.tum import Trajectory

MAX_GAP = 0.1
"""Seconds; the widest spacing of two ground-truth samples a frame between them takes an
interpolated pose from (a 40 ms mocap dropout at 100 Hz leaves a 50 ms gap: bridged)."""
EXACT_TOLERANCE = 1e-3
"""Seconds; a sample this close to a frame is the frame's pose, also before the first or
after the last sample (timestamps printed with a few decimals)."""


def poses_at(
    timestamps: np.ndarray, groundtruth: Trajectory | None, max_gap: float = MAX_GAP
) -> Tensor:
    """Ground-truth poses at ``timestamps`` (module docstring).

    Args:
        timestamps: ``(N,)`` float64 seconds (image times).
        groundtruth: ground truth at its own rate (strictly increasing timestamps), or None.
        max_gap: widest sample spacing bridged by interpolation [s].

    Returns:
        ``(N, 8)`` float64 poses (t, q_xyzw, s), a NaN row for a frame without a pose
        (every row without ground truth).
    """
    stamps = np.asarray(timestamps, dtype=np.float64)
    out = torch.full((len(stamps), 8), float("nan"), dtype=torch.float64)
    if groundtruth is None or len(groundtruth) == 0 or len(stamps) == 0:
        return out
    reference = np.asarray(groundtruth.timestamps, dtype=np.float64)
    poses = groundtruth.T_WC.detach().to("cpu", torch.float64).numpy()
    after = np.searchsorted(reference, stamps)  # first sample >= the frame
    right = np.clip(after, 0, len(reference) - 1)
    left = np.clip(after - 1, 0, len(reference) - 1)
    nearest = np.where(
        np.abs(reference[left] - stamps) <= np.abs(reference[right] - stamps), left, right
    )
    exact = np.abs(reference[nearest] - stamps) <= EXACT_TOLERANCE
    inside = (after > 0) & (after < len(reference))
    bridged = inside & ~exact & (reference[right] - reference[left] <= max_gap)
    result = np.full((len(stamps), 8), np.nan)
    result[exact] = poses[nearest[exact]]
    if bridged.any():
        a, b = left[bridged], right[bridged]
        alpha = (stamps[bridged] - reference[a]) / (reference[b] - reference[a])
        result[bridged, :3] = (1 - alpha)[:, None] * poses[a, :3] + alpha[:, None] * poses[b, :3]
        result[bridged, 3:7] = slerp(poses[a, 3:7], poses[b, 3:7], alpha)
        result[bridged, 7] = (1 - alpha) * poses[a, 7] + alpha * poses[b, 7]
    out[:] = torch.from_numpy(result)
    return out


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    Args:
        q0, q1: ``(M, 4)`` unit quaternions (any component order, the same in both).
        alpha: ``(M,)`` fractions in [0, 1] (0 gives ``q0``, 1 gives ``q1``).

    Returns:
        ``(M, 4)`` unit quaternions.
    """
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where((dot < 0)[:, None], -q1, q1)  # q and -q are one rotation
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-8
    sin_theta = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / sin_theta)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / sin_theta)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def missing_pose_summary(
    timestamps: np.ndarray, groundtruth: Trajectory, has_pose: np.ndarray
) -> str:
    """Where the frames without a pose are, for the one warning: ``"4 before the first
    ground-truth pose, 2 in gaps wider than 0.1 s"``."""
    missing = ~np.asarray(has_pose, dtype=bool)
    stamps = np.asarray(timestamps)[missing]
    first, last = float(groundtruth.timestamps[0]), float(groundtruth.timestamps[-1])
    parts = [
        (int((stamps < first).sum()), "before the first ground-truth pose"),
        (int((stamps > last).sum()), "after the last"),
        (int(((stamps >= first) & (stamps <= last)).sum()), f"in gaps wider than {MAX_GAP:g} s"),
    ]
    return ", ".join(f"{count} {where}" for count, where in parts if count)
