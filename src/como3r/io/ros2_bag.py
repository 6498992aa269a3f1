"""ROS 2 bag export of a finished run folder (manual: docs/commands/export.md).

The bag is a rosbag2 folder (``metadata.yaml`` version 8 and one MCAP file with
zstd-compressed chunks, CDR messages of the ROS 2 Humble definitions, which Jazzy's are equal
to) written with ``rosbags``, so it plays with ``ros2 bag play DIR`` and opens in Foxglove,
and no ROS installation is needed to write it. It reads what the other exports read
(:mod:`como3r.io.export`) plus the full-rate ``trajectories/agent_<a>.txt``; nothing of a live
run is touched.

**Frames** (REP-103/105 names):

- ``map``: como3r's shared world frame, the frame of ``trajectories/*.txt`` and ``map.ply``.
  Its axes are those of the run's world (the first camera's, OpenCV-like: y down), not REP-103's
  z-up, and its unit is the map's (metres only as far as the prior's scale is metric).
- ``agent_<a>/camera_optical``: agent ``a``'s camera in the optical convention (x right, y
  down, z forward), which is como3r's camera frame. Every pose in the bag is this frame's
  rigid pose in ``map`` (the TUM file's ``t``, ``q``; a keyframe's Sim(3) scale belongs to its
  pointmap, see :mod:`como3r.io.export`).

**Topics:**

- ``/tf`` (``tf2_msgs/TFMessage``): ``map`` -> ``agent_<a>/camera_optical``, one per tracked
  frame of every agent.
- ``/agent_<a>/odometry`` (``nav_msgs/Odometry``): the same poses; the twist, in the camera
  frame, is the finite difference to the next frame (to the previous for the last frame, zero
  for a single one); all covariances are zero (como3r estimates none).
- ``/agent_<a>/keyframes`` (``nav_msgs/Path``): at each keyframe, the final poses of the agent's
  keyframes up to it.
- ``/agent_<a>/camera/image/compressed`` (``sensor_msgs/CompressedImage``, ``png``) and
  ``/agent_<a>/camera/camera_info`` (``sensor_msgs/CameraInfo``, ``plumb_bob`` without
  distortion): each keyframe's image at the keyframe's size and its intrinsics (pixel centres
  at integers, as in ROS).
- ``/map`` (``sensor_msgs/PointCloud2``): ``map.ply`` once, at the bag's first stamp, with
  transient-local QoS (a late subscriber still gets it); fields ``x y z`` float32, ``rgb``
  (float32 holding ``0x00RRGGBB``, the PCL convention RViz and Foxglove read) and
  ``agent_id`` uint32.

**Stamps** are the input's timestamps as the TUM files hold them (a keyframe's: its frame's,
:func:`keyframe_stamps`); each message is logged at its stamp. Agents recorded with separate
clocks keep their own time bases.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.errors import InputError
from como3r.geometry.lie import se3_compose, se3_inverse, se3_log
from como3r.io.keyframe_data import read_keyframe_data
from como3r.io.ply import read_ply
from como3r.io.run_graph import RunGraph, RunKeyframe, keyframe_intrinsics
from como3r.io.tum import Trajectory, read_tum

#: the world frame's id
MAP_FRAME = "map"
#: rosbag2 metadata version written (8: read by rosbag2 since Iron; 9 only since Jazzy)
BAG_VERSION = 8
#: a keyframe's time in graph.json and its frame's in the TUM file (rounded to the
#: microsecond) agree to this many seconds
STAMP_TOLERANCE = 1e-5


def camera_frame(agent: int) -> str:
    """Frame id of agent ``agent``'s camera (optical convention)."""
    return f"agent_{agent}/camera_optical"


def agent_topics(agent: int) -> dict[str, str]:
    """The per-agent topics: ``odometry``, ``keyframes``, ``image``, ``camera_info``."""
    return {
        "odometry": f"/agent_{agent}/odometry",
        "keyframes": f"/agent_{agent}/keyframes",
        "image": f"/agent_{agent}/camera/image/compressed",
        "camera_info": f"/agent_{agent}/camera/camera_info",
    }


def read_trajectories(run: Path, agents: list[int]) -> dict[int, Trajectory]:
    """``trajectories/agent_<a>.txt`` of each agent.

    Raises:
        InputError: one is missing, malformed, or has a negative timestamp (no ROS time).
    """
    trajectories = {}
    for agent in agents:
        path = run / "trajectories" / f"agent_{agent}.txt"
        trajectory = read_tum(path)
        if float(trajectory.timestamps[0]) < 0:
            raise InputError(f"{path}: negative timestamps have no ROS time")
        trajectories[agent] = trajectory
    return trajectories


def write_ros2_bag(
    run: Path, graph: RunGraph, out: Path, step: Callable[[], None] = lambda: None
) -> dict[str, int]:
    """Write the bag into the existing, empty staging folder ``out`` (see the module docstring).

    ``rosbags`` creates the bag folder itself, so it is written to ``out/<out's final name>``
    (its MCAP file named after it) and its files are moved up into ``out``; the paths in
    ``metadata.yaml`` are relative, so they stay valid.

    Returns:
        counts: ``messages``, ``frames`` (tracked, all agents), ``keyframes``, ``points``.
    """
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    agents = sorted({k.agent for k in graph.keyframes})
    trajectories = read_trajectories(run, agents)
    cloud = read_ply(run / "map.ply")
    messages: list[tuple[int, int, str, Callable[[], Any]]] = []  # (ns, order, topic, make)

    def add(stamp: float, topic: str, make: Callable[[], Any]) -> None:
        messages.append((_nanoseconds(stamp), len(messages), topic, make))

    topics = {"/tf": "tf2_msgs/msg/TFMessage", "/map": "sensor_msgs/msg/PointCloud2"}
    for agent in agents:
        names = agent_topics(agent)
        topics.update(
            {
                names["odometry"]: "nav_msgs/msg/Odometry",
                names["keyframes"]: "nav_msgs/msg/Path",
                names["image"]: "sensor_msgs/msg/CompressedImage",
                names["camera_info"]: "sensor_msgs/msg/CameraInfo",
            }
        )
        trajectory = trajectories[agent]
        twists = _twists(trajectory)
        for i, stamp in enumerate(trajectory.timestamps.tolist()):
            pose = trajectory.T_WC[i].numpy()
            add(stamp, "/tf", lambda s=stamp, a=agent, p=pose: _tf(store, s, a, p))
            add(
                stamp,
                names["odometry"],
                lambda s=stamp, a=agent, p=pose, v=twists[i]: _odometry(store, s, a, p, v),
            )
        keyframes = [k for k in graph.keyframes if k.agent == agent]
        stamps = keyframe_stamps(keyframes, trajectory, run)
        for n, (kf, stamp) in enumerate(zip(keyframes, stamps)):
            add(
                stamp,
                names["keyframes"],
                lambda s=stamp, ks=keyframes[: n + 1], ss=stamps[: n + 1]: _path(store, s, ks, ss),
            )
            add(stamp, names["image"], lambda k=kf, s=stamp: _image(store, run, k, s))
            add(stamp, names["camera_info"], lambda k=kf, s=stamp: _camera_info(store, run, k, s))
    first = min(m[0] for m in messages) * 1e-9
    add(first, "/map", lambda: _cloud(store, first, cloud))
    messages.sort(key=lambda m: m[:2])

    bag = out / out.name.removesuffix(".partial")
    latched = _latched_qos()
    writer = Writer(bag, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    # zstd inside the MCAP file's chunks (rosbag2's own MCAP presets do the same; players and
    # Foxglove read it as an uncompressed bag)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connections = {
            topic: writer.add_connection(
                topic,
                msgtype,
                typestore=store,
                offered_qos_profiles=latched if topic == "/map" else (),
            )
            for topic, msgtype in topics.items()
        }
        for ns, _, topic, make in messages:
            writer.write(connections[topic], ns, store.serialize_cdr(make(), topics[topic]))
            if topic.endswith("/camera_info"):  # the last of a keyframe's three messages
                step()
    for path in bag.iterdir():
        shutil.move(path, out / path.name)
    bag.rmdir()
    return {
        "messages": len(messages),
        "frames": sum(len(t) for t in trajectories.values()),
        "keyframes": len(graph.keyframes),
        "points": len(cloud),
    }


def keyframe_stamps(keyframes: list[RunKeyframe], trajectory: Trajectory, run: Path) -> list[float]:
    """Each keyframe's stamp: the timestamp of its frame in the agent's trajectory file.

    ``graph.json`` keeps a keyframe's time as read, the TUM file to the microsecond; taking
    the file's, an image's stamp is exactly one of ``/tf``'s, so a viewer looking its camera up
    in ``/tf`` at the last frame does not extrapolate past the last transform.

    Raises:
        InputError: a keyframe without a tracked frame within :data:`STAMP_TOLERANCE`.
    """
    times = trajectory.timestamps
    stamps = []
    for kf in keyframes:
        i = int(np.argmin(np.abs(times - kf.timestamp)))
        if abs(times[i] - kf.timestamp) > STAMP_TOLERANCE:
            raise InputError(
                f"{run}: keyframe {kf.kf_id} of agent {kf.agent} "
                f"({kf.timestamp!r} s) has no pose in trajectories/"
                f"agent_{kf.agent}.txt"
            )
        stamps.append(float(times[i]))
    return stamps


def _nanoseconds(stamp: float) -> int:
    return int(round(stamp * 1e9))


def _latched_qos() -> list[Any]:
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    return [
        Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            QosTime(0, 0),
            QosTime(0, 0),
            QosLiveliness.AUTOMATIC,
            QosTime(0, 0),
            False,
        )
    ]


def _header(store: Any, stamp: float, frame_id: str) -> Any:
    types = store.types
    ns = _nanoseconds(stamp)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id=frame_id,
    )


def _pose(store: Any, T: np.ndarray) -> Any:
    """``geometry_msgs/Pose`` of a ``(7,)`` pose ``(t, q_xyzw)``."""
    types = store.types
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(T[0]), y=float(T[1]), z=float(T[2])),
        orientation=_quaternion(store, T[3:7]),
    )


def _quaternion(store: Any, q: np.ndarray) -> Any:
    return store.types["geometry_msgs/msg/Quaternion"](
        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
    )


def _vector(store: Any, v: np.ndarray) -> Any:
    return store.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _tf(store: Any, stamp: float, agent: int, T: np.ndarray) -> Any:
    types = store.types
    transform = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, stamp, MAP_FRAME),
        child_frame_id=camera_frame(agent),
        transform=types["geometry_msgs/msg/Transform"](
            translation=_vector(store, T[:3]), rotation=_quaternion(store, T[3:7])
        ),
    )
    return types["tf2_msgs/msg/TFMessage"](transforms=[transform])


def _twists(trajectory: Trajectory) -> np.ndarray:
    """``(N, 6)`` body twists ``(v, ω)`` in each frame's camera: ``log(T_k^-1 T_k+1) / Δt``
    (the last frame takes its predecessor's; zero for a single frame). Timestamps strictly
    increase (:func:`~como3r.io.tum.read_tum`)."""
    T = trajectory.T_WC[:, :7].to(torch.float64)
    twists = np.zeros((len(T), 6))
    if len(T) < 2:
        return twists
    dt = np.diff(trajectory.timestamps.astype(np.float64))
    twists[:-1] = se3_log(se3_compose(se3_inverse(T[:-1]), T[1:])).numpy() / dt[:, None]
    twists[-1] = twists[-2]
    return twists


def _odometry(store: Any, stamp: float, agent: int, T: np.ndarray, twist: np.ndarray) -> Any:
    types = store.types
    zero = np.zeros(36, dtype=np.float64)
    return types["nav_msgs/msg/Odometry"](
        header=_header(store, stamp, MAP_FRAME),
        child_frame_id=camera_frame(agent),
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=_pose(store, T), covariance=zero),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=_vector(store, twist[:3]), angular=_vector(store, twist[3:])
            ),
            covariance=zero,
        ),
    )


def _path(store: Any, stamp: float, keyframes: list[RunKeyframe], stamps: list[float]) -> Any:
    types = store.types
    poses = [
        types["geometry_msgs/msg/PoseStamped"](
            header=_header(store, s, MAP_FRAME), pose=_pose(store, k.T_WC[:7])
        )
        for k, s in zip(keyframes, stamps)
    ]
    return types["nav_msgs/msg/Path"](header=_header(store, stamp, MAP_FRAME), poses=poses)


def _image(store: Any, run: Path, kf: RunKeyframe, stamp: float) -> Any:
    data = read_keyframe_data(run, kf.agent, kf.kf_id)
    data.image()  # readable and of the pointmap's size, else a clear InputError
    return store.types["sensor_msgs/msg/CompressedImage"](
        header=_header(store, stamp, camera_frame(kf.agent)),
        format="png",
        data=np.frombuffer(data.image_path.read_bytes(), dtype=np.uint8),
    )


def _camera_info(store: Any, run: Path, kf: RunKeyframe, stamp: float) -> Any:
    pin = keyframe_intrinsics(read_keyframe_data(run, kf.agent, kf.kf_id))
    K = np.array([pin.fx, 0.0, pin.cx, 0.0, pin.fy, pin.cy, 0.0, 0.0, 1.0])
    P = np.array([pin.fx, 0.0, pin.cx, 0.0, 0.0, pin.fy, pin.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    types = store.types
    return types["sensor_msgs/msg/CameraInfo"](
        header=_header(store, stamp, camera_frame(kf.agent)),
        height=pin.height,
        width=pin.width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=K,
        r=np.eye(3).ravel(),
        p=P,
        binning_x=0,
        binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


#: one PointCloud2 point: 20 bytes, little-endian
POINT_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("agent_id", "<u4")]
)


def _cloud(store: Any, stamp: float, cloud: np.ndarray) -> Any:
    """``sensor_msgs/PointCloud2`` of ``map.ply``'s structured vertices (``rgb`` written as
    the uint32 bits of the float32 field it is declared as)."""
    points = np.zeros(len(cloud), dtype=POINT_DTYPE)
    for axis in "xyz":
        points[axis] = cloud[axis]
    points["rgb"] = (
        (cloud["red"].astype(np.uint32) << 16)
        | (cloud["green"].astype(np.uint32) << 8)
        | cloud["blue"].astype(np.uint32)
    )
    points["agent_id"] = cloud["agent_id"]
    types = store.types
    field = types["sensor_msgs/msg/PointField"]
    float32, uint32 = field.FLOAT32, field.UINT32
    fields = [
        field(name=name, offset=POINT_DTYPE.fields[name][1], datatype=kind, count=1)
        for name, kind in (
            ("x", float32),
            ("y", float32),
            ("z", float32),
            ("rgb", float32),
            ("agent_id", uint32),
        )
    ]
    xyz = np.stack([points["x"], points["y"], points["z"]], axis=1)
    return types["sensor_msgs/msg/PointCloud2"](
        header=_header(store, stamp, MAP_FRAME),
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=POINT_DTYPE.itemsize,
        row_step=POINT_DTYPE.itemsize * len(points),
        data=np.frombuffer(points.tobytes(), dtype=np.uint8),
        is_dense=bool(np.isfinite(xyz).all()),
    )
