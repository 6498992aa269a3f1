"""Tiny ROS logs written by the tests themselves with the ``rosbags`` writers: a ROS 1
``.bag`` and ROS 2 bag folders in SQLite 3 and MCAP storage."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from .layouts import HEIGHT, WIDTH, pixels

#: how each kind of log is written: ROS 1 bag, ROS 2 bag in SQLite 3, ROS 2 bag in MCAP
KINDS = ("ros1", "sqlite3", "mcap")
#: camera_info K (fx, fy, cx, cy) of the test images
CALIB = (30.0, 31.0, 15.5, 11.5)
#: frame i is stamped 100 + i / 20 seconds (20 Hz) and logged 3 ms later
FIRST_STAMP_NS = 100_000_000_000
PERIOD_NS = 50_000_000
LOG_DELAY_NS = 3_000_000

#: builds a message of a typestore
Build = Callable[[Any], Any]


@dataclass(frozen=True)
class Message:
    """One message to write: topic, type, log time [ns] and how to build it."""

    topic: str
    msgtype: str
    log_time: int
    build: Build


def stamp_ns(i: int) -> int:
    return FIRST_STAMP_NS + i * PERIOD_NS


def _header(store: Any, ns: int, seq: int = 0) -> Any:
    T = store.types
    time = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    fields = store.fielddefs["std_msgs/msg/Header"][1]
    extra = {"seq": seq} if any(name == "seq" for name, _ in fields) else {}
    return T["std_msgs/msg/Header"](stamp=time, frame_id="camera", **extra)


def raw_image(rgb: np.ndarray, encoding: str, stamp: int, padding: int = 0) -> Build:
    """An Image message of ``(H, W, 3)`` RGB pixels in ``encoding`` (``rgb8``, ``bgr8``,
    ``mono8``: the red channel, ``16UC1``: red * 256), rows padded by ``padding`` bytes."""

    def build(store: Any) -> Any:
        if encoding == "bgr8":
            data = rgb[..., ::-1]
        elif encoding == "mono8":
            data = rgb[..., :1]
        elif encoding == "16UC1":
            data = (rgb[..., :1].astype("<u2") * 256).view(np.uint8)
        else:
            data = rgb
        rows = np.ascontiguousarray(data).reshape(rgb.shape[0], -1)
        rows = np.concatenate([rows, np.zeros((rows.shape[0], padding), np.uint8)], axis=1)
        return store.types["sensor_msgs/msg/Image"](
            header=_header(store, stamp),
            height=rgb.shape[0],
            width=rgb.shape[1],
            encoding=encoding,
            is_bigendian=0,
            step=rows.shape[1],
            data=rows.ravel(),
        )

    return build


def compressed_image(rgb: np.ndarray, fmt: str, stamp: int) -> Build:
    """A CompressedImage message: ``rgb`` encoded as ``.png`` or ``.jpg``; ``fmt`` as sent."""
    suffix = ".jpg" if "jpeg" in fmt else ".png"
    ok, encoded = cv2.imencode(suffix, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok

    def build(store: Any) -> Any:
        return store.types["sensor_msgs/msg/CompressedImage"](
            header=_header(store, stamp), format=fmt, data=encoded.ravel()
        )

    return build


def camera_info(
    calib: tuple[float, float, float, float] = CALIB,
    distortion: tuple[float, ...] = (),
    model: str = "plumb_bob",
    size: tuple[int, int] = (WIDTH, HEIGHT),
    P: tuple[float, float, float, float] | None = None,
) -> Build:
    """A CameraInfo message (ROS 1 field names K D R P, ROS 2 k d r p)."""
    fx, fy, cx, cy = calib
    px, py, pcx, pcy = P if P is not None else calib

    def build(store: Any) -> Any:
        T = store.types
        names = [name for name, _ in store.fielddefs["sensor_msgs/msg/CameraInfo"][1]]
        upper = "K" in names
        values = {
            "k": np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
            "d": np.array(distortion, dtype=np.float64),
            "r": np.eye(3).ravel(),
            "p": np.array([px, 0, pcx, 0, 0, py, pcy, 0, 0, 0, 1, 0], dtype=np.float64),
        }
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return T["sensor_msgs/msg/CameraInfo"](
            header=_header(store, FIRST_STAMP_NS),
            height=size[1],
            width=size[0],
            distortion_model=model,
            binning_x=0,
            binning_y=0,
            roi=roi,
            **{(k.upper() if upper else k): v for k, v in values.items()},
        )

    return build


def image_stream(
    topic: str, n: int, encoding: str = "rgb8", start: int = 0, compressed: str = ""
) -> list[Message]:
    """``n`` frames of :func:`~.layouts.pixels` (``start`` on) on ``topic``, raw in
    ``encoding`` or, with ``compressed`` (``png``, ``jpeg``), as CompressedImage."""
    messages = []
    for i in range(start, start + n):
        stamp = stamp_ns(i)
        if compressed:
            messages.append(
                Message(
                    topic,
                    "sensor_msgs/msg/CompressedImage",
                    stamp + LOG_DELAY_NS,
                    compressed_image(pixels(i), compressed, stamp),
                )
            )
        else:
            messages.append(
                Message(
                    topic,
                    "sensor_msgs/msg/Image",
                    stamp + LOG_DELAY_NS,
                    raw_image(pixels(i), encoding, stamp),
                )
            )
    return messages


def write_log(
    path: Path, kind: str, messages: list[Message], empty_topics: tuple[tuple[str, str], ...] = ()
) -> Path:
    """Write ``messages`` (in log-time order) as a ``kind`` log at ``path`` (a ``.bag`` file
    for ``ros1``, a bag folder otherwise); ``empty_topics`` ``(topic, type)`` get a
    connection and no message. Returns ``path``."""
    ros1 = kind == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        writer: Any = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with writer:
        connections: dict[str, Any] = {}
        for topic, msgtype in [*((m.topic, m.msgtype) for m in messages), *empty_topics]:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
        for message in sorted(messages, key=lambda m: m.log_time):
            writer.write(
                connections[message.topic],
                message.log_time,
                serialize(message.build(store), message.msgtype),
            )
    return path


def log_path(root: Path, kind: str, name: str = "log") -> Path:
    """Where :func:`write_log` writes a ``kind`` log named ``name`` in ``root``."""
    return root / (f"{name}.bag" if kind == "ros1" else name)
