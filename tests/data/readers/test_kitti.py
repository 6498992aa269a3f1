"""Tests of como3r.data.readers.kitti: a KITTI odometry ``dataset/sequences/XX`` folder, its
P2 intrinsics and ``dataset/poses/XX.txt`` moved to the colour camera image_2; the grey
download (image_0, P0, cam0's poses as they are), synthetic and the real excerpt."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from como3r.data.agent import open_agent
from como3r.data.readers import read_ground_truth

from ..shared_data import SHARED_DATA
from .layouts import KITTI_P2, input_error, pixels, pose_matrices, write_kitti

KITTI_GREY_REAL = SHARED_DATA / "kitti_odometry_00_gray_60/dataset/sequences/00"


def test_sequence_is_read_as_published(tmp_path):
    info = write_kitti(tmp_path / "dataset", name="05", n=4)
    agent = open_agent(info["sequence"])
    assert agent.format == "kitti" and agent.name == "05" and agent.num_frames == 4
    assert agent.stems == ("000000", "000001", "000002", "000003")
    np.testing.assert_allclose(agent.timestamps, info["times"], rtol=1e-6)
    assert agent.calib == (718.856, 718.856, 607.1928, 185.2157)  # P2's K
    np.testing.assert_array_equal(agent.load_frame(3).image, pixels(3))
    assert agent.has_gt_pose.all()
    torch.testing.assert_close(agent.load_frame(1).T_WC_gt, agent.groundtruth.T_WC[1])


def test_ground_truth_is_cam0_moved_to_image_2(tmp_path):
    """P2 = K [I | t2]: cam0's origin is at t2 in cam2, cam2 6 cm to cam0's left."""
    info = write_kitti(tmp_path / "dataset", n=3)
    t2 = np.linalg.solve(KITTI_P2[:, :3], KITTI_P2[:, 3])
    np.testing.assert_allclose(t2, [0.05994, -0.00113, 0.00378], atol=1e-5)
    cam0_cam2 = np.eye(4)
    cam0_cam2[:3, 3] = -t2
    expected = info["cam0"] @ cam0_cam2
    source, trajectory = read_ground_truth(info["sequence"])
    assert source == tmp_path / "dataset" / "poses" / "05.txt"
    np.testing.assert_allclose(trajectory.timestamps, info["times"], rtol=1e-6)
    M = pose_matrices(trajectory.T_WC)
    np.testing.assert_allclose(M, expected, atol=1e-5)
    np.testing.assert_allclose(M[:, :3, :3], info["cam0"][:, :3, :3], atol=1e-5)
    np.testing.assert_allclose(
        np.linalg.norm(M[:, :3, 3] - info["cam0"][:, :3, 3], axis=1), np.linalg.norm(t2), atol=1e-5
    )
    np.testing.assert_allclose(pose_matrices(open_agent(info["sequence"]).groundtruth.T_WC), M)


def test_a_subset_of_the_frames_keeps_their_times_and_poses(tmp_path):
    info = write_kitti(tmp_path / "dataset", n=5, frames=(0, 2, 4))
    agent = open_agent(info["sequence"])
    assert agent.stems == ("000000", "000002", "000004")
    np.testing.assert_allclose(agent.timestamps, info["times"][[0, 2, 4]], rtol=1e-6)
    assert agent.has_gt_pose.all()
    frames, trajectory = agent.gt_for_frames()
    np.testing.assert_array_equal(frames, [0, 1, 2])
    torch.testing.assert_close(trajectory.T_WC, agent.groundtruth.T_WC[[0, 2, 4]])


def test_a_test_sequence_without_poses(tmp_path):
    info = write_kitti(tmp_path / "dataset", name="11", n=2, poses=False)
    agent = open_agent(info["sequence"])
    assert agent.groundtruth is None and not agent.has_gt_pose.any()
    input_error(
        f"no ground truth for KITTI sequence 11: expected "
        f"{tmp_path / 'dataset' / 'poses' / '11.txt'} (KITTI publishes poses for "
        "sequences 00-10 only)",
        read_ground_truth,
        info["sequence"],
    )


def test_the_grey_download_is_read_from_image_0(tmp_path):
    """data_odometry_gray.zip: image_0/ and image_1/, no image_2/; cam0's intrinsics (P0) and
    poses as published (cam0 is the poses' camera), frames as three equal channels."""
    info = write_kitti(tmp_path / "dataset", n=3, folders=("image_0", "image_1"))
    agent = open_agent(info["sequence"])
    assert agent.format == "kitti" and agent.num_frames == 3
    assert agent.image_paths[0].parent.name == "image_0"
    assert agent.calib == (718.856, 718.856, 607.1928, 185.2157)  # P0's K
    frame = agent.load_frame(2)
    assert frame.image.shape == (24, 32, 3) and frame.image.dtype == np.uint8
    for channel in range(3):
        np.testing.assert_array_equal(frame.image[..., channel], pixels(2)[..., 0])
    np.testing.assert_allclose(pose_matrices(agent.groundtruth.T_WC), info["cam0"], atol=1e-5)
    _, trajectory = read_ground_truth(info["sequence"])
    np.testing.assert_allclose(pose_matrices(trajectory.T_WC), info["cam0"], atol=1e-5)


def test_colour_is_taken_first_when_both_downloads_are_there(tmp_path):
    info = write_kitti(tmp_path / "dataset", n=2, folders=("image_0", "image_2"))
    agent = open_agent(info["sequence"])
    assert agent.image_paths[0].parent.name == "image_2"
    np.testing.assert_array_equal(agent.load_frame(1).image, pixels(1))


def test_a_grey_sequence_without_p0_names_it(tmp_path):
    info = write_kitti(tmp_path / "dataset", n=2, folders=("image_0",))
    _edit_line(info["sequence"] / "calib.txt", 1, None)
    input_error(
        "calib.txt: no 'P0:' line (the left grey camera's 3x4 projection matrix)",
        open_agent,
        info["sequence"],
    )


@pytest.mark.skipif(
    not KITTI_GREY_REAL.is_dir(), reason=f"KITTI grey excerpt not found at {KITTI_GREY_REAL}"
)
def test_the_real_grey_excerpt():
    """Sequence 00's first 60 frames as data_odometry_gray.zip extracts them: 1241x376 grey,
    P0, the poses file's rows as the frames' poses."""
    agent = open_agent(KITTI_GREY_REAL)
    assert agent.format == "kitti" and agent.num_frames == 60 and agent.image_size == (1241, 376)
    assert agent.calib == (718.856, 718.856, 607.1928, 185.2157)
    assert agent.has_gt_pose.all()
    frame = agent.load_frame(59)
    assert frame.image.shape == (376, 1241, 3)
    assert (frame.image[..., 0] == frame.image[..., 1]).all()
    assert (frame.image[..., 0] == frame.image[..., 2]).all() and frame.image.std() > 10
    rows = (KITTI_GREY_REAL.parent.parent / "poses" / "00.txt").read_text().splitlines()
    M = np.array(rows[59].split(), dtype=np.float64).reshape(3, 4)
    np.testing.assert_allclose(pose_matrices(frame.T_WC_gt[None])[0, :3], M, atol=1e-6)


# ---------------------------------------------------------------------------------- bad inputs


def _edit_line(path, line_no: int, text: str | None) -> None:
    """Replace (or, with None, delete) line ``line_no`` (1-based) of a text file."""
    lines = path.read_text().splitlines()
    if text is None:
        del lines[line_no - 1]
    else:
        lines[line_no - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "line_no, text, fragment",
    [
        (2, "0.1 0.2", "times.txt:2: expected one timestamp, got 2 values"),
        (3, "abc", "times.txt:3: not a timestamp: 'abc'"),
        (3, "0.01", "times.txt:3: timestamps are not strictly increasing"),
        (4, None, "image_2/000003.png: frame 3 has no line in"),
    ],
)
def test_malformed_times(tmp_path, line_no, text, fragment):
    info = write_kitti(tmp_path / "dataset", n=4)
    _edit_line(info["sequence"] / "times.txt", line_no, text)
    input_error(fragment, open_agent, info["sequence"])


@pytest.mark.parametrize(
    "line_no, text, fragment",
    [
        (3, None, "calib.txt: no 'P2:' line"),
        (
            3,
            "P2: 1 0 2 0 0 1 2",
            "calib.txt:3: expected 12 finite numbers (P2: 3x4 projection matrix), got 7",
        ),
        (3, "P2: 700 0 600 0 0 700 180 0 0 0 2 0", "calib.txt:3: P2 is not a projection matrix"),
    ],
)
def test_malformed_calib(tmp_path, line_no, text, fragment):
    info = write_kitti(tmp_path / "dataset", n=2)
    _edit_line(info["sequence"] / "calib.txt", line_no, text)
    input_error(fragment, open_agent, info["sequence"])
    input_error(fragment, read_ground_truth, info["sequence"])


@pytest.mark.parametrize(
    "line_no, text, fragment",
    [
        (
            2,
            "1 0 0 0 0 1 0 0 0 0 1",
            "05.txt:2: expected 12 finite numbers (3x4 camera-to-world matrix, row-major), got 11",
        ),
        (2, "1 0 0 0 0 1 0 0 0 0 1 x", "05.txt:2: expected 12 numbers"),
        (3, "1.2 0 0 0 0 1 0 0 0 0 1 0", "05.txt:3: not a rigid camera-to-world transform"),
        (3, None, "05.txt: 2 poses for 3 lines of times.txt; expected one per frame"),
    ],
)
def test_malformed_poses(tmp_path, line_no, text, fragment):
    info = write_kitti(tmp_path / "dataset", n=3)
    _edit_line(tmp_path / "dataset" / "poses" / "05.txt", line_no, text)
    input_error(fragment, open_agent, info["sequence"])
    input_error(fragment, read_ground_truth, info["sequence"])


def test_images_not_named_by_frame_number(tmp_path):
    info = write_kitti(tmp_path / "dataset", n=2)
    images = info["sequence"] / "image_2"
    (images / "000001.png").rename(images / "x1.png")
    input_error(
        "image_2/x1.png: not named by its frame number (expected e.g. 000000.png)",
        open_agent,
        info["sequence"],
    )
    (images / "x1.png").rename(images / "1.png")
    assert open_agent(info["sequence"]).stems == ("000000", "1")
    (images / "0001.png").write_bytes((images / "1.png").read_bytes())
    input_error(
        "image_2/1.png: frame 1 has two images (also 0001.png)", open_agent, info["sequence"]
    )


def test_missing_times_or_calib(tmp_path):
    info = write_kitti(tmp_path / "dataset", n=2)
    (info["sequence"] / "calib.txt").unlink()
    input_error(
        "calib.txt: missing (calibration of the KITTI sequence)", open_agent, info["sequence"]
    )
    (info["sequence"] / "image_2" / "000000.png").unlink()
    (info["sequence"] / "image_2" / "000001.png").unlink()
    input_error("image_2: no images", open_agent, info["sequence"])
