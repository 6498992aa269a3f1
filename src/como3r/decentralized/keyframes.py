"""Keyframes of a robot, selected by the distance its odometry travelled (F-Sec. IV-D).

FLOCC-SLAM's pose graph has one node per keyframe (F-Sec. III: ``T_alpha,0 ... T_alpha,n``)
and sparser keyframes trade accuracy for memory and bandwidth (F-Fig. 5). A frame becomes a
keyframe when the odometry path length since the previous keyframe reaches the keyframe
distance; the first frame with odometry is always one. The decentralized mode sets that
distance relative to the scene (``keyframe_distance_ratio`` times the scene depth a robot
sees), so its keyframes are equally dense at any scene scale.

:class:`RobotData` is one robot's input as :func:`open_robot` reads it, once: its frames'
odometry, its odometry's declared start and, after the mission, its keyframes; the mission
driver and the robot built on it (:class:`~.robot.Robot`) share it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from como3r.config import Config
from como3r.config_decentralized import DecentralizedConfig
from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput
from como3r.data.input_files import associate_timestamps
from como3r.decentralized.odometry_kind import declared_start
from como3r.decentralized.pose_graph_problem import OdometryStart
from como3r.errors import InputError
from como3r.geometry.lie import sim3_compose, sim3_inverse, sim3_normalize

#: Frames pair with odometry poses within this many seconds (as ground truth does).
MIN_TOLERANCE_S = 1e-3


@dataclass(frozen=True)
class FrameOdometry:
    """Odometry poses of the frames of one robot that have one.

    Attributes:
        frames: ``(N,)`` int64 frame indices, increasing.
        timestamps: ``(N,)`` float64 frame timestamps [s].
        T_OC: ``(N, 8)`` float64 odometry poses (t, q_xyzw, s = 1) in the robot's odometry
            frame O.
    """

    frames: np.ndarray
    timestamps: np.ndarray
    T_OC: Tensor

    def __len__(self) -> int:
        return int(self.frames.shape[0])


@dataclass(frozen=True)
class Keyframes:
    """A robot's keyframes: rows of its :class:`FrameOdometry`.

    Attributes:
        rows: ``(K,)`` int64 rows of the frame odometry, increasing.
        frames: ``(K,)`` int64 frame indices.
        timestamps: ``(K,)`` float64 [s].
        T_OC: ``(K, 8)`` float64 odometry poses.
    """

    rows: np.ndarray
    frames: np.ndarray
    timestamps: np.ndarray
    T_OC: Tensor

    def __len__(self) -> int:
        return int(self.rows.shape[0])

    def up_to(self, time_s: float) -> int:
        """Number of keyframes with a timestamp at or before ``time_s``."""
        return int(np.searchsorted(self.timestamps, time_s, side="right"))


def frame_odometry(agent: AgentInput) -> FrameOdometry:
    """Associate every frame of ``agent`` with its odometry pose by timestamp.

    Raises:
        InputError: the agent has no ``odometry.txt`` or no frame matches an odometry pose.
    """
    if agent.odometry is None:
        raise InputError(
            f"{agent.root}: the decentralized mode needs odometry.txt (TUM, metric "
            "odometry of the robot)"
        )
    tolerance = max(0.5 / agent.fps, MIN_TOLERANCE_S)
    rows = associate_timestamps(agent.timestamps, agent.odometry.timestamps, tolerance)
    frames = np.flatnonzero(rows >= 0).astype(np.int64)
    if frames.size == 0:
        raise InputError(
            f"{agent.root}/odometry.txt: no pose within {tolerance:.4f} s of a frame timestamp"
        )
    T_OC = agent.odometry.T_WC[torch.from_numpy(rows[frames])].double()
    return FrameOdometry(frames, agent.timestamps[frames].copy(), T_OC)


def select_keyframes(odometry: FrameOdometry, distance: float) -> Keyframes:
    """Keyframes every ``distance`` of odometry path (module docstring).

    Args:
        odometry: the robot's frame odometry, ``N >= 1`` frames.
        distance: path length between keyframes in odometry units, >= 0 (0: every frame).
    """
    positions = odometry.T_OC[:, :3].numpy()
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    rows = [0]
    since = 0.0
    for k, step in enumerate(steps, start=1):
        since += float(step)
        if since >= distance:
            rows.append(k)
            since = 0.0
    chosen = np.asarray(rows, dtype=np.int64)
    return Keyframes(
        chosen,
        odometry.frames[chosen],
        odometry.timestamps[chosen],
        odometry.T_OC[torch.from_numpy(chosen)],
    )


def frame_poses(odometry: FrameOdometry, keyframes: Keyframes, estimate: np.ndarray) -> Tensor:
    """Poses of every frame from estimates of the first keyframes and the odometry.

    A frame is placed relative to the latest estimated keyframe at or before it by the
    odometry between them, ``T_k O_k^-1 O_n``; without any estimate, at its odometry pose.

    Args:
        odometry: the robot's frame odometry (N frames).
        keyframes: its keyframes (rows of ``odometry``).
        estimate: ``(K', 8)`` poses of keyframes ``0 .. K'-1``, ``K' <= K``.

    Returns:
        ``(N, 8)`` float64 poses.
    """
    if len(estimate) == 0:
        return odometry.T_OC.clone()
    rows = np.arange(len(odometry))
    keyframe = np.searchsorted(keyframes.rows, rows, side="right") - 1
    keyframe = torch.from_numpy(np.minimum(keyframe, len(estimate) - 1))
    T_WK = torch.as_tensor(estimate, dtype=torch.float64)[keyframe]
    T_OK = keyframes.T_OC[keyframe]
    relative = sim3_compose(sim3_inverse(T_OK), odometry.T_OC)
    return sim3_normalize(sim3_compose(T_WK, relative))


@dataclasses.dataclass
class RobotData:
    """One robot's input, odometry, its odometry's declared start (:mod:`.odometry_kind`;
    None: undeclared) and (the driver's, after the mission, from its report) keyframes."""

    agent: AgentInput
    odometry: FrameOdometry
    keyframes: Keyframes | None = None
    start: OdometryStart | None = None


def open_robot(
    path: str | Path, config: Config, settings: DecentralizedConfig, log: bool = True
) -> RobotData:
    """A robot's input, odometry and declared odometry start, checked before any work; each
    file read once here (the robot built on it reads none of them again). With ``log``, say
    at info level what the odometry's kind is, or that it is undeclared.

    Raises:
        InputError: a missing or malformed input, odometry or ``odometry.json``.
    """
    agent = open_agent(
        path, fps=config.input.frame_rate_hz, format=config.input.format, topic=config.input.topic
    )
    return RobotData(agent, frame_odometry(agent), start=declared_start(agent, settings, log=log))
