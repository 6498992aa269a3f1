"""The initial estimate of a pose graph (:func:`initial_poses`, :func:`initial_scales`;
:mod:`.pose_graph` solves from it): loop scales from odometry or 1, and each robot placed by
the loops that agree on its alignment to robots already placed, its keyframes chained by its
odometry; and the problem's keyframe spacing, the unit of its scale-free tolerances.
"""

from __future__ import annotations

import math
from collections import defaultdict

import gtsam
import numpy as np

from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    PoseGraphProblem,
    loop_measurement,
    to_pose3,
)
from como3r.errors import ConfigError

#: Loops agreeing on a robot's alignment within these bounds support each other (init); the
#: translation bound in keyframe spacings (:func:`keyframe_spacing`; was 1 m at the default
#: synthetic scene's 0.5 m spacing).
CONSENSUS_TRANSLATION_SPACINGS = 2.0


CONSENSUS_ROTATION_RAD = math.radians(10.0)


def initial_scales(loops: list[LoopClosure], scale_init: str) -> np.ndarray:
    """``(L,)`` initial loop scales: F-Eq. 6 (``odometry``; 1 where unavailable) or 1
    (``prior``: the prior's own scale)."""
    if scale_init == "prior":
        return np.ones(len(loops))
    if scale_init != "odometry":
        raise ConfigError(
            f"decentralized.pose_graph.scale_init: {scale_init!r} is not 'odometry' or 'prior'"
        )
    scales = np.array([loop.odometry_scale for loop in loops], dtype=np.float64)
    return np.where(np.isfinite(scales) & (scales > 0), scales, 1.0)


def _extend_by_odometry(estimate: np.ndarray, odometry: np.ndarray) -> list[gtsam.Pose3]:
    """Poses of all keyframes: ``estimate`` for the first ones, then odometry increments."""
    poses = [to_pose3(T) for T in estimate]
    for k in range(len(poses), len(odometry)):
        step = to_pose3(odometry[k - 1]).between(to_pose3(odometry[k]))
        poses.append(poses[-1].compose(step))
    return poses


def keyframe_spacing(problem: PoseGraphProblem, scales: np.ndarray) -> float:
    """The problem's length unit, in odometry units: the median odometry distance between
    consecutive keyframes of all its robots (keyframes are spaced relative to the scene
    depth, so this follows the scene's scale); without any pair of consecutive keyframes,
    the median length of the scaled loop translations (F-Eq. 6-7).

    Args:
        problem: odometry ``(K, 8)`` per robot and the loops.
        scales: ``(L,)`` loop scales (:func:`initial_scales`).

    Returns:
        A length > 0 (1 when the problem has neither a keyframe step nor a loop translation).
    """
    steps = [
        np.linalg.norm(np.diff(odometry[:, :3], axis=0), axis=1)
        for odometry in problem.odometry.values()
    ]
    lengths = np.concatenate([np.zeros(0), *steps])
    if not np.any(lengths > 0):
        lengths = np.array(
            [scale * np.linalg.norm(loop.T_ab[:3]) for loop, scale in zip(problem.loops, scales)]
        )
    lengths = lengths[np.isfinite(lengths) & (lengths > 0)]
    return float(np.median(lengths)) if lengths.size else 1.0


def _consensus_alignment(
    candidates: list[tuple[gtsam.Pose3, float]], translation_tolerance: float
) -> gtsam.Pose3:
    """The candidate alignment with the largest confidence-weighted support: the summed
    confidence (F-Eq. 2) of the candidates within ``translation_tolerance`` (odometry
    units) and :data:`CONSENSUS_ROTATION_RAD` of it."""
    best, best_support = candidates[0][0], -1.0
    for pose, _ in candidates:
        support = 0.0
        for other, probability in candidates:
            delta = pose.between(other)
            if (
                np.linalg.norm(delta.translation()) < translation_tolerance
                and np.linalg.norm(gtsam.Rot3.Logmap(delta.rotation())) < CONSENSUS_ROTATION_RAD
            ):
                support += probability
        if support > best_support:
            best, best_support = pose, support
    return best


def initial_poses(
    problem: PoseGraphProblem, scales: np.ndarray, spacing: float
) -> dict[int, list[gtsam.Pose3]]:
    """Initial keyframe poses of every robot in the output frame.

    The anchor starts at ``anchor_pose``; robots with a current estimate start from it;
    the others are placed breadth-first through the loops to robots already placed, each
    by the loop-implied alignment that most other loops agree with (within
    :data:`CONSENSUS_TRANSLATION_SPACINGS` keyframe spacings).

    Args:
        problem: the pose graph.
        scales: ``(L,)`` loop scales.
        spacing: the problem's keyframe spacing (:func:`keyframe_spacing`).

    Raises:
        ValueError: a robot is connected to the anchor neither by loops nor by an estimate.
    """
    placed: dict[int, list[gtsam.Pose3]] = {}
    anchor_odometry = problem.odometry[problem.anchor]
    placed[problem.anchor] = _extend_by_odometry(problem.anchor_pose[None], anchor_odometry)
    for robot, estimate in problem.initial.items():
        if robot != problem.anchor and len(estimate):
            placed[robot] = _extend_by_odometry(estimate, problem.odometry[robot])
    pending = set(problem.odometry) - set(placed)
    while pending:
        candidates: dict[int, list[tuple[gtsam.Pose3, float]]] = defaultdict(list)
        for loop, scale in zip(problem.loops, scales):
            for src, kf_src, dst, kf_dst, relative in (
                (
                    loop.robot_a,
                    loop.keyframe_a,
                    loop.robot_b,
                    loop.keyframe_b,
                    loop_measurement(loop, scale),
                ),
                (
                    loop.robot_b,
                    loop.keyframe_b,
                    loop.robot_a,
                    loop.keyframe_a,
                    loop_measurement(loop, scale).inverse(),
                ),
            ):
                if src in placed and dst in pending:
                    world_dst = placed[src][kf_src].compose(relative)
                    odometry_dst = to_pose3(problem.odometry[dst][kf_dst])
                    candidates[dst].append(
                        (world_dst.compose(odometry_dst.inverse()), loop.probability)
                    )
        if not candidates:
            raise ValueError(
                f"robots {sorted(pending)} are not connected to anchor "
                f"{problem.anchor} by loop closures"
            )
        for robot, options in sorted(candidates.items()):
            alignment = _consensus_alignment(options, CONSENSUS_TRANSLATION_SPACINGS * spacing)
            placed[robot] = [alignment.compose(to_pose3(T)) for T in problem.odometry[robot]]
            pending.discard(robot)
    return placed
