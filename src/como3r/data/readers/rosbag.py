"""ROS logs: ROS 1 bags, ROS 2 bags (SQLite 3 or MCAP storage), read through ``rosbags``, a
pure-Python reader of every rosbag version that needs no ROS installation
(https://ternaris.gitlab.io/rosbags/).

What this reader opens (the ``rosbag`` format):

* a ROS 1 ``.bag`` file;
* a ROS 2 bag folder as ``ros2 bag record`` writes it: ``metadata.yaml`` with its ``.db3``
  (``sqlite3`` storage) or ``.mcap`` (``mcap`` storage) files, or one of those files (its
  folder is opened). ``rosbags`` reads MCAP only as the storage of such a folder, through the
  ``metadata.yaml`` that names its files and topics: a bare ``.mcap`` file without
  ``metadata.yaml`` beside it is refused with an :class:`InputError` that says so.

Frames come from one image topic, ``sensor_msgs/msg/Image`` (encodings ``rgb8``, ``bgr8``,
``mono8``, ``rgba8``, ``bgra8``; depth and other 16-bit or float encodings such as ``16UC1``
are refused) or ``sensor_msgs/msg/CompressedImage`` (JPEG or PNG, decoded with
``cv2.imdecode``; ``compressedDepth`` is refused). ``topic`` (``--topic`` /
``input.topic``) names it; without it the log's one image topic is taken, and a log with
several is an :class:`InputError` listing them.

* timestamps: each message's ``header.stamp``; a message whose stamp is zero (a publisher
  that leaves the header empty) takes its log time, the time the recorder received it.
  They must increase strictly, in log order.
* intrinsics: the first ``sensor_msgs/msg/CameraInfo`` message of ``camera_info`` in the
  image topic's namespace (``/cam/camera_info`` beside ``/cam/image_raw`` and
  ``/cam/image_raw/compressed``): ``fx, fy, cx, cy`` from ``K`` (``k`` in ROS 2), and a
  ``plumb_bob`` or ``rational_polynomial`` distortion ``D`` undone as each frame is read,
  as :mod:`~como3r.data.readers.euroc` does (OpenCV, the same ``K`` before and after). A
  rectified topic (its last name starts with ``image_rect``) is already undistorted and
  its camera matrix is ``P``'s left 3x3, as in ROS's ``image_proc``. A ``K`` of zeros (an
  uncalibrated camera) leaves the input uncalibrated; other distortion models are refused.
* no ground truth and no depth.

Opening reads the topic's messages once, in log order, for their stamps, sizes and
encodings (the first compressed frame is decoded for its size); pixels are decoded lazily by
:meth:`RosbagInput.load_frame` (which finds its message by log time) and
:meth:`RosbagInput.frames` (one sequential pass).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from como3r.data.agent_input import AgentInput, Frame
from como3r.data.readers.undistort import undistort
from como3r.errors import InputError
from como3r.io.tum import Trajectory

logger = logging.getLogger(__name__)

EXPECTED = "a ROS 1 .bag file, or a ROS 2 bag folder (metadata.yaml with its .db3 or .mcap files)"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: ``sensor_msgs/Image`` encodings read, and the OpenCV conversion to RGB (None: as is)
ENCODINGS = {
    "rgb8": (3, None),
    "bgr8": (3, cv2.COLOR_BGR2RGB),
    "mono8": (1, cv2.COLOR_GRAY2RGB),
    "rgba8": (4, cv2.COLOR_RGBA2RGB),
    "bgra8": (4, cv2.COLOR_BGRA2RGB),
}
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
_STORAGE_SUFFIXES = (".db3", ".mcap")


def matches(path: Path) -> bool:
    """A ``.bag`` or ``.mcap`` file, a ``.db3`` file beside a ``metadata.yaml``, or a folder
    with ``metadata.yaml`` and a ``.db3`` or ``.mcap`` file."""
    if path.is_file():
        suffix = path.suffix.lower()
        return suffix in (".bag", ".mcap") or (
            suffix == ".db3" and (path.parent / "metadata.yaml").is_file()
        )
    return (
        path.is_dir()
        and (path / "metadata.yaml").is_file()
        and any(p.suffix.lower() in _STORAGE_SUFFIXES for p in path.iterdir())
    )


@dataclass(frozen=True, eq=False)
class RosbagInput(AgentInput):
    """An :class:`AgentInput` read from one image topic of a ROS log.

    Attributes:
        bag: what ``rosbags`` opens: the ``.bag`` file or the ROS 2 bag folder.
        topic: the image topic.
        log_times: ``(N,)`` int64 nanoseconds at which the recorder logged each frame.
        ranks: ``(N,)`` int64 position of each frame among the topic's messages of the same
            log time (0 almost always).
        distortion: OpenCV ``(k1, k2, p1, p2, k3[, k4, k5, k6])`` undone on every frame, or
            empty.
    """

    bag: Path = Path()
    topic: str = ""
    log_times: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    ranks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    distortion: tuple[float, ...] = ()
    _local: threading.local = field(default_factory=threading.local, repr=False)

    @property
    def frames_are_files(self) -> bool:
        """False: the frames are messages inside the log (see :class:`AgentInput`)."""
        return False

    def frames(self) -> Iterator[Frame]:
        """Every frame in order, in one sequential pass over the log."""
        with contextlib.closing(_open_reader(self.bag)) as reader:
            for i, (connection, _, raw) in enumerate(_messages(reader, self.bag, self.topic)):
                if i >= self.num_frames:
                    return
                yield self._assemble(i, self._image(_deserialize(reader, raw, connection), i))

    def load_frame(self, i: int) -> Frame:
        """Decode frame ``i``: its message is found by its log time (random access)."""
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range for {self.num_frames} frames")
        reader = getattr(self._local, "reader", None)
        if reader is None:  # one open reader per thread: SQLite connections stay in theirs
            reader = self._local.reader = _open_reader(self.bag)
        stamp = int(self.log_times[i])
        found = list(_messages(reader, self.bag, self.topic, start=stamp, stop=stamp + 1))
        if len(found) <= self.ranks[i]:
            raise InputError(f"{self.bag}: message {i} of {self.topic} is gone from the log")
        connection, _, raw = found[int(self.ranks[i])]
        return self._assemble(i, self._image(_deserialize(reader, raw, connection), i))

    def _image(self, msg: Any, i: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB of message ``i``, undistorted."""
        image = decode_image(msg, f"{self.bag}: {self.topic} message {i}")
        if (image.shape[1], image.shape[0]) != self.image_size:
            raise InputError(
                f"{self.bag}: {self.topic} message {i} is {image.shape[1]}x"
                f"{image.shape[0]}, the first is {self.image_size[0]}x"
                f"{self.image_size[1]}"
            )
        return undistort(image, self.calib, self.distortion)


def open_sequence(path: Path, fps: float, topic: str = "") -> RosbagInput:
    """Open one image topic of a ROS log (module docstring); ``fps`` is recorded only.

    Args:
        path: ``.bag`` file, ROS 2 bag folder, or a ``.db3`` / ``.mcap`` file in one.
        fps: frame rate recorded in the input (timestamps come from the log).
        topic: the image topic; empty: the log's only image topic.

    Raises:
        InputError: a log ``rosbags`` cannot read (a bare ``.mcap`` file among them), no
            such topic, a topic of another type or without messages, several image topics
            and no ``topic``, an unsupported encoding or distortion model, stamps that do not
            increase, images of different sizes, a ``CameraInfo`` of another size.
    """
    bag = _bag(path)
    with contextlib.closing(_open_reader(bag)) as reader:
        topic = _choose_topic(bag, reader.topics, topic)
        log_times, stamps, sizes, first = [], [], set(), None
        for connection, log_time, raw in _messages(reader, bag, topic):
            msg = _deserialize(reader, raw, connection)
            where = f"{bag}: {topic} message {len(stamps)}"
            if first is None:
                first = decode_image(msg, where)
            else:
                _check_encoding(msg, where)
            if hasattr(msg, "width"):
                sizes.add((int(msg.width), int(msg.height)))
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            log_times.append(log_time)
            stamps.append(stamp if stamp != 0 else log_time)
        if first is None:
            raise InputError(f"{bag}: topic {topic} has no messages")
        image_size = (first.shape[1], first.shape[0])
        if len(sizes) > 1:
            raise InputError(
                f"{bag}: {topic} holds images of sizes "
                f"{', '.join(f'{w}x{h}' for w, h in sorted(sizes))}; all frames "
                "of an agent must have one size"
            )
        calib, distortion = _camera_info(bag, reader, topic, image_size)
    nanoseconds = np.array(stamps, dtype=np.int64)
    steps = np.diff(nanoseconds)
    if np.any(steps <= 0):
        bad = int(np.argmax(steps <= 0)) + 1
        before, after = (f"{ns // 10**9}.{ns % 10**9:09d}" for ns in stamps[bad - 1 : bad + 1])
        raise InputError(
            f"{bag}: {topic} stamps are not strictly increasing at message {bad} "
            f"({before} s then {after} s)"
        )
    times = np.array(log_times, dtype=np.int64)
    ranks = np.zeros(len(times), dtype=np.int64)
    for i in range(1, len(times)):
        ranks[i] = ranks[i - 1] + 1 if times[i] == times[i - 1] else 0
    return RosbagInput(
        root=path,
        name=bag.stem if bag.is_file() else bag.resolve().name,
        num_frames=len(times),
        image_size=image_size,
        timestamps=nanoseconds * 1e-9,
        calib=calib,
        groundtruth=None,
        odometry=None,
        has_depth=False,
        has_surface=False,
        fps=float(fps),
        stems=tuple(str(ns) for ns in nanoseconds.tolist()),
        image_paths=(),
        video=None,
        depth_paths=(),
        surface_paths=(),
        format="rosbag",
        bag=bag,
        topic=topic,
        log_times=times,
        ranks=ranks,
        distortion=distortion,
    )


def ground_truth(path: Path) -> tuple[Path, Trajectory]:
    """ROS logs carry no ground truth this reader takes: always an :class:`InputError`."""
    raise InputError(
        f"{path}: a ROS log holds no ground truth como3r reads; give --gt a TUM "
        "trajectory file (timestamp tx ty tz qx qy qz qw)"
    )


def decode_image(msg: Any, where: str) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of an ``Image`` or ``CompressedImage`` message.

    Raises:
        InputError: an unsupported encoding or format, too little data, or compressed bytes
            OpenCV cannot decode; ``where`` names the message.
    """
    channels, conversion = _check_encoding(msg, where)
    if channels == 0:  # compressed
        data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
        if bgr is None:
            raise InputError(f"{where}: cannot decode the {msg.format!r} image")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height == 0 or width == 0 or step < width * channels or len(msg.data) < height * step:
        raise InputError(
            f"{where}: {len(msg.data)} bytes do not hold a {width}x{height} "
            f"{msg.encoding} image of row step {step}"
        )
    rows = np.frombuffer(memoryview(msg.data), dtype=np.uint8)[: height * step]
    pixels = rows.reshape(height, step)[:, : width * channels].reshape(height, width, channels)
    if conversion is None:
        return pixels.copy()
    return cv2.cvtColor(np.ascontiguousarray(pixels), conversion)


def _check_encoding(msg: Any, where: str) -> tuple[int, int | None]:
    """``(channels, conversion)`` of a raw image's encoding; ``(0, None)`` for a JPEG or
    PNG compressed image. Raises :class:`InputError` for anything else."""
    if hasattr(msg, "format"):  # CompressedImage
        kind = str(msg.format).lower()
        if "compresseddepth" in kind:
            raise InputError(
                f"{where}: a compressed depth image ({msg.format!r}), not a colour image"
            )
        if kind and not any(name in kind for name in ("jpeg", "jpg", "png")):
            raise InputError(
                f"{where}: compressed format {msg.format!r} is not supported (jpeg or png)"
            )
        return 0, None
    encoding = str(msg.encoding).lower()
    if encoding not in ENCODINGS:
        what = (
            "a depth or intensity image, not a colour image"
            if encoding.startswith(("mono16", "16u", "16s", "32s", "32f", "64f"))
            else "not supported"
        )
        raise InputError(
            f"{where}: encoding {msg.encoding!r} is {what} (supported: {', '.join(ENCODINGS)})"
        )
    return ENCODINGS[encoding]


def _bag(path: Path) -> Path:
    """What ``rosbags`` opens for ``path``: a ``.bag`` file or a ROS 2 bag folder."""
    if path.is_dir() or path.suffix.lower() == ".bag":
        return path
    if path.suffix.lower() in _STORAGE_SUFFIXES:
        if (path.parent / "metadata.yaml").is_file():
            return path.parent
        raise InputError(
            f"{path}: the rosbags library reads {path.suffix} storage only as part "
            "of a ROS 2 bag folder, with the metadata.yaml that ros2 bag record "
            "writes beside it; there is none in its folder"
        )
    raise InputError(f"{path}: not a ROS log: expected {EXPECTED}")


def _open_reader(bag: Path) -> Any:
    """An open ``rosbags`` AnyReader of ``bag`` (the caller closes it); its errors are
    :class:`InputError`."""
    from rosbags.highlevel import AnyReader  # rosbags is imported only to read a log
    from rosbags.typesys import Stores, get_typestore

    try:  # a ROS 2 bag older than Iron stores no message definitions: take the latest ones
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # the library's errors, whatever their class
        raise InputError(f"{bag}: cannot read the ROS log ({exc})") from None
    return reader


def _messages(
    reader: Any, bag: Path, topic: str, start: int | None = None, stop: int | None = None
) -> Iterator[tuple[Any, int, bytes]]:
    """``(connection, log time [ns], raw bytes)`` of ``topic``'s messages in log order,
    logged in ``[start, stop)``; a log that fails to read is an :class:`InputError`."""
    try:
        yield from reader.messages(reader.topics[topic].connections, start=start, stop=stop)
    except Exception as exc:
        raise InputError(f"{bag}: cannot read {topic} ({exc})") from None


def _deserialize(reader: Any, raw: bytes, connection: Any) -> Any:
    try:
        return reader.deserialize(raw, connection.msgtype)
    except Exception as exc:
        raise InputError(
            f"{reader.paths[0]}: cannot decode a {connection.msgtype} message of "
            f"{connection.topic} ({exc})"
        ) from None


def _choose_topic(bag: Path, topics: dict[str, Any], topic: str) -> str:
    """The image topic: ``topic`` (with or without its leading ``/``), or the only one."""
    images = {name: info for name, info in topics.items() if info.msgtype in (IMAGE, COMPRESSED)}
    listing = (
        ", ".join(
            f"{name} ({info.msgtype}, {info.msgcount} messages)"
            for name, info in sorted(images.items())
        )
        or "none"
    )
    if not topic:
        if len(images) != 1:
            if images:
                raise InputError(
                    f"{bag}: {len(images)} image topics, choose one with --topic: {listing}"
                )
            raise InputError(
                f"{bag}: no image topic ({IMAGE} or {COMPRESSED}); topics: "
                f"{', '.join(sorted(topics)) or 'none'}"
            )
        topic = next(iter(images))
    elif topic not in topics and f"/{topic}" in topics:
        topic = f"/{topic}"
    if topic not in topics:
        raise InputError(f"{bag}: no topic {topic!r}; image topics: {listing}")
    if topics[topic].msgtype not in (IMAGE, COMPRESSED):
        raise InputError(
            f"{bag}: topic {topic} is {topics[topic].msgtype}, not an image topic "
            f"({IMAGE} or {COMPRESSED}); image topics: {listing}"
        )
    if topics[topic].msgcount == 0:
        raise InputError(f"{bag}: topic {topic} has no messages")
    return topic


def _camera_info(
    bag: Path,
    reader: Any,
    topic: str,
    image_size: tuple[int, int],
) -> tuple[tuple[float, float, float, float] | None, tuple[float, ...]]:
    """``(fx, fy, cx, cy)`` or None, and the distortion to undo, from the ``camera_info``
    beside ``topic`` (module docstring)."""
    base = topic.removesuffix("/compressed")
    namespace, _, name = base.rpartition("/")
    info_topic = f"{namespace}/camera_info"
    info = reader.topics.get(info_topic)
    if info is None or info.msgtype != CAMERA_INFO or info.msgcount == 0:
        logger.info("%s: no %s beside %s: uncalibrated", bag, info_topic, topic)
        return None, ()
    connection, _, raw = next(reader.messages(info.connections))
    msg = _deserialize(reader, raw, connection)
    where = f"{bag}: {info_topic}"
    width, height = int(msg.width), int(msg.height)
    if (width or height) and (width, height) != image_size:
        raise InputError(
            f"{where}: the camera is {width}x{height}, the images of {topic} are "
            f"{image_size[0]}x{image_size[1]}"
        )
    rectified = name.startswith("image_rect")
    # ROS 1 names the matrices K, D, P; ROS 2 k, d, p
    matrix = np.asarray(_field(msg, "p" if rectified else "k"), dtype=np.float64)
    columns = 4 if rectified else 3
    fx, fy, cx, cy = matrix[0], matrix[columns + 1], matrix[2], matrix[columns + 2]
    if fx <= 0 or fy <= 0:
        logger.warning(
            "%s: no intrinsics in %s (K is not calibrated): uncalibrated", bag, info_topic
        )
        return None, ()
    coefficients = tuple(float(d) for d in _field(msg, "d"))
    if rectified or not any(coefficients):
        return (float(fx), float(fy), float(cx), float(cy)), ()
    if msg.distortion_model not in DISTORTION_MODELS:
        raise InputError(
            f"{where}: distortion_model {msg.distortion_model!r} is not supported "
            f"(only {', '.join(DISTORTION_MODELS)})"
        )
    if len(coefficients) not in (4, 5, 8):
        raise InputError(
            f"{where}: {len(coefficients)} distortion coefficients for "
            f"{msg.distortion_model} (expected 5 or 8)"
        )
    return (float(fx), float(fy), float(cx), float(cy)), coefficients


def _field(msg: Any, name: str) -> Any:
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


__all__ = ["RosbagInput", "decode_image", "ground_truth", "matches", "open_sequence"]
