"""Tests of como3r.data.readers.camera: live inputs through cv2.VideoCapture, their
newest-frame-only drop policy and how a stream ends (a video file written here plays the
camera; a scripted capture stands in where timing must be exact)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from como3r.data.readers.camera import (
    CameraInput,
    CameraSource,
    camera_schedule,
    interrupt_ends_streams,
    is_stream_url,
    open_camera,
    parse_source,
)

from .layouts import input_error

WIDTH, HEIGHT = 32, 24
#: frame i of the test video is a flat grey of level LEVEL * i (JPEG keeps it within +-2)
LEVEL = 4


def write_video(path: Path, n: int) -> Path:
    """An MJPG ``.avi`` of ``n`` flat frames whose grey level says their number."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (WIDTH, HEIGHT))
    assert writer.isOpened()
    for i in range(n):
        writer.write(np.full((HEIGHT, WIDTH, 3), LEVEL * i, np.uint8))
    writer.release()
    return path


def number(image: np.ndarray) -> int:
    """The frame number of a decoded frame of :func:`write_video`."""
    return int(round(float(image.mean()) / LEVEL))


class ScriptedCapture:
    """A VideoCapture stand-in: frame i is read when ``release_frames`` lets it through, so a
    test decides exactly which frames arrive while the consumer is busy."""

    def __init__(self, n: int | None) -> None:
        self.n, self.read_count, self.released = n, 0, False
        self.allowed = threading.Semaphore(0)

    def release_frames(self, count: int) -> None:
        for _ in range(count):
            self.allowed.release()

    def read(self) -> tuple[bool, np.ndarray | None]:
        if not self.allowed.acquire(timeout=1.0):  # nothing more let through: the end
            return False, None
        if self.n is not None and self.read_count >= self.n:
            return False, None
        self.read_count += 1
        return True, np.full((HEIGHT, WIDTH, 3), self.read_count, np.uint8)

    def release(self) -> None:
        self.released = True


def scripted(
    n: int | None = None, max_frames: int | None = None
) -> tuple[CameraInput, ScriptedCapture]:
    """A :class:`CameraInput` over a :class:`ScriptedCapture` whose first frame is 0."""
    capture = ScriptedCapture(n)
    first = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    return CameraInput(CameraSource("scripted", max_frames), capture, first, 30.0), capture


def wait_until(condition, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.002)


def test_a_busy_consumer_gets_the_newest_frame_and_the_others_are_counted():
    camera, capture = scripted(n=9)  # frame 0, then 1..9 as they are let through
    assert camera.take() is True and number(camera.load_frame(0).image) == 0
    capture.release_frames(4)  # frames 1-4 arrive while SLAM works on frame 0
    wait_until(lambda: camera.received == 5)
    assert camera.take() is True
    frame = camera.load_frame(1)
    assert frame.index == 1 and frame.image[0, 0, 0] == 4  # the newest; 1, 2, 3 dropped
    assert camera.dropped == 3 and camera.taken == 2
    assert camera.take(timeout=0.01) is False  # nothing new yet
    capture.release_frames(20)  # the rest, then the end of the stream
    wait_until(lambda: camera._ended)
    assert camera.take() is True and camera.load_frame(2).image[0, 0, 0] == 9
    assert camera.take() is None  # ended
    report = camera.stop()
    assert report == (
        "scripted: 3 frames processed, 7 dropped while SLAM was busy (queue of "
        "one, the newest kept), 10 read"
    )
    assert capture.released and camera.stop() == report  # once
    with pytest.raises(IndexError, match="frame 1 is not the one taken last"):
        camera.load_frame(1)


def test_a_slow_consumer_of_a_video_played_live_drops_frames(tmp_path):
    """The video played through the camera path at its 30 Hz: a consumer that takes 100 ms
    per frame sees about every third frame, in order; the others are counted as dropped."""
    video = write_video(tmp_path / "stream.avi", 30)
    camera = open_camera(parse_source(str(video)))
    assert camera.image_size == (WIDTH, HEIGHT) and camera.num_frames is None
    assert camera.name == "stream" and camera.calib is None and not camera.has_depth
    assert camera.fps == pytest.approx(30)
    seen, stamps, start = [], [], time.monotonic()
    for frame in camera.frames():
        seen.append(number(frame.image))
        stamps.append(frame.timestamp)
        time.sleep(0.1)
    assert time.monotonic() - start > 0.9  # played at 30 Hz, not as fast as it decodes
    report = camera.stop()
    assert camera.received == 30 and seen[0] == 0 and seen == sorted(set(seen))
    assert camera.dropped >= 10 and len(seen) == camera.taken <= 15
    # every frame read was either processed or dropped, but the one waiting at the end
    assert camera.taken + camera.dropped in (29, 30)
    assert np.all(np.diff(stamps) > 0) and abs(stamps[0] - time.time()) < 60
    assert f"{camera.taken} frames processed, {camera.dropped} dropped" in report


def test_max_frames_ends_the_stream(tmp_path):
    camera = open_camera(parse_source(str(write_video(tmp_path / "v.avi", 30)), max_frames=3))
    assert [f.index for f in camera.frames()] == [0, 1, 2]
    assert camera.take() is None and "3 frames processed" in camera.stop()


def test_stop_ends_a_stream_that_never_ends():
    camera, capture = scripted(n=None)
    capture.release_frames(3)
    assert camera.take() is True
    camera.stop()
    assert camera.take() is None and list(camera.frames()) == []


@pytest.mark.parametrize("first", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_the_first_ctrl_c_ends_the_streams_and_the_second_interrupts(first):
    camera, capture = scripted(n=None)
    terminate = signal.getsignal(signal.SIGTERM)
    with interrupt_ends_streams():
        assert camera.take() is True
        os.kill(os.getpid(), first)
        capture.release_frames(2)
        assert camera.take() is None  # ended, not interrupted
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1)  # the signal arrives between two bytecodes
    camera.stop()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGTERM) is terminate
    other, _ = scripted(n=None)  # the next run's streams are not ended by this one's Ctrl-C
    assert other.take() is True
    other.stop()


def test_the_schedule_takes_turns_and_ends_with_the_last_stream():
    (a, capture_a), (b, capture_b) = scripted(n=1), scripted(n=3)
    capture_a.release_frames(5)
    capture_b.release_frames(5)
    order = []
    for k, index in camera_schedule([a, b]):
        order.append((k, index))
        [a, b][k].load_frame(index)
        time.sleep(0.01)  # SLAM at work: the cameras deliver meanwhile
    assert order[:2] == [(0, 0), (1, 0)]
    assert [i for k, i in order if k == 0] == list(range(a.taken))
    assert [i for k, i in order if k == 1] == list(range(b.taken))
    assert a._ended and b._ended
    a.stop()
    b.stop()


def test_sources_and_what_is_refused(tmp_path):
    assert parse_source("0") == CameraSource(0)
    assert parse_source(" 2 ", max_frames=5) == CameraSource(2, 5)
    assert parse_source("rtsp://10.0.0.2:554/live").device == "rtsp://10.0.0.2:554/live"
    assert is_stream_url("HTTP://cam/video.mjpg") and is_stream_url(str(Path("rtsp://h/x")))
    assert not is_stream_url("/data/rtsp/x.avi") and not is_stream_url("C:/videos/x.avi")
    input_error(
        "--camera cam0: expected a device index (0), a stream URL (rtsp://, rtsps://, "
        "rtmp://, http://...) or a video file",
        parse_source,
        "cam0",
    )
    input_error("--max-frames must be at least 1, got 0", parse_source, "0", max_frames=0)
    input_error(
        "camera 99: cannot open (no such device, or it is in use)", open_camera, CameraSource(99)
    )
    (tmp_path / "noise.avi").write_bytes(b"not a video")
    input_error(
        "noise.avi: cannot open (unreachable, or not a stream OpenCV can decode)",
        open_camera,
        parse_source(str(tmp_path / "noise.avi")),
    )
