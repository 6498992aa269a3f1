"""Live events of a run: what a 3D viewer (or any other sink) sees while the team works.

They flow like the progress events of :mod:`como3r.progress`: small frozen dataclasses
handed to one optional callback (``live``) of :func:`como3r.runtime.pipeline.run` and
:func:`como3r.runtime.multiprocess.run_multiprocess`, built only when a sink is attached. The
live viewer (:mod:`como3r.viewer`, manual: docs/viewer.md) is the sink that exists; it never
reaches into SLAM state, only into these events.

* :class:`FrameEvent` -- after every frame of an agent: its pose, intrinsics, a
  downsampled image and its tracking state. In the multi-process runtime the agent process
  builds it and sends it as a message (registered in :mod:`como3r.transport.messages`); the
  coordinator's process passes it on unchanged.
* :class:`KeyframeEvent` -- when the coordinator takes a keyframe (and again when the
  keyframe's fused pointmap is refreshed, and at the end with its refined one): its pose and
  its confident points, subsampled, in its own camera frame.
* :class:`MapEvent` -- after every gauge merge or global solve, and once at the end: every
  keyframe's pose, the coordinator's cross-agent edges (at the end also the agents'
  intra-agent loop edges), the gauge components and the merged map.
* :class:`TrajectoryEvent` -- at the end: an agent's final trajectory.

Everything is numpy (no torch) and in the conventions of the rest of como3r: poses ``T_WC``
``(8,)`` Sim(3) (translation, quaternion x y z w, scale), points in metres of the map,
camera frames x right, y down, z forward. This module imports nothing of como3r: every
layer may build events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FrameEvent",
    "KeyframeEvent",
    "MapEvent",
    "TrajectoryEvent",
    "LiveEvent",
    "LiveCallback",
    "FRAME_IMAGE_LONG_SIDE",
    "KEYFRAME_POINTS",
]

#: a frame event's image is the network input subsampled to at most this long side
FRAME_IMAGE_LONG_SIDE = 256

#: a keyframe contributes at most this many pixels (a regular grid) before the confidence test
KEYFRAME_POINTS = 4096


@dataclass(frozen=True)
class FrameEvent:
    """One frame of one agent, as just tracked.

    Attributes:
        agent: agent id.
        frame_index: the frame's index in the agent's stream.
        timestamp: the frame's timestamp [s].
        state: ``"tracking"``, ``"lost"`` or ``"relocalized"``
            (:func:`como3r.progress.tracking_state`).
        T_WC: ``(8,)`` float64 pose in the agent's current world frame; None when lost.
        K: ``(3, 3)`` float64 intrinsics of ``image`` (the agent's calibration or
            self-calibration, else the focal length its keyframe's pointmap implies); None
            before the agent's first keyframe.
        image: ``(h, w, 3)`` uint8 RGB, long side at most :data:`FRAME_IMAGE_LONG_SIDE`.
        wall_time: seconds since the epoch when the frame was done.
    """

    agent: int
    frame_index: int
    timestamp: float
    state: str
    T_WC: np.ndarray | None
    K: np.ndarray | None
    image: np.ndarray
    wall_time: float
    version: int = 1


@dataclass(frozen=True)
class KeyframeEvent:
    """A keyframe as the coordinator holds it.

    Attributes:
        agent: agent id.
        kf_id: keyframe id within the agent.
        frame_index: its frame's index in the agent's stream.
        T_WC: ``(8,)`` float64 its pose.
        points: ``(N, 3)`` float32 its confident points (mean confidence above
            ``visualization.map_min_confidence``) on a grid of at most
            :data:`KEYFRAME_POINTS` pixels, in its camera frame.
        wall_time: seconds since the epoch.
    """

    agent: int
    kf_id: int
    frame_index: int
    T_WC: np.ndarray
    points: np.ndarray
    wall_time: float


@dataclass(frozen=True)
class MapEvent:
    """The coordinator's map after a gauge merge, a global solve or the end of the run.

    Attributes:
        reason: what changed it: ``"gauge"``, ``"global_ba"`` (both, comma-separated, when
            one keyframe caused both) or ``"final"``.
        keyframes: ``(G, 2)`` int64 ``[agent, kf_id]`` of every keyframe.
        T_WC: ``(G, 8)`` float64 their poses.
        edges: ``(E, 4)`` int64 ``[agent_i, kf_i, agent_j, kf_j]`` of every admitted
            cross-agent edge and, in the final event, every intra-agent loop edge.
        edge_kinds: ``(E,)`` ``"inter"`` or ``"loop"`` per edge.
        components: the gauge components (agent ids; agents of one share a world frame).
        points: ``(N, 3)`` float32 the merged map: every keyframe's points of
            :class:`KeyframeEvent`, in the world frame.
        point_agents: ``(N,)`` int32 the agent of each point.
        wall_time: seconds since the epoch.
    """

    reason: str
    keyframes: np.ndarray
    T_WC: np.ndarray
    edges: np.ndarray
    edge_kinds: tuple[str, ...]
    components: tuple[tuple[int, ...], ...]
    points: np.ndarray
    point_agents: np.ndarray
    wall_time: float


@dataclass(frozen=True)
class TrajectoryEvent:
    """An agent's final trajectory (every tracked frame), once the run is solved.

    Attributes:
        agent: agent id.
        frame_indices: ``(N,)`` int64 its tracked frames.
        T_WC: ``(N, 8)`` float64 their poses in the shared world frame.
        wall_time: seconds since the epoch.
    """

    agent: int
    frame_indices: np.ndarray
    T_WC: np.ndarray
    wall_time: float


LiveEvent = FrameEvent | KeyframeEvent | MapEvent | TrajectoryEvent

LiveCallback = Callable[[LiveEvent], None]
"""What a run calls with every live event."""
