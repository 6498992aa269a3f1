"""Tests of como3r.data.readers.euroc: a EuRoC MAV sequence in the ASL folder format, its
undistortion and its ground truth composed with the camera's T_BS."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from como3r.data.agent import open_agent
from como3r.data.readers import read_ground_truth

from .layouts import (
    EUROC_CALIB,
    EUROC_T_BS,
    euroc_sensor_yaml,
    input_error,
    pixels,
    pose_matrices,
    write_euroc,
)


def _body_matrices(rows: np.ndarray) -> np.ndarray:
    """``(M, 4, 4)`` T_WB of ground-truth rows ``p xyz, q wxyz``."""
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(rows[:, [4, 5, 6, 3]]).as_matrix()
    T[:, :3, 3] = rows[:, :3]
    return T


@pytest.mark.parametrize("sub", ["", "mav0"])
def test_sequence_is_read_as_published(tmp_path, sub):
    info = write_euroc(tmp_path / "MH_01_easy", n=4)
    agent = open_agent(tmp_path / "MH_01_easy" / sub)
    assert agent.format == "euroc" and agent.name == "MH_01_easy" and agent.num_frames == 4
    assert agent.stems == tuple(str(t) for t in info["ns"])
    np.testing.assert_allclose(agent.timestamps, info["ns"] * 1e-9, rtol=0, atol=1e-6)
    assert np.all(np.diff(agent.timestamps) > 0.0499)  # 20 Hz, seconds
    assert agent.calib == EUROC_CALIB and not agent.has_depth
    frame = agent.load_frame(2)  # grey becomes 3-channel RGB; no distortion: pixels as stored
    assert frame.image.shape == (24, 32, 3) and frame.image.dtype == np.uint8
    for channel in range(3):
        np.testing.assert_array_equal(frame.image[..., channel], pixels(2)[..., 0])
    assert [f.index for f in agent.frames()] == [0, 1, 2, 3]
    # each frame's ground truth is a 200 Hz sample (from 20 ms before) at its time
    assert agent.has_gt_pose.all()
    torch.testing.assert_close(frame.T_WC_gt, agent.groundtruth.T_WC[24])


def test_ground_truth_is_the_body_pose_composed_with_T_BS(tmp_path):
    info = write_euroc(tmp_path / "V1_01_easy", n=3)
    expected = _body_matrices(info["gt"]) @ EUROC_T_BS  # T_WC = T_WB T_BS
    source, trajectory = read_ground_truth(tmp_path / "V1_01_easy")
    assert source == tmp_path / "V1_01_easy" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    np.testing.assert_allclose(trajectory.timestamps, info["gt_ns"] * 1e-9, rtol=0, atol=1e-6)
    np.testing.assert_allclose(pose_matrices(trajectory.T_WC), expected, atol=1e-6)
    agent = open_agent(tmp_path / "V1_01_easy")
    np.testing.assert_allclose(pose_matrices(agent.groundtruth.T_WC), expected, atol=1e-6)
    # the camera sits 6.8 cm from the body origin, so the positions differ by that
    offsets = np.linalg.norm(expected[:, :3, 3] - info["gt"][:, :3], axis=1)
    np.testing.assert_allclose(offsets, np.linalg.norm(EUROC_T_BS[:3, 3]), atol=1e-6)


def test_identity_T_BS_gives_the_body_trajectory(tmp_path):
    info = write_euroc(tmp_path / "seq", n=2, T_BS=np.eye(4))
    _, trajectory = read_ground_truth(tmp_path / "seq")
    np.testing.assert_allclose(
        pose_matrices(trajectory.T_WC), _body_matrices(info["gt"]), atol=1e-6
    )


def test_undistortion_moves_a_known_point_back(tmp_path):
    """A blob drawn where the radial-tangential lens images pixel (56, 42) of the pinhole
    camera is read back at (56, 42)."""
    calib, distortion = (40.0, 40.0, 32.0, 24.0), (-0.3, 0.08, 0.001, -0.001)
    fx, fy, cx, cy = calib
    target = np.array([56.0, 42.0])
    normalised = np.array([[(target[0] - cx) / fx, (target[1] - cy) / fy, 1.0]])
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    distorted = cv2.projectPoints(normalised, np.zeros(3), np.zeros(3), K, np.array(distortion))[
        0
    ].reshape(2)
    assert np.linalg.norm(distorted - target) > 2.0  # the lens moves it by pixels

    v, u = np.mgrid[0:48, 0:64]
    blob = 250 * np.exp(-((u - distorted[0]) ** 2 + (v - distorted[1]) ** 2) / (2 * 1.5**2))
    write_euroc(
        tmp_path / "seq",
        images=[blob.astype(np.uint8)] * 2,
        calib=calib,
        distortion=distortion,
        resolution=(64, 48),
    )
    agent = open_agent(tmp_path / "seq")
    assert agent.calib == calib  # the same K before and after undistortion
    image = agent.load_frame(1).image[..., 0].astype(np.float64)
    weights = np.where(image > 20, image, 0.0)
    centroid = np.array([(weights * u).sum(), (weights * v).sum()]) / weights.sum()
    np.testing.assert_allclose(centroid, target, atol=0.3)
    raw = blob > 20
    raw_centroid = np.array([(blob * raw * u).sum(), (blob * raw * v).sum()]) / (blob * raw).sum()
    assert np.linalg.norm(raw_centroid - target) > 2.0
    np.testing.assert_array_equal(next(iter(agent)).image, agent.load_frame(0).image)


def test_without_ground_truth(tmp_path):
    write_euroc(tmp_path / "seq", n=2, groundtruth=False)
    agent = open_agent(tmp_path / "seq")
    assert agent.groundtruth is None and not agent.has_gt_pose.any()
    input_error(
        "EuRoC sequence has no mav0/state_groundtruth_estimate0/data.csv",
        read_ground_truth,
        tmp_path / "seq",
    )


def test_frames_far_from_ground_truth_have_none(tmp_path):
    write_euroc(tmp_path / "seq", n=3)
    gt = tmp_path / "seq" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:10]) + "\n")  # 45 ms: frame 0 only
    agent = open_agent(tmp_path / "seq")
    np.testing.assert_array_equal(agent.has_gt_pose, [True, False, False])


# ---------------------------------------------------------------------------------- bad inputs


def _replace(path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(
    "old, new, fragment",
    [
        (
            "intrinsics: [30.0, 31.0, 15.5, 11.5]",
            "intrinsics: [30.0, 31.0, 15.5]",
            "sensor.yaml:15: expected 4 finite numbers (intrinsics: fu fv cu cv), got 3",
        ),
        (
            "intrinsics: [30.0, 31.0, 15.5, 11.5]",
            "intrinsics: [30.0, x, 15.5, 11.5]",
            "sensor.yaml:15: expected 4 numbers (intrinsics: fu fv cu cv), found text",
        ),
        (
            "intrinsics: [30.0, 31.0, 15.5, 11.5]",
            "intrinsics: [-30.0, 31.0, 15.5, 11.5]",
            "sensor.yaml:15: focal lengths must be positive",
        ),
        (
            "intrinsics: [30.0, 31.0, 15.5, 11.5] #fu, fv, cu, cv\n",
            "",
            "sensor.yaml: no 'intrinsics' entry",
        ),
        (
            "radial-tangential",
            "equidistant",
            "sensor.yaml:16: distortion_model 'equidistant' is not supported (only radial-tangential)",
        ),
        (
            "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]",
            "distortion_coefficients: [0.1]",
            "expected 4 finite numbers (distortion_coefficients: k1 k2 p1 p2 [k3]), got 1",
        ),
        ("data: [0.01", "data: [0.5", "sensor.yaml:6: T_BS: not a rigid camera-to-body transform"),
        ("  rows: 4\n", "  rows: [4\n", "sensor.yaml:9: not valid YAML"),
        (
            "resolution: [32, 24]",
            "resolution: [752, 480]",
            "sensor.yaml: resolution [752, 480] but the images are 32x24",
        ),
    ],
)
def test_malformed_sensor_yaml(tmp_path, old, new, fragment):
    write_euroc(tmp_path / "seq", n=2)
    _replace(tmp_path / "seq" / "mav0" / "cam0" / "sensor.yaml", old, new)
    input_error(fragment, open_agent, tmp_path / "seq")


def test_sensor_yaml_line_numbers_are_the_published_layout():
    lines = euroc_sensor_yaml().splitlines()
    assert lines[5] == "T_BS:" and lines[14].startswith("intrinsics:")


def test_missing_sensor_yaml(tmp_path):
    write_euroc(tmp_path / "seq", n=2)
    (tmp_path / "seq" / "mav0" / "cam0" / "sensor.yaml").unlink()
    input_error("cam0/sensor.yaml: missing (the camera's intrinsics", open_agent, tmp_path / "seq")
    input_error("cam0/sensor.yaml: missing", read_ground_truth, tmp_path / "seq")


def test_malformed_image_list(tmp_path):
    info = write_euroc(tmp_path / "seq", n=3)
    listing = tmp_path / "seq" / "mav0" / "cam0" / "data.csv"
    _replace(listing, f"{info['ns'][1]},", "14036x,")
    input_error("data.csv:3: not a timestamp: '14036x'", open_agent, tmp_path / "seq")
    _replace(listing, "14036x,", f"{info['ns'][2]},")
    input_error("data.csv:4: timestamps are not strictly increasing", open_agent, tmp_path / "seq")


def test_listed_image_missing(tmp_path):
    info = write_euroc(tmp_path / "seq", n=3)
    (tmp_path / "seq" / "mav0" / "cam0" / "data" / f"{info['ns'][1]}.png").unlink()
    input_error(f"{info['ns'][1]}.png: missing (listed in", open_agent, tmp_path / "seq")


@pytest.mark.parametrize(
    "line, fragment",
    [
        ("1403636579743555584,1.0,2.0", "data.csv:2: expected at least 8 comma-separated numbers"),
        ("1403636579743555584,1,2,3,0.5,0.5,0.5,0.1", "data.csv:2: quaternion q_RS norm 0.87"),
        ("1403636579743555584,1,2,nan,1,0,0,0", "data.csv:2: expected 8 finite numbers"),
        (
            "1403636579743555584,1,2,3,1,0,0,0\n1403636579743555584,1,2,3,1,0,0,0",
            "data.csv:3: timestamps are not strictly increasing",
        ),
    ],
)
def test_malformed_ground_truth(tmp_path, line, fragment):
    write_euroc(tmp_path / "seq", n=2)
    gt = tmp_path / "seq" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    header = gt.read_text().splitlines()[0]
    gt.write_text(f"{header}\n{line}\n")
    input_error(fragment, open_agent, tmp_path / "seq")
    input_error(fragment, read_ground_truth, tmp_path / "seq")
