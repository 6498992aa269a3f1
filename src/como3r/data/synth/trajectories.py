"""Closed planar paths and the camera poses of agents moving along them.

World frame: z up. Cameras follow OpenCV (x right, y down, z forward); a pose is
``T_WC`` with a world point ``x_W = R_WC x_C + t_WC``.

Every multi-agent preset puts its agents on one closed loop of length ``P`` with ``N``
junctions ``J_k`` at arc length ``k P / N``. Agent ``a`` drives from ``J_a - S/2`` to
``J_{a+1} + S/2``, so consecutive agents (and, closing the ring, the last and the first)
share a stretch of length ``S`` around each junction, and each agent spends exactly the
fraction ``2 S / L`` of its path ``L`` on stretches another agent also drives: that
fraction is the ``overlap`` argument of :func:`como3r.data.synth.synthesize`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

_LOOP_SAMPLES = 8192


class LoopCurve:
    """A closed planar curve parameterised by arc length (dense polyline, periodic).

    Args:
        points: ``(M, 2)`` samples along the curve, counter-clockwise, first point not
            repeated at the end.
    """

    def __init__(self, points: np.ndarray) -> None:
        closed = np.vstack([points, points[:1]])
        seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        self._closed = closed
        self.length = float(self._arc[-1])
        prev_pts = np.roll(points, 1, axis=0)
        next_pts = np.roll(points, -1, axis=0)
        tangent = next_pts - prev_pts
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        self._tangent = np.vstack([tangent, tangent[:1]])

    @property
    def points(self) -> np.ndarray:
        """``(M, 2)`` the defining samples."""
        return self._closed[:-1]

    def at(self, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``(K, 2)`` and unit tangents ``(K, 2)`` at arc lengths ``(K,)``
        (taken modulo the length)."""
        a = np.mod(np.asarray(arc, dtype=np.float64), self.length)
        xy = np.stack([np.interp(a, self._arc, self._closed[:, i]) for i in range(2)], axis=1)
        tan = np.stack([np.interp(a, self._arc, self._tangent[:, i]) for i in range(2)], axis=1)
        return xy, tan / np.linalg.norm(tan, axis=1, keepdims=True)


def flower_loop(
    center: tuple[float, float], radius: float, bulge: float, petals: int, phase: float
) -> LoopCurve:
    """``r(theta) = radius + bulge sin^4(petals (theta - phase) / 2)`` around ``center``.

    The waists ``theta_k = phase + 2 pi k / petals`` (where ``r = radius`` and the curve
    runs perpendicular to the radius) are the junctions between rooms; arc length 0 is at
    ``theta_0``. The fourth power keeps the curve near the waist circle for a while on
    either side of a junction, so it crosses the wall between two rooms squarely through
    the door and only then swings out into the room.
    """
    theta = phase + np.linspace(0.0, 2.0 * np.pi, _LOOP_SAMPLES, endpoint=False)
    r = radius + bulge * np.sin(0.5 * petals * (theta - phase)) ** 4
    return LoopCurve(np.stack([center[0] + r * np.cos(theta), center[1] + r * np.sin(theta)], 1))


def fit_flower_bulge(length: float, radius: float, petals: int) -> float:
    """Bulge that gives :func:`flower_loop` the requested length (0 if the circle of
    ``radius`` is already at least that long)."""
    if 2.0 * np.pi * radius >= length:
        return 0.0

    def loop_length(bulge: float) -> float:
        return flower_loop((0.0, 0.0), radius, bulge, petals, 0.0).length

    lo, hi = 0.0, max(radius, 1.0)
    while loop_length(hi) < length:
        hi *= 2.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if loop_length(mid) < length else (lo, mid)
    return 0.5 * (lo + hi)


def stadium_loop(center: tuple[float, float], straight: float, radius: float) -> LoopCurve:
    """Two straights of length ``straight`` (parallel to x) joined by half circles.

    Arc length 0 is at the start of the lower straight, matching
    :class:`como3r.data.synth.primitives.StadiumRoad`.
    """
    length = 2.0 * straight + 2.0 * np.pi * radius
    arc = np.linspace(0.0, length, _LOOP_SAMPLES, endpoint=False)
    half = 0.5 * straight
    cap = np.pi * radius
    xy = np.empty((arc.size, 2))
    low = arc < straight
    right = (arc >= straight) & (arc < straight + cap)
    high = (arc >= straight + cap) & (arc < 2 * straight + cap)
    left = arc >= 2 * straight + cap
    xy[low] = np.stack([arc[low] - half, np.full(low.sum(), -radius)], 1)
    ang = (arc[right] - straight) / radius - 0.5 * np.pi
    xy[right] = np.stack([half + radius * np.cos(ang), radius * np.sin(ang)], 1)
    xy[high] = np.stack([half - (arc[high] - straight - cap), np.full(high.sum(), radius)], 1)
    ang = (arc[left] - 2 * straight - cap) / radius + 0.5 * np.pi
    xy[left] = np.stack([-half + radius * np.cos(ang), radius * np.sin(ang)], 1)
    return LoopCurve(xy + np.asarray(center))


@dataclass(frozen=True)
class CameraMotion:
    """How a camera rides along a path (all angles in degrees, lengths in metres).

    ``yaw`` oscillates around the direction of travel so that a forward-moving camera
    still sees parallax; pitch, roll and height wobble gently like a hand-held camera.
    """

    speed: float = 0.08
    height: float = 1.5
    yaw_amplitude: float = 10.0
    yaw_wavelength: float = 3.5
    pitch: float = -4.0
    pitch_amplitude: float = 2.0
    roll_amplitude: float = 1.0
    bob_amplitude: float = 0.03


def camera_rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` R_WC of OpenCV cameras from heading angles in radians.

    ``yaw`` is the heading in the ground plane (0 = world +x, counter-clockwise),
    ``pitch`` > 0 looks up, ``roll`` > 0 turns the camera x axis towards its y axis.
    """
    cp = np.cos(pitch)
    forward = np.stack([cp * np.cos(yaw), cp * np.sin(yaw), np.sin(pitch)], axis=1)
    right = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=1)
    down = np.cross(forward, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right, down = c * right + s * down, c * down - s * right
    return np.stack([right, down, forward], axis=2)


@dataclass(frozen=True)
class AgentPath:
    """Poses of one agent, one per frame.

    Attributes:
        arc: ``(K,)`` arc length along the loop of every frame (not wrapped), metres.
        positions: ``(K, 3)`` camera centres t_WC.
        rotations: ``(K, 3, 3)`` R_WC.
        jumps: frames ``j`` whose step from frame ``j - 1`` is a teleport (the ``revisit``
            preset), not travelled.
    """

    arc: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray
    jumps: tuple[int, ...] = ()

    def length(self) -> float:
        """Distance travelled along the path in metres: the arc length of every step but
        the teleports."""
        steps = np.abs(np.diff(self.arc))
        steps[[j - 1 for j in self.jumps]] = 0.0
        return float(steps.sum())

    def sim3(self) -> torch.Tensor:
        """``(K, 8)`` float64 poses (t, q_xyzw with w >= 0, s = 1)."""
        quat = Rotation.from_matrix(self.rotations).as_quat()
        quat *= np.where(quat[:, 3:] < 0, -1.0, 1.0)
        ones = np.ones((len(quat), 1))
        return torch.from_numpy(np.concatenate([self.positions, quat, ones], axis=1))


def ride(
    curve: LoopCurve,
    arc_start: float,
    frames: int,
    motion: CameraMotion,
    lateral_offset: float,
    phases: np.ndarray,
) -> AgentPath:
    """Poses of a camera riding ``curve`` from ``arc_start`` at ``motion.speed`` per frame.

    Args:
        curve: the loop.
        arc_start: arc length of frame 0.
        frames: number of frames K.
        motion: speed and wobble.
        lateral_offset: metres to the left of the curve (keeps agents sharing a stretch
            from riding on exactly the same line).
        phases: ``(4,)`` radians, phases of the yaw, pitch, roll and height wobble.
    """
    arc = arc_start + motion.speed * np.arange(frames)
    xy, tangent = curve.at(arc)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    xy = xy + lateral_offset * normal
    # Wobble as functions of the distance travelled: same path shape at any frame rate.
    w = 2.0 * np.pi * arc / motion.yaw_wavelength
    yaw = np.arctan2(tangent[:, 1], tangent[:, 0]) + np.radians(motion.yaw_amplitude) * np.sin(
        w + phases[0]
    )
    pitch = np.radians(motion.pitch + motion.pitch_amplitude * np.sin(0.37 * w + phases[1]))
    roll = np.radians(motion.roll_amplitude) * np.sin(0.61 * w + phases[2])
    z = motion.height + motion.bob_amplitude * np.sin(2.3 * w + phases[3])
    return AgentPath(
        arc=arc,
        positions=np.concatenate([xy, z[:, None]], axis=1),
        rotations=camera_rotations(yaw, pitch, roll),
    )


@dataclass(frozen=True)
class RingPlan:
    """Where N agents start on a loop so that neighbours share stretches of length S.

    Attributes:
        loop_length: P = N * (L - S) (for one agent, L plus one step: a closed loop), or the
            longer minimum loop asked for.
        shared: S, length of each shared stretch.
        starts: ``(N,)`` arc length of each agent's first frame.
        closed: whether the agents' paths close the loop (the last agent meets the first,
            one agent returns to its start); false on a lengthened loop.
    """

    loop_length: float
    shared: float
    starts: np.ndarray
    closed: bool = True

    @property
    def junctions(self) -> np.ndarray:
        """``(N,)`` arc lengths of the junctions J_k (centres of the shared stretches)."""
        return self.starts + 0.5 * self.shared


def plan_ring(
    agents: int, path_length: float, overlap: float, step: float, min_loop: float = 0.0
) -> RingPlan:
    """Starts of ``agents`` paths of length ``path_length`` on one loop (module docstring).

    With one agent the loop is ``path_length + step`` long: the agent goes round once and
    its last frame lands one step before its first. A longer ``min_loop`` (metres) keeps
    the starts and lengthens the loop: the agents then ride an open chain on it (each still
    shares a stretch with the next, the last no longer with the first) and turn less per
    metre.
    """
    if agents == 1:
        natural, shared, starts = path_length + step, 0.0, np.zeros(1)
    else:
        shared = 0.5 * overlap * path_length
        room = path_length - shared
        natural, starts = room * agents, room * np.arange(agents) - 0.5 * shared
    return RingPlan(max(natural, min_loop), shared, starts, closed=min_loop <= natural)
