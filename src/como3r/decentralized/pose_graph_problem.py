"""A multi-robot pose graph problem (F-Sec. III-C; :mod:`.pose_graph` solves it): its inter-robot
loop closures, the robots' keyframe odometry (with each odometry's unconverged start) and the
anchor, a solution, the conversion of
poses to and from ``gtsam.Pose3`` and the graph's variable keys, and the structure loops give
it: the robots they connect and the clusters of nearby loops.
"""

from __future__ import annotations

from collections import defaultdict, deque
from dataclasses import dataclass, field

import gtsam
import numpy as np


@dataclass(frozen=True)
class LoopClosure:
    """An inter-robot loop closure between keyframe ``keyframe_a`` of robot ``robot_a``
    (alpha, who registered it) and keyframe ``keyframe_b`` of robot ``robot_b`` (beta).

    Attributes:
        T_ab: ``(8,)`` float64 relative pose from the prior: camera b in camera a
            (t in the prior's units, q_xyzw, s = the fit's scale, unused).
        odometry_scale: F-Eq. 6 factor ``|t_odom(i-1, i)| / |t_prior(i-1, i)|``; NaN if
            unavailable.
        ratio: correspondence ratio r (F-Eq. 1).
        probability: confidence p (F-Eq. 2).
        correspondences: correspondences of the loop pair.
    """

    robot_a: int
    keyframe_a: int
    robot_b: int
    keyframe_b: int
    T_ab: np.ndarray
    odometry_scale: float
    ratio: float
    probability: float
    correspondences: int

    @property
    def robots(self) -> tuple[int, int]:
        return self.robot_a, self.robot_b


@dataclass(frozen=True)
class OdometryStart:
    """A robot's odometry's unconverged start scale (F-Sec. IV-C), in the pose graph's units:
    its steps may stretch along themselves by ``scale_sigma`` of their length, decaying as
    ``exp(-d / spacings)`` with the distance ``d`` travelled in keyframe spacings
    (:func:`~.factor_noise.odometry_noise`). ``(0, 0)``: metric from the start.

    Attributes:
        scale_sigma: the start's scale uncertainty, a fraction of a step's length, >= 0.
        spacings: its decay length in keyframe spacings, >= 0.
    """

    scale_sigma: float = 0.0
    spacings: float = 0.0


@dataclass
class PoseGraphProblem:
    """One connected multi-robot pose graph.

    Attributes:
        odometry: robot -> ``(K, 8)`` keyframe odometry poses ``T_OC`` in its own frame.
        loops: loop closures between these robots.
        anchor: the robot whose first keyframe fixes the gauge.
        anchor_pose: ``(8,)`` pose of the anchor's first keyframe in the output frame.
        initial: robot -> ``(K', 8)`` current estimates of its first ``K'`` keyframes,
            already in the output frame (used for initialisation only).
        starts: robot -> its odometry's unconverged start, from the kind its input declares
            (:mod:`.odometry_kind`); a robot without one (undeclared) has the
            configuration's ``pose_graph.odom_start_scale_sigma`` over
            ``odom_start_spacings`` (:func:`~.factor_noise.robot_start`).
    """

    odometry: dict[int, np.ndarray]
    loops: list[LoopClosure]
    anchor: int
    anchor_pose: np.ndarray
    initial: dict[int, np.ndarray] = field(default_factory=dict)
    starts: dict[int, OdometryStart] = field(default_factory=dict)


@dataclass
class PoseGraphSolution:
    """Result of one solve.

    Attributes:
        poses: robot -> ``(K, 8)`` keyframe poses ``T_WC`` in the output frame.
        loop_scales: ``(L,)`` scale applied to each loop's prior translation.
        loop_weights: ``(L,)`` GNC weights (1 for LM).
        loop_residuals: ``(L,)`` whitened squared residual of each loop at weight 1.
        seconds: solver wall time.
        iterations: LM iterations (summed over GNC's outer iterations).
        cost: final value of the (weighted) objective.
    """

    poses: dict[int, np.ndarray]
    loop_scales: np.ndarray
    loop_weights: np.ndarray
    loop_residuals: np.ndarray
    seconds: float
    iterations: int
    cost: float


def to_pose3(T: np.ndarray) -> gtsam.Pose3:
    """``gtsam.Pose3`` of an ``(8,)`` (or ``(7,)``) pose ``(t, q_xyzw[, s])``."""
    x, y, z, w = (float(v) for v in T[3:7])
    return gtsam.Pose3(gtsam.Rot3.Quaternion(w, x, y, z), np.asarray(T[:3], dtype=np.float64))


def from_pose3(pose: gtsam.Pose3) -> np.ndarray:
    """``(8,)`` float64 ``(t, q_xyzw, 1)`` of a ``gtsam.Pose3`` (``w >= 0``)."""
    q = pose.rotation().toQuaternion()
    quat = np.array([q.x(), q.y(), q.z(), q.w()])
    quat = -quat if quat[3] < 0 else quat
    return np.concatenate([pose.translation(), quat / np.linalg.norm(quat), [1.0]])


def pose_key(robot: int, keyframe: int) -> int:
    """GTSAM key of robot ``robot``'s keyframe ``keyframe``."""
    return gtsam.symbol("x", (robot << 24) | keyframe)


def scale_key(index: int) -> int:
    """GTSAM key of loop scale variable ``index``."""
    return gtsam.symbol("s", index)


def odometry_scale_key(robot: int, step: int) -> int:
    """GTSAM key of robot ``robot``'s odometry scale on the step into keyframe ``step``."""
    return gtsam.symbol("l", (robot << 24) | step)


def connected_components(robots: list[int], loops: list[LoopClosure]) -> list[list[int]]:
    """Groups of ``robots`` connected by ``loops`` (sorted; singletons included)."""
    neighbours: dict[int, set[int]] = {r: set() for r in robots}
    for loop in loops:
        if loop.robot_a in neighbours and loop.robot_b in neighbours:
            neighbours[loop.robot_a].add(loop.robot_b)
            neighbours[loop.robot_b].add(loop.robot_a)
    components, seen = [], set()
    for start in sorted(robots):
        if start in seen:
            continue
        queue, component = deque([start]), []
        seen.add(start)
        while queue:
            robot = queue.popleft()
            component.append(robot)
            for other in sorted(neighbours[robot] - seen):
                seen.add(other)
                queue.append(other)
        components.append(sorted(component))
    return components


def loop_clusters(loops: list[LoopClosure], window: int) -> list[list[int]]:
    """Clusters of loop indices (F-Sec. III-C-c): same pair of robots, endpoints fewer than
    ``window`` keyframes apart on both robots, closed transitively. Each cluster is sorted
    by the keyframes of the robot with the smaller id."""

    def endpoints(loop: LoopClosure) -> tuple[int, int, int, int]:
        if loop.robot_a < loop.robot_b:
            return loop.robot_a, loop.robot_b, loop.keyframe_a, loop.keyframe_b
        return loop.robot_b, loop.robot_a, loop.keyframe_b, loop.keyframe_a

    parent = list(range(len(loops)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    ends = [endpoints(loop) for loop in loops]
    for i, (ra, rb, ka, kb) in enumerate(ends):
        for j in range(i):
            ra2, rb2, ka2, kb2 = ends[j]
            if (ra, rb) == (ra2, rb2) and abs(ka - ka2) < window and abs(kb - kb2) < window:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = defaultdict(list)
    for i in range(len(loops)):
        groups[find(i)].append(i)
    return sorted(
        (sorted(g, key=lambda i: ends[i][2:] + (i,)) for g in groups.values()), key=lambda g: g[0]
    )


def loop_measurement(loop: LoopClosure, scale: float) -> gtsam.Pose3:
    pose = to_pose3(loop.T_ab)
    return gtsam.Pose3(pose.rotation(), scale * pose.translation())
