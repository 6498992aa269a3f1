"""Tests of como3r.data.readers.rosbag: ROS 1 bags and ROS 2 bags (SQLite 3, MCAP) written
here with the rosbags writers; frames, stamps, topic choice, CameraInfo and the errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from como3r.data.agent import open_agent
from como3r.data.readers import detect_format, read_ground_truth
from como3r.data.readers.undistort import undistort
from como3r.data.split import split_sequence

from .layouts import HEIGHT, WIDTH, input_error, pixels, write_7scenes
from .logs import (
    CALIB,
    KINDS,
    LOG_DELAY_NS,
    Message,
    camera_info,
    image_stream,
    log_path,
    raw_image,
    stamp_ns,
    write_log,
)

TOPIC = "/camera/image_raw"


def _expected(i: int, encoding: str) -> np.ndarray:
    """What frame i decodes to: RGB, or the grey channel made RGB for mono8."""
    rgb = pixels(i)
    return np.repeat(rgb[..., :1], 3, axis=2) if encoding == "mono8" else rgb


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_raw_frames_and_stamps_round_trip(tmp_path, kind, encoding):
    path = write_log(log_path(tmp_path, kind), kind, image_stream(TOPIC, 4, encoding))
    agent = open_agent(path)
    assert agent.format == "rosbag" and agent.topic == TOPIC and agent.num_frames == 4
    assert agent.name == "log" and agent.image_size == (WIDTH, HEIGHT)
    assert agent.calib is None and agent.groundtruth is None and not agent.has_depth
    assert not agent.frames_are_files
    np.testing.assert_allclose(
        agent.timestamps, [stamp_ns(i) * 1e-9 for i in range(4)], rtol=0, atol=1e-9
    )  # the header stamps, not the log times
    assert agent.stems == tuple(str(stamp_ns(i)) for i in range(4))
    frames = list(agent.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for i, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.image, _expected(i, encoding))
        assert frame.timestamp == agent.timestamps[i]
    # random access finds the same message by its log time, from any order
    for i in (3, 0, 2):
        np.testing.assert_array_equal(agent.load_frame(i).image, _expected(i, encoding))


def test_padded_rows_and_a_path_inside_the_bag_folder(tmp_path):
    messages = [
        Message(
            TOPIC,
            "sensor_msgs/msg/Image",
            stamp_ns(i),
            raw_image(pixels(i), "bgr8", stamp_ns(i), padding=5),
        )
        for i in range(2)
    ]
    path = write_log(tmp_path / "log", "sqlite3", messages)
    storage = next(path.glob("*.db3"))
    agent = open_agent(storage)  # the .db3 file opens its bag folder
    assert detect_format(storage) == "rosbag" and agent.bag == path
    np.testing.assert_array_equal(agent.load_frame(1).image, pixels(1))


@pytest.mark.parametrize("kind", KINDS)
def test_compressed_png_and_jpeg(tmp_path, kind):
    path = write_log(
        log_path(tmp_path, kind),
        kind,
        image_stream("/cam/image_raw/compressed", 3, compressed="png")
        + image_stream("/jpeg/image/compressed", 3, compressed="rgb8; jpeg compressed bgr8"),
    )
    agent = open_agent(path, topic="/cam/image_raw/compressed")
    assert agent.image_size == (WIDTH, HEIGHT)
    for i, frame in enumerate(agent.frames()):  # PNG is lossless
        np.testing.assert_array_equal(frame.image, pixels(i))
    jpeg = open_agent(path, topic="/jpeg/image/compressed")
    _, data = cv2.imencode(".jpg", cv2.cvtColor(pixels(2), cv2.COLOR_RGB2BGR))
    decoded = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(jpeg.load_frame(2).image, decoded)  # lossy, in RGB order


def test_a_zero_stamp_takes_the_log_time(tmp_path):
    messages = image_stream(TOPIC, 3)
    zero = Message(
        TOPIC, "sensor_msgs/msg/Image", messages[1].log_time, raw_image(pixels(1), "rgb8", 0)
    )
    path = write_log(tmp_path / "log", "sqlite3", [messages[0], zero, messages[2]])
    stamps = open_agent(path).timestamps
    assert stamps[0] == stamp_ns(0) * 1e-9 and stamps[2] == stamp_ns(2) * 1e-9
    assert stamps[1] == pytest.approx((stamp_ns(1) + LOG_DELAY_NS) * 1e-9, abs=1e-9)


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_several_image_topics_need_topic(tmp_path, kind):
    path = write_log(
        log_path(tmp_path, kind),
        kind,
        image_stream("/left/image_raw", 2)
        + image_stream("/right/image_raw", 3, start=5)
        + [Message("/imu", "sensor_msgs/msg/CameraInfo", 1, camera_info())],
    )
    message = input_error(
        "2 image topics, choose one with --topic: /left/image_raw "
        "(sensor_msgs/msg/Image, 2 messages), /right/image_raw "
        "(sensor_msgs/msg/Image, 3 messages)",
        open_agent,
        path,
    )
    assert "/imu" not in message
    right = open_agent(path, topic="/right/image_raw")
    assert right.num_frames == 3
    np.testing.assert_array_equal(right.load_frame(0).image, pixels(5))
    assert open_agent(path, topic="left/image_raw").topic == "/left/image_raw"  # no leading /


def test_topic_errors(tmp_path):
    path = write_log(
        tmp_path / "log.bag",
        "ros1",
        image_stream(TOPIC, 2) + [Message("/info", "sensor_msgs/msg/CameraInfo", 1, camera_info())],
        empty_topics=(("/empty/image", "sensor_msgs/msg/Image"),),
    )
    input_error(
        "no topic '/nope'; image topics: /camera/image_raw (sensor_msgs/msg/Image, "
        "2 messages), /empty/image (sensor_msgs/msg/Image, 0 messages)",
        open_agent,
        path,
        topic="/nope",
    )
    input_error(
        "topic /info is sensor_msgs/msg/CameraInfo, not an image topic",
        open_agent,
        path,
        topic="/info",
    )
    input_error("topic /empty/image has no messages", open_agent, path, topic="/empty/image")
    only_info = write_log(
        tmp_path / "info.bag",
        "ros1",
        [Message("/info", "sensor_msgs/msg/CameraInfo", 1, camera_info())],
    )
    input_error(
        "no image topic (sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage); topics: /info",
        open_agent,
        only_info,
    )


@pytest.mark.parametrize(
    "encoding, fragment",
    [
        ("16UC1", "encoding '16UC1' is a depth or intensity image, not a colour image"),
        ("yuv422", "encoding 'yuv422' is not supported (supported: rgb8, bgr8, mono8"),
    ],
)
def test_unsupported_encodings_are_refused(tmp_path, encoding, fragment):
    path = write_log(tmp_path / "log", "sqlite3", image_stream(TOPIC, 2, encoding))
    message = input_error(fragment, open_agent, path)
    assert message.startswith(f"{path}: {TOPIC} message 0")


def test_a_later_message_of_another_encoding_or_a_depth_png_is_refused(tmp_path):
    mixed = image_stream(TOPIC, 2) + image_stream(TOPIC, 1, "16UC1", start=2)
    input_error(
        f"{TOPIC} message 2: encoding '16UC1' is a depth",
        open_agent,
        write_log(tmp_path / "mixed", "sqlite3", mixed),
    )
    depth = image_stream(TOPIC, 1, compressed="16UC1; compressedDepth png")
    input_error(
        "a compressed depth image ('16UC1; compressedDepth png')",
        open_agent,
        write_log(tmp_path / "depth", "sqlite3", depth),
    )


def test_stamps_must_increase_and_sizes_agree(tmp_path):
    messages = image_stream(TOPIC, 3)
    back = Message(
        TOPIC,
        "sensor_msgs/msg/Image",
        messages[2].log_time,
        raw_image(pixels(2), "rgb8", stamp_ns(0)),
    )
    input_error(
        f"{TOPIC} stamps are not strictly increasing at message 2 (100.050000000 s "
        "then 100.000000000 s)",
        open_agent,
        write_log(tmp_path / "back", "sqlite3", [*messages[:2], back]),
    )
    small = Message(
        TOPIC,
        "sensor_msgs/msg/Image",
        messages[2].log_time,
        raw_image(pixels(2)[:10], "rgb8", stamp_ns(2)),
    )
    input_error(
        f"{TOPIC} holds images of sizes 32x10, 32x24",
        open_agent,
        write_log(tmp_path / "sizes", "sqlite3", [*messages[:2], small]),
    )


@pytest.mark.parametrize("kind", KINDS)
def test_camera_info_beside_the_topic_gives_the_intrinsics(tmp_path, kind):
    distortion = (-0.2, 0.05, 0.001, -0.002, 0.0)
    messages = [
        Message(
            "/camera/camera_info",
            "sensor_msgs/msg/CameraInfo",
            1,
            camera_info(distortion=distortion),
        ),
        *image_stream(TOPIC, 2),
        *image_stream(f"{TOPIC}/compressed", 2, compressed="png"),
    ]
    path = write_log(log_path(tmp_path, kind), kind, messages)
    for topic in (TOPIC, f"{TOPIC}/compressed"):  # image_transport's topic shares it
        agent = open_agent(path, topic=topic)
        assert agent.calib == CALIB and agent.distortion == distortion
        # undistorted as EuRoC's frames are: OpenCV, the same K before and after
        np.testing.assert_array_equal(
            agent.load_frame(1).image, undistort(pixels(1), CALIB, distortion)
        )


def test_a_rectified_topic_takes_P_and_is_not_undistorted(tmp_path):
    P = (28.0, 28.5, 16.0, 12.0)
    messages = [
        Message(
            "/camera/camera_info",
            "sensor_msgs/msg/CameraInfo",
            1,
            camera_info(distortion=(-0.2, 0.05, 0.0, 0.0, 0.0), P=P),
        ),
        *image_stream("/camera/image_rect_color", 2),
    ]
    agent = open_agent(write_log(tmp_path / "log", "sqlite3", messages))
    assert agent.calib == P and agent.distortion == ()
    np.testing.assert_array_equal(agent.load_frame(1).image, pixels(1))


@pytest.mark.parametrize(
    "info, calib, fragment",
    [
        (camera_info(distortion=(0.1, 0.0, 0.0, 0.0)), CALIB, None),  # plumb_bob, 4 numbers
        (camera_info(calib=(0.0, 0.0, 0.0, 0.0)), None, None),  # an uncalibrated camera: K = 0
        (
            camera_info(distortion=(0.1, 0.0, 0.0, 0.0), model="equidistant"),
            None,
            "distortion_model 'equidistant' is not supported (only plumb_bob, rational_polynomial)",
        ),
        (
            camera_info(size=(64, 48)),
            None,
            "the camera is 64x48, the images of /camera/image_raw are 32x24",
        ),
    ],
)
def test_camera_info_checks(tmp_path, info, calib, fragment):
    messages = [
        Message("/camera/camera_info", "sensor_msgs/msg/CameraInfo", 1, info),
        *image_stream(TOPIC, 2),
    ]
    path = write_log(tmp_path / "log", "sqlite3", messages)
    if fragment is not None:
        input_error(f"{path}: /camera/camera_info: {fragment}", open_agent, path)
    else:
        assert open_agent(path).calib == calib


def test_detection_and_what_is_refused(tmp_path):
    bag = write_log(tmp_path / "log.bag", "ros1", image_stream(TOPIC, 2))
    folder = write_log(tmp_path / "ros2", "mcap", image_stream(TOPIC, 2))
    assert detect_format(bag) == detect_format(folder) == "rosbag"
    assert detect_format(next(folder.glob("*.mcap"))) == "rosbag"
    bare = tmp_path / "bare" / "recording.mcap"
    bare.parent.mkdir()
    bare.write_bytes(next(folder.glob("*.mcap")).read_bytes())
    input_error(
        f"{bare}: the rosbags library reads .mcap storage only as part of a ROS 2 bag "
        "folder, with the metadata.yaml",
        open_agent,
        bare,
    )
    (tmp_path / "garbage.bag").write_bytes(b"not a bag at all")
    input_error(
        f"{tmp_path / 'garbage.bag'}: cannot read the ROS log", open_agent, tmp_path / "garbage.bag"
    )
    input_error(f"{bag}: a ROS log holds no ground truth como3r reads", read_ground_truth, bag)
    seq = tmp_path / "seq-01"
    write_7scenes(seq, n=2)
    input_error("--topic /x is for ROS logs; this is a 7scenes input", open_agent, seq, topic="/x")
    input_error(
        "not a ROS log (--format rosbag): expected a ROS 1 .bag file",
        open_agent,
        seq,
        format="rosbag",
    )


def test_split_writes_the_decoded_frames(tmp_path):
    path = write_log(tmp_path / "log.bag", "ros1", image_stream(TOPIC, 4, "bgr8"))
    folders = split_sequence(path, tmp_path / "split", agents=2, overlap=0.0, topic=TOPIC)
    agent = open_agent(folders[1])
    assert agent.num_frames == 2 and agent.stems == (str(stamp_ns(2)), str(stamp_ns(3)))
    np.testing.assert_allclose(agent.timestamps, [stamp_ns(2) * 1e-9, stamp_ns(3) * 1e-9])
    np.testing.assert_array_equal(agent.load_frame(1).image, pixels(3))
    assert cv2.imread(str(agent.image_paths[0])) is not None
