"""Live inputs: a camera (device index) or a network stream (``rtsp://``, ``http://``, ...)
read through OpenCV's ``cv2.VideoCapture`` while SLAM runs (``como3r run --camera``).

A live stream has no length and cannot be rewound, so it is not an
:class:`~como3r.data.agent_input.AgentInput`: :class:`CameraInput` offers the same attributes
the run reads (``image_size``, ``calib``, ``groundtruth``, ``has_depth``, ...), with
``num_frames`` None, and hands its frames out once, in order (:meth:`CameraInput.take`,
:meth:`CameraInput.load_frame`, :meth:`CameraInput.frames`).

Frame-drop policy. A reader thread reads the capture as fast as it delivers and keeps only
the newest frame (a queue of one): a frame that arrives before SLAM has taken the previous
one replaces it, and the replaced frame is counted as dropped. SLAM therefore always works on
the latest picture and never falls behind the camera; the cost is that fast motion between
two taken frames is not seen. ``input.subsample`` does not apply (the drop policy is the
subsampling), and the ``input.prefetch_frames`` frames the run encodes ahead are taken
early: set it to 0 for the freshest frame at the price of encoding in line. The counts are
logged and returned by :meth:`CameraInput.stop` at the end of the run (``RunSummary.notes``).

The stream ends at the end of the stream (the capture stops delivering: a file's end, a
closed connection, an unplugged camera), after ``max_frames`` frames taken, at
:meth:`CameraInput.stop`, or on the first Ctrl-C inside :func:`interrupt_ends_streams`; the
run then finishes and writes its outputs as for a recorded input. Timestamps are the
wall-clock time [s since the epoch] at which each frame was read (made strictly increasing).
A video file given as the source plays as if it were live: at its own frame rate (the
container's, else ``input.frame_rate_hz``), as a camera would deliver it, which makes a
recording a repeatable stand-in for a camera (tests, replays). A live input is uncalibrated
and has no depth or ground truth.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from como3r.data.agent_input import Frame
from como3r.errors import InputError

logger = logging.getLogger(__name__)

#: URL schemes read as network streams
STREAM_SCHEMES = ("rtsp", "rtsps", "rtmp", "http", "https", "udp", "tcp", "srt")
#: how long OpenCV may take to open a stream, and to read one frame of it [ms]
TIMEOUT_MS = 10_000
#: how often a wait for frames looks again at a stopped stream [s]
POLL_S = 0.05

#: set by the first Ctrl-C inside :func:`interrupt_ends_streams`: every stream ends
_INTERRUPTED = threading.Event()


@dataclass(frozen=True)
class CameraSource:
    """A live input as ``como3r run --camera`` names it.

    Attributes:
        device: a camera's device index, or a stream URL or video file.
        max_frames: the stream ends after this many frames taken; None: no limit.
    """

    device: int | str
    max_frames: int | None = None

    def __str__(self) -> str:
        return f"camera {self.device}" if isinstance(self.device, int) else str(self.device)


def parse_source(text: str, max_frames: int | None = None) -> CameraSource:
    """The :class:`CameraSource` of a ``--camera`` value: digits are a device index, a
    ``scheme://`` of :data:`STREAM_SCHEMES` a stream URL, an existing file a video.

    Raises:
        InputError: anything else, or a ``max_frames`` below 1.
    """
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--max-frames must be at least 1, got {max_frames}")
    text = text.strip()
    if text.isdigit():
        return CameraSource(int(text), max_frames)
    if is_stream_url(text) or Path(text).is_file():
        return CameraSource(text, max_frames)
    raise InputError(
        f"--camera {text}: expected a device index (0), a stream URL "
        f"({', '.join(f'{s}://' for s in STREAM_SCHEMES[:4])}...) or a video file"
    )


def is_stream_url(text: str) -> bool:
    """``text`` starts with ``scheme://`` of one of :data:`STREAM_SCHEMES`; also the form
    ``scheme:/`` a ``pathlib.Path`` leaves of it."""
    match = re.match(r"([a-zA-Z][a-zA-Z0-9+.-]*):/", text)
    return match is not None and match.group(1).lower() in STREAM_SCHEMES


class CameraInput:
    """An open live input (module docstring); the reader thread runs until :meth:`stop`.

    Attributes:
        source: what was opened.
        root: ``source`` as text; name: ``camera<N>`` or the stream's file or host name.
        num_frames: None (a live stream has no length).
        image_size: ``(W, H)`` of the first frame; fps: the capture's rate, or the default.
        calib, groundtruth, odometry: None; has_depth, has_surface: False;
        format: ``camera``.
        received: frames read from the capture; taken: frames handed to SLAM;
        dropped: frames replaced by a newer one before SLAM took them.
    """

    num_frames = None
    calib = None
    groundtruth = None
    odometry = None
    has_depth = False
    has_surface = False
    format = "camera"

    def __init__(
        self, source: CameraSource, capture: Any, first: np.ndarray, fps: float, paced: bool = False
    ) -> None:
        self.source = source
        self.root = str(source.device)
        self.name = _name(source.device)
        self.image_size = (first.shape[1], first.shape[0])
        self.fps = fps
        self.received, self.taken, self.dropped = 1, 0, 0
        self._capture = capture
        self._lock = threading.Condition()
        self._newest: tuple[np.ndarray, float] | None = (first, time.time())
        self._last: Frame | None = None
        self._last_stamp = -np.inf
        self._ended = False
        self._stop = threading.Event()
        self._report: str | None = None
        self._period = 1.0 / fps if paced else 0.0
        self._thread = threading.Thread(target=self._read, name=f"como3r-{self.name}", daemon=True)
        self._thread.start()

    def take(self, timeout: float = POLL_S) -> bool | None:
        """Take the newest frame for SLAM (it becomes :meth:`load_frame` of index
        ``taken - 1``), waiting up to ``timeout`` seconds for one.

        Returns:
            True: a frame was taken; False: none arrived in time; None: the stream ended.
        """
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._newest is None:
                if self._over():
                    return None
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(min(left, POLL_S))
            if self._stop.is_set() or _INTERRUPTED.is_set():  # a frame read before the end
                return None  # of a stream is still taken; one read before a stop is not
            bgr, stamp = self._newest
            self._newest = None
            self.taken += 1
        stamp = max(stamp, self._last_stamp + 1e-6)  # strictly increasing
        self._last_stamp = stamp
        self._last = Frame(self.taken - 1, stamp, f"{self.taken - 1:06d}", self._rgb(bgr))
        if self.source.max_frames is not None and self.taken >= self.source.max_frames:
            logger.info(
                "%s: %d frames taken (--max-frames): ending the stream", self.source, self.taken
            )
            self._stop.set()
        return True

    def load_frame(self, i: int) -> Frame:
        """The frame taken last, which must be frame ``i``: a live frame is read once."""
        if self._last is None or self._last.index != i:
            taken = "none" if self._last is None else f"frame {self._last.index}"
            raise IndexError(f"{self.source}: frame {i} is not the one taken last ({taken})")
        return self._last

    def frames(self) -> Iterator[Frame]:
        """Every frame taken, until the stream ends (a slow consumer sees frames dropped)."""
        while (taken := self.take()) is not None:
            if taken:
                yield self.load_frame(self.taken - 1)

    def stop(self) -> str:
        """End the stream (if it has not ended), release the capture, and report; again,
        the same report.

        Returns:
            One line: frames read, taken and dropped (logged the first time).
        """
        if self._report is None:
            self._stop.set()
            with self._lock:
                self._lock.notify_all()
            self._thread.join(timeout=TIMEOUT_MS / 1000)
            if not self._thread.is_alive():  # else a read blocks it; the process ends it
                self._capture.release()
            self._report = (
                f"{self.source}: {self.taken} frames processed, {self.dropped} "
                f"dropped while SLAM was busy (queue of one, the newest kept), "
                f"{self.received} read"
            )
            logger.info("%s", self._report)
        return self._report

    def _over(self) -> bool:
        return self._ended or self._stop.is_set() or _INTERRUPTED.is_set()

    def _rgb(self, bgr: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB of a captured frame of the first frame's size."""
        if (bgr.shape[1], bgr.shape[0]) != self.image_size:
            raise InputError(
                f"{self.source}: a frame is {bgr.shape[1]}x{bgr.shape[0]}, the "
                f"first was {self.image_size[0]}x{self.image_size[1]}"
            )
        if bgr.ndim == 2:
            return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _read(self) -> None:
        """The reader thread: keep the newest frame, count the ones it replaces."""
        start = time.monotonic()
        try:
            while not self._over():
                ok, bgr = self._capture.read()
                if not ok:
                    logger.info("%s: end of stream after %d frames", self.source, self.received)
                    break
                if self._period:  # a file plays at its frame rate
                    self._stop.wait(start + self.received * self._period - time.monotonic())
                with self._lock:
                    self.received += 1
                    if self._newest is not None:
                        self.dropped += 1
                    self._newest = (bgr, time.time())
                    self._lock.notify_all()
        finally:
            with self._lock:
                self._ended = True
                self._lock.notify_all()


def open_camera(source: CameraSource, fps: float = 30.0) -> CameraInput:
    """Open a live input and start reading it (module docstring).

    Args:
        source: the device, URL or file, and the frame limit.
        fps: frame rate recorded when the capture reports none.

    Raises:
        InputError: the source cannot be opened or delivers no first frame.
    """
    # OpenCV and FFmpeg would print their own diagnostics next to our one-line InputError
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        if isinstance(source.device, int):
            capture = cv2.VideoCapture(source.device)
        else:  # FFmpeg's timeouts; a camera backend (V4L2) would refuse them
            capture = cv2.VideoCapture(
                source.device,
                cv2.CAP_ANY,
                [
                    cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                    TIMEOUT_MS,
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                    TIMEOUT_MS,
                ],
            )
    finally:
        cv2.utils.logging.setLogLevel(level)
    if not capture.isOpened():
        capture.release()
        what = (
            "no such device, or it is in use"
            if isinstance(source.device, int)
            else "unreachable, or not a stream OpenCV can decode"
        )
        raise InputError(f"{source}: cannot open ({what})")
    ok, first = capture.read()
    if not ok:
        capture.release()
        raise InputError(f"{source}: opened, but delivered no frame")
    rate = capture.get(cv2.CAP_PROP_FPS)
    logger.info("%s: %dx%d, reading live", source, first.shape[1], first.shape[0])
    paced = not isinstance(source.device, int) and not is_stream_url(source.device)
    return CameraInput(source, capture, first, rate if 0 < rate < 1000 else fps, paced)


def camera_schedule(cameras: list[CameraInput]) -> Iterator[tuple[int, int]]:
    """``(camera, frame index)`` of every frame taken, round robin over the cameras that
    have a frame waiting; ends when every stream has ended. Takes the frames (call
    :meth:`CameraInput.load_frame` for each before the next is yielded)."""
    running = list(range(len(cameras)))
    while running:
        for k in list(running):
            taken = cameras[k].take(POLL_S / len(running))
            if taken is None:
                running.remove(k)
            elif taken:
                yield k, cameras[k].taken - 1


@contextlib.contextmanager
def interrupt_ends_streams() -> Iterator[None]:
    """Within the block the first Ctrl-C or SIGTERM ends every live stream (the run then
    finishes and writes its outputs); a second one interrupts as usual. A signal ignored
    when the block starts (SIGINT of a command started in the background) stays ignored.
    Outside the main thread, where Python delivers no signal, it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}

    def on_interrupt(signum: int, frame: Any) -> None:
        if _INTERRUPTED.is_set():
            raise KeyboardInterrupt
        _INTERRUPTED.set()
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        logger.warning(
            "%s: ending the live streams; the run finishes and writes its "
            "outputs (Ctrl-C again to abort)",
            name,
        )

    for signum, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(signum, on_interrupt)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _INTERRUPTED.clear()


def _name(device: int | str) -> str:
    """``camera0``, a file's stem, or the stream URL's host and path as one word."""
    if isinstance(device, int):
        return f"camera{device}"
    if not is_stream_url(device):
        return Path(device).stem
    return re.sub(r"[^A-Za-z0-9]+", "_", device.split(":", 1)[1]).strip("_") or "stream"


__all__ = [
    "CameraInput",
    "CameraSource",
    "camera_schedule",
    "interrupt_ends_streams",
    "is_stream_url",
    "open_camera",
    "parse_source",
]
