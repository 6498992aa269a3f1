"""Ground-truth poses at image times (como3r.data.poses): interpolation within the gap rule,
on synthetic samples and on the real TUM freiburg3_teddy excerpt (its motion capture starts
after the camera) and a copy of it with a hole cut into its ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from como3r.data.agent import open_agent
from como3r.data.poses import MAX_GAP, poses_at, slerp
from como3r.io.tum import Trajectory, read_tum

from .shared_data import SHARED_DATA

TEDDY = SHARED_DATA / "tum_freiburg3_teddy_100/rgbd_dataset_freiburg3_teddy"
needs_teddy = pytest.mark.skipif(not TEDDY.is_dir(), reason=f"TUM excerpt not found at {TEDDY}")


def _trajectory(stamps: np.ndarray, seed: int = 0) -> Trajectory:
    rng = np.random.default_rng(seed)
    q = Rotation.random(len(stamps), random_state=seed).as_quat()  # xyzw
    rows = np.concatenate([rng.normal(size=(len(stamps), 3)), q, np.ones((len(stamps), 1))], 1)
    return Trajectory(np.asarray(stamps, dtype=np.float64), torch.from_numpy(rows))


def test_samples_are_returned_and_frames_between_them_interpolated():
    gt = _trajectory(np.array([0.0, 0.05, 0.1, 0.15]))
    frames = np.array([0.0, 0.02, 0.05, 0.0625, 0.15])
    out = poses_at(frames, gt).numpy()
    np.testing.assert_allclose(out[[0, 2, 4]], gt.T_WC.numpy()[[0, 1, 3]])
    rows = gt.T_WC.numpy()
    for k, (a, b, alpha) in ((1, (0, 1, 0.4)), (3, (1, 2, 0.25))):
        np.testing.assert_allclose(out[k, :3], (1 - alpha) * rows[a, :3] + alpha * rows[b, :3])
        expected = Slerp([0.0, 1.0], Rotation.from_quat(rows[[a, b], 3:7]))([alpha])
        assert (Rotation.from_quat(out[k, 3:7]) * expected.inv()).magnitude()[0] < 1e-9
        assert out[k, 7] == pytest.approx(1.0)


def test_frames_outside_the_samples_or_in_wide_gaps_have_no_pose():
    gt = _trajectory(np.array([1.0, 1.01, 1.2, 1.25, 1.3]))
    frames = np.array([0.9, 0.9995, 1.005, 1.1, 1.22, 1.3004, 1.31])
    has = torch.isfinite(poses_at(frames, gt)).all(1).numpy()
    # before; 0.5 ms before the first sample (its pose); between samples 10 ms apart; in a
    # 190 ms gap; between samples 50 ms apart; 0.4 ms after the last (its pose); after
    np.testing.assert_array_equal(has, [False, True, True, False, True, True, False])
    assert MAX_GAP == 0.1
    assert not torch.isfinite(poses_at(frames, None)).any()


def test_the_freiburg1_dropout_of_the_issue_is_bridged():
    """A real freiburg1 sequence: a 40 ms mocap dropout leaves frames whose nearest poses
    are 41 ms and 34 ms away (75 ms apart): interpolated, not refused."""
    gt = _trajectory(np.array([10.0 - 0.041, 10.0 + 0.034]))
    pose = poses_at(np.array([10.0]), gt)[0]
    assert torch.isfinite(pose).all()
    alpha = 0.041 / 0.075
    rows = gt.T_WC.numpy()
    np.testing.assert_allclose(pose[:3].numpy(), (1 - alpha) * rows[0, :3] + alpha * rows[1, :3])


def test_slerp_takes_the_shorter_arc():
    q0 = np.array([[0.0, 0.0, 0.0, 1.0]])
    q1 = -Rotation.from_euler("z", 90, degrees=True).as_quat()[None]  # the same rotation as +q
    mid = slerp(q0, q1, np.array([0.5]))
    assert Rotation.from_quat(mid[0]).magnitude() == pytest.approx(np.pi / 4)


@needs_teddy
def test_the_real_tum_excerpt_has_poses_after_its_motion_capture_starts():
    agent = open_agent(TEDDY)
    first_pose = float(agent.groundtruth.timestamps[0])
    has = agent.has_gt_pose
    assert agent.num_frames == 100 and has.sum() == 95
    np.testing.assert_array_equal(has, agent.timestamps >= first_pose)
    assert agent.missing_gt_warning().endswith(
        "5 of 100 frames have no ground-truth pose (5 before the first ground-truth pose)"
    )
    frame = agent.load_frame(50)
    t = agent.timestamps[50]
    gt = agent.groundtruth
    k = int(np.searchsorted(gt.timestamps, t))
    ends = gt.T_WC[[k - 1, k], :3].numpy()
    alpha = (t - gt.timestamps[k - 1]) / (gt.timestamps[k] - gt.timestamps[k - 1])
    np.testing.assert_allclose(frame.T_WC_gt[:3].numpy(), (1 - alpha) * ends[0] + alpha * ends[1])


def cut_hole(source: Path, target: Path, start: float, seconds: float) -> Path:
    """A copy of a TUM sequence folder (links to its images and lists) whose ground truth
    has no samples in ``[start, start + seconds)`` (seconds after its first sample)."""
    target.mkdir(parents=True)
    for name in ("rgb", "depth", "rgb.txt", "depth.txt"):
        (target / name).symlink_to(source / name)
    lines = (source / "groundtruth.txt").read_text().splitlines()
    first = read_tum(source / "groundtruth.txt").timestamps[0]
    kept = [
        line
        for line in lines
        if line.startswith("#") or not start <= float(line.split()[0]) - first < start + seconds
    ]
    (target / "groundtruth.txt").write_text("\n".join(kept) + "\n")
    return target


@needs_teddy
def test_a_40_ms_motion_capture_dropout_is_bridged(tmp_path):
    seq = cut_hole(TEDDY, tmp_path / "rgbd_dataset_freiburg3_teddy", 1.0, 0.04)
    agent = open_agent(seq)
    gaps = np.diff(agent.groundtruth.timestamps)
    assert 0.045 < gaps.max() < MAX_GAP  # 4 samples gone
    original = open_agent(TEDDY)
    np.testing.assert_array_equal(agent.has_gt_pose, original.has_gt_pose)
    # over 50 ms of slow hand-held motion linear interpolation stays within a few mm
    difference = (agent.gt_poses - original.gt_poses)[agent.has_gt_pose, :3].norm(dim=1)
    assert 0 < float(difference.max()) < 0.005


@needs_teddy
def test_a_wider_hole_leaves_its_frames_out(tmp_path):
    seq = cut_hole(TEDDY, tmp_path / "rgbd_dataset_freiburg3_teddy", 1.0, 0.3)
    agent = open_agent(seq)
    gt = agent.groundtruth.timestamps
    hole = (agent.timestamps > gt[0] + 0.99) & (agent.timestamps < gt[0] + 1.3)
    assert 8 <= hole.sum() <= 10
    np.testing.assert_array_equal(agent.has_gt_pose, (agent.timestamps >= gt[0]) & ~hole)
    assert (
        f"(5 before the first ground-truth pose, {int(hole.sum())} in gaps wider than "
        "0.1 s)" in agent.missing_gt_warning()
    )


def test_encodable_frames_of_the_simulated_prior(tmp_path):
    """Frames without a pose are left out unless surface maps key them; without any ground
    truth nothing is left out here (the prior says what is missing)."""
    from como3r.data.ground_truth import encodable, skipped_warning

    from .test_agent import write_agent

    stamps = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5]
    for name, surface in (("plain", False), ("keys", True)):
        root = write_agent(
            tmp_path / name, n=6, timestamps=stamps, surface=surface, groundtruth=True
        )
        rows = (root / "groundtruth.txt").read_text().splitlines()
        (root / "groundtruth.txt").write_text("\n".join(rows[-4:]) + "\n")  # from 0.2 s
        agent = open_agent(root)
        if surface:
            assert encodable(agent).all() and skipped_warning(agent) is None
        else:
            np.testing.assert_array_equal(encodable(agent), [False, False, True, True, True, True])
            assert skipped_warning(agent).endswith(
                "2 of 6 frames have no ground-truth pose (2 before the first ground-truth "
                "pose); --prior simulated skips them"
            )
    bare = open_agent(write_agent(tmp_path / "bare", n=3))
    assert encodable(bare).all() and skipped_warning(bare) is None
