"""Tests of como3r.data.readers.sevenscenes: a 7-Scenes sequence folder as published, and
the real 50-frame redkitchen excerpt (read in place, never copied)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.readers import read_ground_truth
from como3r.data.readers.sevenscenes import DEFAULT_INTRINSICS

from .layouts import (
    SEVEN_SCENES_REAL,
    depth_metres,
    input_error,
    pixels,
    pose_matrices,
    write_7scenes,
    write_pose,
)


@pytest.mark.parametrize("invalid", [65535, 0])
def test_sequence_is_read_as_published(tmp_path, invalid):
    seq = tmp_path / "redkitchen" / "seq-01"
    T = write_7scenes(seq, n=4, start=150, invalid=invalid)
    agent = open_agent(seq)
    assert agent.format == "7scenes" and agent.num_frames == 4 and agent.name == "seq-01"
    assert agent.stems == ("frame-000150", "frame-000151", "frame-000152", "frame-000153")
    np.testing.assert_allclose(agent.timestamps, np.arange(150, 154) / 30.0)  # number / 30 Hz
    assert agent.calib == DEFAULT_INTRINSICS == (585.0, 585.0, 320.0, 240.0)
    frame = agent.load_frame(2)
    np.testing.assert_array_equal(frame.image, pixels(2))
    expected = np.round(depth_metres(2) * 1000) / 1000
    expected[0, :2] = 0.0  # 0 and 65535 are invalid
    np.testing.assert_allclose(frame.depth, expected, atol=1e-6)
    np.testing.assert_allclose(pose_matrices(agent.groundtruth.T_WC), T, atol=1e-6)
    torch.testing.assert_close(frame.T_WC_gt, agent.groundtruth.T_WC[2])
    assert agent.has_gt_pose.all()


def test_timestamps_follow_the_frame_rate(tmp_path):
    write_7scenes(tmp_path / "seq", n=2, start=30)
    np.testing.assert_allclose(open_agent(tmp_path / "seq", fps=15.0).timestamps, [2.0, 31 / 15])


def test_jpeg_colour_and_no_depth_or_poses(tmp_path):
    write_7scenes(tmp_path / "seq", n=3, colour="jpg", depth=False, poses=False)
    agent = open_agent(tmp_path / "seq")
    assert agent.num_frames == 3 and not agent.has_depth and agent.groundtruth is None
    assert not agent.has_gt_pose.any()
    input_error("has no frame-NNNNNN.pose.txt files", read_ground_truth, tmp_path / "seq")


def test_a_seq_folder_of_jpeg_colour_with_depth_and_poses(tmp_path):
    """``scene/seq-01/`` as its zip extracts, colour as JPEG (as some copies ship it): every
    part pairs up as with PNG colour, the simulated prior has what it needs."""
    T = write_7scenes(tmp_path / "chess" / "seq-01", n=3, colour="jpg")
    agent = open_agent(tmp_path / "chess" / "seq-01")
    assert agent.format == "7scenes" and agent.num_frames == 3 and agent.has_depth
    assert agent.image_paths[0].name == "frame-000000.color.jpg"
    assert agent.has_gt_pose.all() and agent.calib is not None
    frame = agent.load_frame(1)
    assert frame.image.shape == (24, 32, 3)
    np.testing.assert_array_equal(frame.image, np.asarray(Image.open(agent.image_paths[1])))
    np.testing.assert_allclose(pose_matrices(frame.T_WC_gt[None])[0], T[1], atol=1e-6)
    assert frame.depth is not None and frame.depth.shape == (24, 32)


def test_frames_in_the_only_subfolder_and_intrinsics_beside_them(tmp_path):
    """The layout of the shared excerpt: ``rgbd-frames/`` with camera-intrinsics.txt beside."""
    root = tmp_path / "excerpt"
    write_7scenes(root / "rgbd-frames", n=2)
    (root / "camera-intrinsics.txt").write_text(
        " 5.00000000e+02\t 0.0\t 3.10000000e+02\t\n 0.0\t 5.1e+02\t 2.3e+02\t\n 0 0 1\n"
    )
    agent = open_agent(root)
    assert agent.num_frames == 2 and agent.name == "excerpt"
    assert agent.calib == (500.0, 510.0, 310.0, 230.0)
    (root / "rgbd-frames" / "calib.txt").write_text("400 401 300 200\n")
    assert open_agent(root).calib == (400.0, 401.0, 300.0, 200.0)  # calib.txt first


def test_ground_truth_for_eval(tmp_path):
    T = write_7scenes(tmp_path / "seq", n=3, start=10)
    source, trajectory = read_ground_truth(tmp_path / "seq")
    assert source == tmp_path / "seq"
    np.testing.assert_allclose(trajectory.timestamps, np.arange(10, 13) / 30.0)
    np.testing.assert_allclose(pose_matrices(trajectory.T_WC), T, atol=1e-6)


# ---------------------------------------------------------------------------------- bad inputs


def test_a_scene_folder_of_several_sequences(tmp_path):
    write_7scenes(tmp_path / "chess" / "seq-01", n=2)
    write_7scenes(tmp_path / "chess" / "seq-02", n=2)
    input_error(
        "holds 2 7-Scenes sequences (seq-01, seq-02); give one", open_agent, tmp_path / "chess"
    )


@pytest.mark.parametrize("kind", ["depth.png", "pose.txt"])
def test_a_frame_without_its_depth_or_pose(tmp_path, kind):
    write_7scenes(tmp_path / "seq", n=3)
    (tmp_path / "seq" / f"frame-000001.{kind}").unlink()
    input_error(f"frame-000001.{kind}: missing (2 ", open_agent, tmp_path / "seq")


def test_depth_without_a_colour_image(tmp_path):
    write_7scenes(tmp_path / "seq", n=3)
    (tmp_path / "seq" / "frame-000002.color.png").unlink()
    input_error(
        "frame-000002.depth.png: no colour image frame-000002.color.png|jpg",
        open_agent,
        tmp_path / "seq",
    )


def test_two_colour_images_of_one_frame(tmp_path):
    write_7scenes(tmp_path / "seq", n=2)
    Image.fromarray(pixels(0)).save(tmp_path / "seq" / "frame-000000.color.jpg")
    input_error("frame 0 has two color files", open_agent, tmp_path / "seq")


def test_unreadable_colour_image(tmp_path):
    write_7scenes(tmp_path / "seq", n=2)
    (tmp_path / "seq" / "frame-000001.color.png").write_bytes(b"garbage")
    input_error("frame-000001.color.png: cannot read image", open_agent, tmp_path / "seq")


def test_depth_of_another_size(tmp_path):
    write_7scenes(tmp_path / "seq", n=2)
    Image.fromarray(np.zeros((5, 7), np.uint16)).save(tmp_path / "seq" / "frame-000001.depth.png")
    input_error("frame-000001.depth.png: depth map is 7x5", open_agent, tmp_path / "seq")


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "expected 16 finite numbers"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 x\n", "not a number"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 -1.#INF\n", "not a number"),
    ],
)
def test_malformed_pose(tmp_path, text, fragment):
    write_7scenes(tmp_path / "seq", n=2)
    (tmp_path / "seq" / "frame-000001.pose.txt").write_text(text)
    message = input_error(fragment, open_agent, tmp_path / "seq")
    assert "frame-000001.pose.txt: expected 16" in message


@pytest.mark.parametrize("scale, flip", [(1.1, False), (1.0, True)])
def test_pose_that_is_not_rigid(tmp_path, scale, flip):
    write_7scenes(tmp_path / "seq", n=2)
    T = np.eye(4)
    T[:3, :3] *= scale
    if flip:
        T[2, 2] = -1.0  # a reflection
    write_pose(tmp_path / "seq" / "frame-000000.pose.txt", T)
    input_error(
        "frame-000000.pose.txt: not a rigid camera-to-world transform", open_agent, tmp_path / "seq"
    )


def test_bad_intrinsics_file(tmp_path):
    write_7scenes(tmp_path / "seq", n=2)
    (tmp_path / "seq" / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    input_error("camera-intrinsics.txt: expected 9 finite numbers", open_agent, tmp_path / "seq")


# ------------------------------------------------------------------------ the real excerpt

real = pytest.mark.skipif(
    not SEVEN_SCENES_REAL.is_dir(), reason=f"7-Scenes excerpt not found at {SEVEN_SCENES_REAL}"
)


@real
def test_the_real_redkitchen_excerpt():
    """50 Kinect frames, read in place: intrinsics from camera-intrinsics.txt, depth in
    metres with 10-12 % invalid (the excerpt's README: 88-90 % valid, up to about 2.9 m),
    rigid poses 5 mm and 0.7 deg apart (a 0.25 m path)."""
    agent = open_agent(SEVEN_SCENES_REAL)
    assert agent.format == "7scenes" and agent.num_frames == 50
    assert agent.image_size == (640, 480) and agent.calib == (585.0, 585.0, 320.0, 240.0)
    assert agent.stems[0] == "frame-000150" and agent.stems[-1] == "frame-000199"
    np.testing.assert_allclose(agent.timestamps, np.arange(150, 200) / 30.0)
    invalid = []
    for i in (0, 25, 49):
        frame = agent.load_frame(i)
        assert frame.image.shape == (480, 640, 3)
        depth = frame.depth
        invalid.append(float((depth == 0).mean()))
        assert 0.3 < float(np.median(depth[depth > 0])) < 3.0 and depth.max() < 4.0
    assert all(0.09 < share < 0.13 for share in invalid), invalid
    raw = np.stack(
        [
            np.loadtxt(p)
            for p in sorted((SEVEN_SCENES_REAL / "rgbd-frames").glob("frame-*.pose.txt"))
        ]
    )
    R = raw[:, :3, :3]  # the files are rigid to the README's 1.6e-4 ...
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 5e-4
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=5e-4)
    M = pose_matrices(agent.groundtruth.T_WC)  # ... and read as those rotations and positions
    np.testing.assert_allclose(M, raw, atol=5e-4)
    steps = np.linalg.norm(np.diff(M[:, :3, 3], axis=0), axis=1)
    assert 0.15 < steps.sum() < 0.35 and steps.max() < 0.02
