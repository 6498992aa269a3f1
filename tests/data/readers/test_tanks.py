"""Tests of como3r.data.readers.tanks: a Tanks and Temples folder as CoMo3R-SLAM stages it
(``image/`` named by frame id, ``gt_traj.txt`` of ``frame_id tx ty tz qx qy qz qw``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.readers import read_ground_truth

from .layouts import input_error, pixels, write_tanks


def test_sequence_is_read_in_frame_id_order(tmp_path):
    rows = write_tanks(tmp_path / "Barn", ids=(1, 2, 3, 5))
    agent = open_agent(tmp_path / "Barn")
    assert agent.format == "tanks" and agent.name == "Barn" and agent.num_frames == 4
    assert agent.stems == ("000001", "000002", "000003", "000005")
    np.testing.assert_allclose(agent.timestamps, np.array([1, 2, 3, 5]) / 30.0)  # id / 30 Hz
    assert agent.calib is None and not agent.has_depth  # uncalibrated, as CoMo3R runs it
    np.testing.assert_array_equal(agent.load_frame(3).image, pixels(5))
    assert agent.has_gt_pose.all()
    torch.testing.assert_close(agent.groundtruth.T_WC[:, :7], torch.from_numpy(rows))
    torch.testing.assert_close(agent.load_frame(3).T_WC_gt, agent.groundtruth.T_WC[3])


def test_timestamps_follow_the_frame_rate(tmp_path):
    write_tanks(tmp_path / "seq", ids=(30, 45))
    np.testing.assert_allclose(open_agent(tmp_path / "seq", fps=15.0).timestamps, [2.0, 3.0])
    _, trajectory = read_ground_truth(tmp_path / "seq", fps=15.0)
    np.testing.assert_allclose(trajectory.timestamps, [2.0, 3.0])


def test_ids_are_numbers_not_names(tmp_path):
    """``frame_9`` comes before ``frame_10`` although it sorts after it by name."""
    (tmp_path / "seq" / "image").mkdir(parents=True)
    for i in (10, 9, 11):
        Image.fromarray(pixels(i)).save(tmp_path / "seq" / "image" / f"frame_{i}.jpg")
    agent = open_agent(tmp_path / "seq")
    assert agent.stems == ("frame_9", "frame_10", "frame_11")
    assert agent.load_frame(0).image.shape == (24, 32, 3)
    assert agent.groundtruth is None and not agent.has_gt_pose.any()
    input_error(
        "Tanks and Temples sequence has no gt_traj.txt", read_ground_truth, tmp_path / "seq"
    )


def test_frames_without_a_ground_truth_line(tmp_path):
    write_tanks(tmp_path / "seq", ids=(1, 2, 3, 4), groundtruth=(2, 4, 6))
    agent = open_agent(tmp_path / "seq")
    # frame 1 is before the first pose; frame 3 lies between poses 67 ms apart: interpolated
    np.testing.assert_array_equal(agent.has_gt_pose, [False, True, True, True])
    frames, trajectory = agent.gt_for_frames()
    np.testing.assert_array_equal(frames, [1, 2, 3])
    np.testing.assert_allclose(trajectory.timestamps, [2 / 30, 3 / 30, 4 / 30])
    torch.testing.assert_close(trajectory.T_WC[1, :3], agent.groundtruth.T_WC[:2, :3].mean(0))


def test_calib_txt_is_the_calibration(tmp_path):
    write_tanks(tmp_path / "seq", ids=(1, 2))
    (tmp_path / "seq" / "calib.txt").write_text("500 501 16 12\n")
    assert open_agent(tmp_path / "seq").calib == (500.0, 501.0, 16.0, 12.0)


# ---------------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    "line, fragment",
    [
        (
            "2 0 0 0 0 0 0",
            "gt_traj.txt:2: expected 8 numbers (timestamp tx ty tz qx qy qz qw), got 7",
        ),
        ("2 0 0 0 0 0 0 x", "gt_traj.txt:2: not a number"),
        ("2 0 0 0 0 0 0 0.5", "gt_traj.txt:2: quaternion norm 0.5000 is not 1"),
        ("1 0 0 0 0 0 0 1", "gt_traj.txt:2: frame ids are not strictly increasing (1 then 1)"),
        ("2.5 0 0 0 0 0 0 1", "gt_traj.txt:2: frame id 2.5 is not a whole number"),
    ],
)
def test_malformed_ground_truth(tmp_path, line, fragment):
    write_tanks(tmp_path / "seq", ids=(1, 2), groundtruth=())
    (tmp_path / "seq" / "gt_traj.txt").write_text(f"1 0 0 0 0 0 0 1\n{line}\n")
    input_error(fragment, open_agent, tmp_path / "seq")
    input_error(fragment, read_ground_truth, tmp_path / "seq")


def test_bad_image_names(tmp_path):
    write_tanks(tmp_path / "seq", ids=(1, 2))
    Image.fromarray(pixels(0)).save(tmp_path / "seq" / "image" / "1.jpg")
    input_error(
        "image/1.jpg: frame 1 has two images (also 000001.png)", open_agent, tmp_path / "seq"
    )
    (tmp_path / "seq" / "image" / "1.jpg").rename(tmp_path / "seq" / "image" / "cover.jpg")
    input_error(
        "image/cover.jpg: not named by its frame number (expected e.g. 000001.jpg)",
        open_agent,
        tmp_path / "seq",
    )


def test_no_frames(tmp_path):
    (tmp_path / "seq" / "image").mkdir(parents=True)
    input_error("seq/image: no images", open_agent, tmp_path / "seq")
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "gt_traj.txt").write_text("1 0 0 0 0 0 0 1\n")
    input_error(
        "Tanks and Temples sequence has no image/ folder of frames", open_agent, tmp_path / "gt"
    )
