"""``como3r export --ros2-bag``: a real (tiny) run's bag read back with rosbags and with the
``mcap`` package's own reader."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import InputError
from como3r.geometry.lie import se3_compose, se3_exp
from como3r.io.export import export_run
from como3r.io.keyframe_data import read_keyframe_data
from como3r.io.ply import read_ply
from como3r.io.ros2_bag import MAP_FRAME, agent_topics, camera_frame, keyframe_stamps
from como3r.io.run_graph import RunKeyframe
from como3r.io.tum import Trajectory, read_tum

from .tiny_run import HEIGHT, WIDTH, tiny_run
from .tiny_run import OVERRIDES as EXPORT_OVERRIDES

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

mcap_reader = pytest.importorskip(
    "mcap.reader",
    reason="the mcap package (test extra) reads the bag's MCAP file independently of rosbags",
)
rosbags_highlevel = pytest.importorskip("rosbags.highlevel")

# as tests/io/test_export.py, with a lower keyframe threshold so that not every tracked frame
# is a keyframe (the bag's full-rate and keyframe topics then differ in count)
OVERRIDES = [*EXPORT_OVERRIDES, "tracking.keyframe_match_fraction=0.1"]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A finished two-agent run of the real pipeline on a tiny synthetic scene."""
    return tiny_run(tmp_path_factory.mktemp("ros2"), OVERRIDES)


@pytest.fixture(scope="module")
def bag(run_dir, tmp_path_factory) -> Path:
    """The run's bag, through the command line."""
    out = tmp_path_factory.mktemp("bag") / "run_bag"
    result = CliRunner().invoke(
        app, ["export", str(run_dir), "--ros2-bag", str(out)], env={"COLUMNS": "120"}
    )
    assert result.exit_code == 0, result.output
    assert "ros2_bag" in result.output
    return out


@pytest.fixture(scope="module")
def messages(bag) -> list[tuple[str, int, object]]:
    """Every message as ``(topic, log time ns, message)``, read with rosbags (types from the
    bag's own message definitions)."""
    with rosbags_highlevel.AnyReader([bag]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def _agents(run_dir: Path) -> list[int]:
    return sorted(
        {k["agent"] for k in json.loads((run_dir / "graph.json").read_text())["keyframes"]}
    )


def _keyframes(run_dir: Path, agent: int) -> list[dict]:
    return [
        k
        for k in json.loads((run_dir / "graph.json").read_text())["keyframes"]
        if k["agent"] == agent
    ]


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def _pose(pose) -> np.ndarray:
    p, q = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])


@pytest.mark.slow
def test_bag_folder_layout(bag) -> None:
    names = sorted(p.name for p in bag.iterdir())
    assert names == [".como3r-run", "metadata.yaml", "run_bag.mcap"]
    assert "storage_identifier: mcap" in (bag / "metadata.yaml").read_text()


@pytest.mark.slow
def test_message_counts_and_types(run_dir, bag) -> None:
    agents = _agents(run_dir)
    assert agents == [0, 1]
    frames = {a: len(read_tum(run_dir / "trajectories" / f"agent_{a}.txt")) for a in agents}
    keyframes = {a: len(_keyframes(run_dir, a)) for a in agents}
    assert all(keyframes[a] < frames[a] for a in agents), "the scene must keep some non-keyframes"
    expected = {"/tf": sum(frames.values()), "/map": 1}
    for a in agents:
        topics = agent_topics(a)
        expected |= {
            topics["odometry"]: frames[a],
            topics["keyframes"]: keyframes[a],
            topics["image"]: keyframes[a],
            topics["camera_info"]: keyframes[a],
        }
    with rosbags_highlevel.AnyReader([bag]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        types = {c.topic: c.msgtype for c in reader.connections}
    assert counts == expected
    assert types["/tf"] == "tf2_msgs/msg/TFMessage"
    assert types["/map"] == "sensor_msgs/msg/PointCloud2"
    assert types[agent_topics(1)["odometry"]] == "nav_msgs/msg/Odometry"
    assert types[agent_topics(1)["image"]] == "sensor_msgs/msg/CompressedImage"


@pytest.mark.slow
def test_tf_and_odometry_are_the_tum_trajectory(run_dir, messages) -> None:
    for agent in _agents(run_dir):
        tum = read_tum(run_dir / "trajectories" / f"agent_{agent}.txt")
        tf = [
            m.transforms[0]
            for topic, _, m in messages
            if topic == "/tf" and m.transforms[0].child_frame_id == camera_frame(agent)
        ]
        odometry = [(t, m) for topic, t, m in messages if topic == agent_topics(agent)["odometry"]]
        assert len(tf) == len(odometry) == len(tum)
        for k, (transform, (log_time, odo)) in enumerate(zip(tf, odometry)):
            expected = tum.T_WC[k, :7].numpy()
            assert transform.header.frame_id == odo.header.frame_id == MAP_FRAME
            assert odo.child_frame_id == camera_frame(agent)
            tr, rot = transform.transform.translation, transform.transform.rotation
            np.testing.assert_allclose(
                [tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w], expected, atol=1e-9
            )
            np.testing.assert_allclose(_pose(odo.pose.pose), expected, atol=1e-9)
            assert _stamp(odo.header) == pytest.approx(tum.timestamps[k], abs=1e-9)
            assert log_time == round(tum.timestamps[k] * 1e9)


@pytest.mark.slow
def test_odometry_twist_carries_each_frame_to_the_next(run_dir, messages) -> None:
    tum = read_tum(run_dir / "trajectories" / "agent_1.txt")
    odometry = [m for topic, _, m in messages if topic == agent_topics(1)["odometry"]]
    for k in range(len(tum) - 1):
        twist = odometry[k].twist.twist
        xi = torch.tensor(
            [
                twist.linear.x,
                twist.linear.y,
                twist.linear.z,
                twist.angular.x,
                twist.angular.y,
                twist.angular.z,
            ],
            dtype=torch.float64,
        )
        dt = tum.timestamps[k + 1] - tum.timestamps[k]
        moved = se3_compose(tum.T_WC[k, :7], se3_exp(xi * dt))
        np.testing.assert_allclose(moved[:3].numpy(), tum.T_WC[k + 1, :3].numpy(), atol=1e-6)
        assert abs(float(moved[3:7] @ tum.T_WC[k + 1, 3:7])) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.slow
def test_keyframe_path_images_and_camera_info(run_dir, messages) -> None:
    for agent in _agents(run_dir):
        topics = agent_topics(agent)
        keyframes = _keyframes(run_dir, agent)
        kf_tum = read_tum(run_dir / "keyframes" / f"agent_{agent}.txt")
        paths = [m for topic, _, m in messages if topic == topics["keyframes"]]
        assert [len(p.poses) for p in paths] == list(range(1, len(keyframes) + 1))
        final = np.array([_pose(p.pose) for p in paths[-1].poses])
        np.testing.assert_allclose(final, kf_tum.T_WC[:, :7].numpy(), atol=2e-9)
        images = [m for topic, _, m in messages if topic == topics["image"]]
        infos = [m for topic, _, m in messages if topic == topics["camera_info"]]
        tf_stamps = {
            (m.transforms[0].header.stamp.sec, m.transforms[0].header.stamp.nanosec)
            for topic, _, m in messages
            if topic == "/tf" and m.transforms[0].child_frame_id == camera_frame(agent)
        }
        for kf, image, info in zip(keyframes, images, infos):
            data = read_keyframe_data(run_dir, agent, kf["keyframe"])
            assert image.header.frame_id == info.header.frame_id == camera_frame(agent)
            assert _stamp(image.header) == pytest.approx(kf["timestamp"], abs=1e-6)
            # exactly a stamp of the camera's transform: no tf extrapolation at the last frame
            assert (image.header.stamp.sec, image.header.stamp.nanosec) in tf_stamps
            assert info.header.stamp == image.header.stamp
            assert image.format == "png"
            decoded = np.asarray(Image.open(io.BytesIO(image.data.tobytes())).convert("RGB"))
            np.testing.assert_array_equal(decoded, data.image())
            assert (info.width, info.height) == (WIDTH, HEIGHT)
            np.testing.assert_allclose(info.k.reshape(3, 3), data.K)
            np.testing.assert_allclose(info.p.reshape(3, 4)[:, :3], data.K)


@pytest.mark.slow
def test_map_cloud_is_map_ply(run_dir, messages) -> None:
    (cloud,) = [m for topic, _, m in messages if topic == "/map"]
    ply = read_ply(run_dir / "map.ply")
    assert cloud.header.frame_id == MAP_FRAME and cloud.width == len(ply) and cloud.height == 1
    fields = {f.name: (f.offset, f.datatype) for f in cloud.fields}
    assert list(fields) == ["x", "y", "z", "rgb", "agent_id"]
    dtype = np.dtype(
        {
            "names": list(fields),
            "offsets": [o for o, _ in fields.values()],
            "formats": ["<f4", "<f4", "<f4", "<u4", "<u4"],
            "itemsize": cloud.point_step,
        }
    )
    points = np.frombuffer(cloud.data.tobytes(), dtype=dtype)
    for axis in "xyz":
        np.testing.assert_array_equal(points[axis], ply[axis])
    np.testing.assert_array_equal(points["rgb"] >> 16, ply["red"])
    np.testing.assert_array_equal(points["rgb"] & 0xFF, ply["blue"])
    np.testing.assert_array_equal(points["agent_id"], ply["agent_id"])
    assert set(np.unique(points["agent_id"])) == {0, 1}


@pytest.mark.slow
def test_mcap_reader_sees_the_same_bag(run_dir, bag) -> None:
    """The ``mcap`` package's reader: ROS 2 schemas, CDR channels, counts and a pose."""
    from rosbags.typesys import Stores, get_typestore

    with open(bag / "run_bag.mcap", "rb") as stream:
        reader = mcap_reader.make_reader(stream)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = {c.topic: summary.schemas[c.schema_id] for c in channels.values()}
        counts = {
            channels_by_id.topic: summary.statistics.channel_message_counts[i]
            for i, channels_by_id in summary.channels.items()
        }
        odometry = [
            (message.log_time, message.data)
            for _, channel, message in reader.iter_messages(topics=[agent_topics(0)["odometry"]])
        ]
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert all(c.message_encoding == "cdr" for c in channels.values())
    assert {s.encoding for s in schemas.values()} == {"ros2msg"}
    assert schemas["/tf"].name == "tf2_msgs/msg/TFMessage"
    tum = read_tum(run_dir / "trajectories" / "agent_0.txt")
    assert counts["/tf"] == len(tum) + len(read_tum(run_dir / "trajectories" / "agent_1.txt"))
    assert counts[agent_topics(0)["odometry"]] == len(tum) == len(odometry)
    k = len(tum) // 2
    log_time, raw = odometry[k]
    assert log_time == round(tum.timestamps[k] * 1e9)
    message = get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(raw, "nav_msgs/msg/Odometry")
    np.testing.assert_allclose(_pose(message.pose.pose), tum.T_WC[k, :7].numpy(), atol=1e-9)


@pytest.mark.slow
def test_bag_is_replaced_only_with_overwrite(run_dir, bag, tmp_path) -> None:
    target = tmp_path / "bag"
    export_run(run_dir, ros2_bag=target)
    with pytest.raises(InputError, match="use --overwrite"):
        export_run(run_dir, ros2_bag=target)
    summary = export_run(run_dir, ros2_bag=target, overwrite=True)
    assert summary.rows[0]["export"] == "ros2_bag"
    assert sorted(p.name for p in target.iterdir()) == [".como3r-run", "bag.mcap", "metadata.yaml"]
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # no staging or old folder left


@pytest.mark.slow
def test_bag_needs_the_trajectories(run_dir, tmp_path, only_error_line) -> None:
    copy = tmp_path / "run"
    copy.mkdir()
    for name in ("graph.json", "map.ply"):
        (copy / name).write_bytes((run_dir / name).read_bytes())
    (copy / "keyframes").symlink_to(run_dir / "keyframes")
    result = CliRunner().invoke(app, ["export", str(copy), "--ros2-bag", str(tmp_path / "bag")])
    assert "no trajectories/agent_0.txt" in only_error_line(result)
    assert not (tmp_path / "bag").exists() and not (tmp_path / "bag.partial").exists()


def test_a_keyframe_without_a_tracked_frame_is_named(tmp_path) -> None:
    trajectory = Trajectory(np.array([0.0, 0.1, 0.2]), torch.zeros(3, 8, dtype=torch.float64))
    keyframe = RunKeyframe(0, 1, 4, 9, 0.35, np.array([0.0] * 6 + [1.0, 1.0]))
    with pytest.raises(
        InputError, match="keyframe 4 of agent 1 .* no pose in trajectories/agent_1.txt"
    ):
        keyframe_stamps([keyframe], trajectory, tmp_path)
    near = RunKeyframe(0, 1, 4, 2, 0.2000004, keyframe.T_WC)
    assert keyframe_stamps([near], trajectory, tmp_path) == [0.2]
