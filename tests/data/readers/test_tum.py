"""Tests of como3r.data.readers.tum: a TUM RGB-D sequence folder as published."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.readers import read_ground_truth
from como3r.data.readers.tum import DISTORTION, INTRINSICS, associate, camera_from_name

from .layouts import HEIGHT, WIDTH, depth_metres, input_error, pixels, write_tum

NAME = "rgbd_dataset_freiburg3_long_office_household"  # fr3: published undistorted


def test_sequence_is_read_as_published(tmp_path):
    root = tmp_path / NAME
    written = write_tum(root, n=5)
    agent = open_agent(root)
    assert agent.format == "tum" and agent.num_frames == 5
    assert agent.image_size == (WIDTH, HEIGHT) and agent.name == NAME
    np.testing.assert_allclose(agent.timestamps, np.round(written["rgb"], 6), atol=1e-6)
    assert agent.calib == INTRINSICS[3] == (535.4, 539.2, 320.1, 247.6)
    frame = agent.load_frame(3)
    np.testing.assert_array_equal(frame.image, pixels(3))
    expected = np.round(depth_metres(3) * 5000) / 5000
    expected[0, 0] = 0.0  # 0 = no data
    np.testing.assert_allclose(frame.depth, expected, atol=1e-6)
    assert frame.depth.dtype == np.float32
    # ground truth: the 100 Hz sample at the frame's time (within 1 ms)
    gt_stamps, rows = written["gt"]
    row = int(np.argmin(np.abs(gt_stamps - agent.timestamps[3])))
    torch.testing.assert_close(
        frame.T_WC_gt[:3], torch.from_numpy(np.round(rows[row, :3], 6)), atol=1e-6, rtol=0
    )
    assert frame.T_WC_gt[7] == 1.0


@pytest.mark.parametrize(
    "name, calib",
    [
        ("rgbd_dataset_freiburg1_xyz", (517.3, 516.5, 318.6, 255.3)),
        ("rgbd_dataset_freiburg2_desk", (520.9, 521.0, 325.1, 249.7)),
        ("rgbd_dataset_freiburg3_long_office_household", (535.4, 539.2, 320.1, 247.6)),
        ("rgbd_dataset_freiburg12_x", None),
        ("my_sequence", None),
    ],
)
def test_intrinsics_from_the_folder_name(name, calib):
    assert camera_from_name(name)[0] == calib


def _full_size_frames(seq) -> None:
    """Replace a written sequence's images and depth maps with 640x480 ones (the size the
    freiburg intrinsics are for): a checkerboard and depth steps of 0.1 m."""
    v, u = np.mgrid[0:480, 0:640]
    board = (((u // 20) + (v // 20)) % 2 * 200 + 20).astype(np.uint8)
    for png in (seq / "rgb").iterdir():
        Image.fromarray(np.stack([board, board, 255 - board], -1)).save(png)
    steps = (5000 * (1.0 + 0.1 * ((u // 40) % 7))).astype(np.uint16)
    for png in (seq / "depth").iterdir():
        Image.fromarray(steps).save(png)


def test_freiburg1_frames_are_undistorted_colour_and_depth_alike(tmp_path):
    # the raw fr1 images bend straight lines: the reader undoes the published d0-d4
    seq = tmp_path / "rgbd_dataset_freiburg1_desk"
    write_tum(seq, n=2)
    _full_size_frames(seq)
    source = open_agent(seq)
    assert source.calib == INTRINSICS[1] and not source.frames_are_files
    raw = np.asarray(Image.open(source.image_paths[0]).convert("RGB"))
    fx, fy, cx, cy = INTRINSICS[1]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    expected = cv2.undistort(raw, K, np.array(DISTORTION[1]))
    frame = source.load_frame(0)
    assert np.abs(frame.image.astype(int) - expected.astype(int)).mean() < 2.0
    assert np.abs(frame.image.astype(int) - raw.astype(int)).mean() > 10.0
    # depth by nearest neighbour: every value is one of the raw map's, none interpolated
    raw_depth = np.asarray(Image.open(source.depth_paths[0])).astype(np.float32) / 5000.0
    assert set(np.unique(frame.depth).tolist()) <= set(np.unique(raw_depth).tolist()) | {0.0}
    assert not np.array_equal(frame.depth, raw_depth)
    fr3 = tmp_path / "rgbd_dataset_freiburg3_office"
    write_tum(fr3, n=2)
    assert open_agent(fr3).frames_are_files  # fr3 is published undistorted


def test_calib_txt_overrides_the_name_and_unknown_names_are_uncalibrated(tmp_path):
    write_tum(tmp_path / "rgbd_dataset_freiburg2_x", n=3)
    (tmp_path / "rgbd_dataset_freiburg2_x" / "calib.txt").write_text("100 101 16 12\n")
    assert open_agent(tmp_path / "rgbd_dataset_freiburg2_x").calib == (100, 101, 16, 12)
    write_tum(tmp_path / "sequence", n=3)
    assert open_agent(tmp_path / "sequence").calib is None


def test_rgb_without_a_depth_partner_is_left_out(tmp_path, caplog):
    """associate.py pairs: frame 2's depth was dropped, so frame 2 is not a frame."""
    root = tmp_path / NAME
    written = write_tum(root, n=5, drop_depth=(2,))
    agent = open_agent(root)
    assert agent.num_frames == 4
    np.testing.assert_allclose(
        agent.timestamps, np.round(written["rgb"][[0, 1, 3, 4]], 6), atol=1e-6
    )
    assert "1 of 5 rgb images have no depth image" in caplog.text
    assert agent.load_frame(2).depth[5, 5] == pytest.approx(depth_metres(3)[5, 5], abs=2e-4)


def test_association_is_one_to_one_by_smallest_difference(tmp_path):
    """A second depth image 0.012 s before frame 1 loses to the one 0.004 s after it."""
    root = tmp_path / NAME
    write_tum(root, n=4, extra_depth=True)
    agent = open_agent(root)
    assert agent.num_frames == 4
    assert agent.load_frame(1).depth[5, 5] != pytest.approx(1234 / 5000)


def test_associate_matches_tum_associate_py():
    rng = np.random.default_rng(0)
    first = np.sort(rng.uniform(0, 1, 40))
    second = np.sort(rng.uniform(0, 1, 35))
    # associate.py, literally: every candidate pair, greedily by difference
    candidates = sorted(
        (abs(a - b), i, j)
        for (i, a), (j, b) in itertools.product(enumerate(first), enumerate(second))
        if abs(a - b) < 0.02
    )
    used_i, used_j, expected = set(), set(), []
    for _, i, j in candidates:
        if i not in used_i and j not in used_j:
            used_i.add(i), used_j.add(j), expected.append((i, j))
    assert associate(first, second, 0.02) == sorted(expected)
    assert associate(np.array([0.0]), np.array([0.02])) == []  # strictly closer than 0.02


def test_without_depth_or_groundtruth(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3, depth=False, groundtruth=False)
    agent = open_agent(root)
    assert agent.num_frames == 3 and not agent.has_depth and agent.groundtruth is None
    assert not agent.has_gt_pose.any()
    input_error("no groundtruth.txt", read_ground_truth, root)


def test_frames_outside_the_groundtruth_have_none(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3)
    gt = root / "groundtruth.txt"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:3] + lines[3 + 10 :]) + "\n")  # first 0.1 s gone
    agent = open_agent(root)  # poses from +0.05 s: frames 0 and 1 (33 ms) come before them
    np.testing.assert_array_equal(agent.has_gt_pose, [False, False, True])


def test_ground_truth_for_eval_is_the_published_file(tmp_path):
    root = tmp_path / NAME
    written = write_tum(root, n=3)
    source, trajectory = read_ground_truth(root)
    assert source == root / "groundtruth.txt"
    assert len(trajectory) == len(written["gt"][0])


# ---------------------------------------------------------------------------------- bad inputs


def test_listed_image_missing(tmp_path):
    root = tmp_path / NAME
    stamps = write_tum(root, n=3)["rgb"]
    (root / "rgb" / f"{stamps[1]:.6f}.png").unlink()
    input_error(
        f"rgb/{stamps[1]:.6f}.png: missing (listed in {root / 'rgb.txt'}:5)", open_agent, root
    )


def test_listed_depth_missing(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3)
    next((root / "depth").iterdir()).unlink()
    input_error("missing (listed in", open_agent, root)


def test_unreadable_image(tmp_path):
    root = tmp_path / NAME
    stamps = write_tum(root, n=3)["rgb"]
    (root / "rgb" / f"{stamps[2]:.6f}.png").write_bytes(b"not a png")
    input_error(f"{stamps[2]:.6f}.png: cannot read image", open_agent, root)


def test_depth_that_is_not_16_bit(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3)
    path = sorted((root / "depth").iterdir())[1]
    Image.fromarray(np.zeros((HEIGHT, WIDTH), np.uint8)).save(path)
    input_error("16-bit", open_agent, root)


@pytest.mark.parametrize(
    "line, fragment",
    [
        ("1305031102.5 rgb/a.png extra", "expected 'timestamp filename'"),
        ("abc rgb/a.png", "not a timestamp"),
        ("1305031101.0 rgb/a.png", "timestamps are not strictly increasing"),
    ],
)
def test_malformed_rgb_txt(tmp_path, line, fragment):
    root = tmp_path / NAME
    write_tum(root, n=3)
    with open(root / "rgb.txt", "a") as f:
        f.write(line + "\n")
    input_error(f"{root / 'rgb.txt'}:7: {fragment}", open_agent, root)


def test_empty_rgb_txt(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3)
    (root / "rgb.txt").write_text("# nothing\n")
    input_error("no 'timestamp filename' entries", open_agent, root)


def test_depth_far_from_every_image(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3, depth_offset=0.5)
    input_error("depth.txt: no depth image within 0.02 s", open_agent, root)


def test_malformed_groundtruth(tmp_path):
    root = tmp_path / NAME
    write_tum(root, n=3)
    with open(root / "groundtruth.txt", "a") as f:
        f.write("1 2 3\n")
    input_error("groundtruth.txt:", open_agent, root)


def _associations(root, frames, depth_first=False):
    """``associations.txt`` of the given frames of a :func:`write_tum` folder, as
    ``associate.py rgb.txt depth.txt`` writes it (``depth_first``: the other way round)."""

    def entries(name):
        rows = [
            line.split()
            for line in (root / name).read_text().splitlines()
            if not line.startswith("#")
        ]
        return [rows[i] for i in frames]

    pairs = zip(entries("rgb.txt"), entries("depth.txt"))
    lines = [" ".join(d + r if depth_first else r + d) for r, d in pairs]
    (root / "associations.txt").write_text("\n".join(lines) + "\n")


def test_associations_txt_gives_the_frames(tmp_path):
    """A user's associate.py output (ORB-SLAM's TUM examples ask for one) is taken as the
    pairing, beside the lists or without them, in either column order."""
    root = tmp_path / NAME
    write_tum(root, n=5)
    _associations(root, [0, 2, 3])
    agent = open_agent(root)
    assert agent.format == "tum" and agent.num_frames == 3 and agent.has_depth
    full = tmp_path / "full" / NAME
    write_tum(full, n=5)
    expected = open_agent(full)
    assert [p.name for p in agent.depth_paths] == [expected.depth_paths[i].name for i in (0, 2, 3)]
    np.testing.assert_allclose(agent.timestamps, expected.timestamps[[0, 2, 3]])
    np.testing.assert_array_equal(agent.load_frame(1).depth, expected.load_frame(2).depth)
    np.testing.assert_array_equal(agent.load_frame(1).image, pixels(2))
    _associations(root, [1, 4], depth_first=True)
    (root / "rgb.txt").unlink()
    (root / "depth.txt").unlink()
    agent = open_agent(root)
    np.testing.assert_allclose(agent.timestamps, expected.timestamps[[1, 4]])
    np.testing.assert_array_equal(agent.load_frame(1).depth, expected.load_frame(4).depth)
    assert agent.has_gt_pose.all()


@pytest.mark.parametrize(
    "line, fragment",
    [
        (
            "1305031102.0 rgb/a.png 1305031102.0",
            "associations.txt:1: expected 'rgb_timestamp rgb_file depth_timestamp depth_file'",
        ),
        ("1305031102.0 rgb/a.png 1305031102.0 depth/a.png", "rgb/a.png: missing (listed in"),
        ("x rgb/a.png 1305031102.0 depth/a.png", "associations.txt:1: not a timestamp: 'x'"),
    ],
)
def test_malformed_associations(tmp_path, line, fragment):
    root = tmp_path / NAME
    write_tum(root, n=2)
    (root / "associations.txt").write_text(line + "\n")
    input_error(fragment, open_agent, root)
