"""Correspondence-ratio confidence of inter-robot loop closures (F-Sec. III-B, F-Eq. 1-3).

The prior matches almost any two images with confidence, so the number of correspondences
of a loop pair is normalised by that of the robot's own consecutive keyframe pair, whose
overlap the odometry guarantees:

    r = |(I_i^alpha, I_j^beta) correspondences| / |(I_{i-1}^alpha, I_i^alpha) correspondences|   (F-Eq. 1)

Loops with ``r < R_thr`` are failed registrations and dropped; the others get the
probability

    p = 1 / (1 + exp(-k (r - 1)))                                                        (F-Eq. 2)

which multiplies the information matrix of the loop's factor (F-Eq. 3).
"""

from __future__ import annotations

import math


def correspondence_ratio(loop_correspondences: int, odometry_correspondences: int) -> float:
    """``r`` of F-Eq. 1; 0 when the odometry pair has no correspondence (nothing to trust)."""
    if loop_correspondences < 0 or odometry_correspondences < 0:
        raise ValueError(
            "correspondence counts must be >= 0, got "
            f"{loop_correspondences} and {odometry_correspondences}"
        )
    if odometry_correspondences == 0:
        return 0.0
    return loop_correspondences / odometry_correspondences


def loop_probability(ratio: float, k: float) -> float:
    """``p`` of F-Eq. 2: the logistic of ``k (r - 1)``, in (0, 1)."""
    z = -k * (ratio - 1.0)
    if z > 0:  # exp(-z) cannot overflow on this branch
        e = math.exp(-z)
        return e / (1.0 + e)
    return 1.0 / (1.0 + math.exp(z))


def accept_loop(ratio: float, threshold: float) -> bool:
    """Whether a loop passes the ratio test ``r >= R_thr`` (F-Sec. III-B)."""
    return ratio >= threshold
