"""VIO-like odometry simulation and keyframe selection (decentralized/odometry_sim.py,
decentralized/keyframes.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from como3r.data.agent import open_agent
from como3r.decentralized.keyframes import frame_odometry, frame_poses, select_keyframes
from como3r.decentralized.odometry_sim import (
    ODOMETRY_PRESETS,
    OdometryNoise,
    add_odometry,
    simulate_odometry,
)
from como3r.errors import InputError
from como3r.geometry.lie import sim3_compose, sim3_inverse
from como3r.io.tum import Trajectory, read_tum, write_tum


def _straight_line(count: int = 400, step: float = 0.05) -> Trajectory:
    """A camera driving along world x, 1.5 m above the ground, looking forward."""
    positions = np.stack([step * np.arange(count), np.zeros(count), np.full(count, 1.5)], 1)
    # OpenCV camera looking along +x with z up: columns right (-y), down (-z), forward (+x).
    quat = np.tile([-0.5, 0.5, -0.5, 0.5], (count, 1))
    poses = np.concatenate([positions, quat, np.ones((count, 1))], 1)
    return Trajectory(np.arange(count) / 30.0, torch.from_numpy(poses))


def _step_lengths(trajectory: Trajectory) -> np.ndarray:
    return np.linalg.norm(np.diff(trajectory.T_WC[:, :3].numpy(), axis=0), axis=1)


def test_vio_scale_is_off_at_the_start_and_converges():
    truth = _straight_line()
    odometry = simulate_odometry(
        truth,
        seed=1,
        noise=OdometryNoise(
            initial_scale_error=0.3,
            scale_convergence_depths=0.3,
            scale_drift=0.0,
            yaw_drift_deg_per_depth=0.0,
            yaw_walk_deg_per_sqrt_depth=0.0,
            translation_walk_per_sqrt_depth=0.0,
        ),
        scene_depth=6.5,
    )
    ratio = _step_lengths(odometry) / _step_lengths(truth)
    assert abs(ratio[0] - 1.0) == pytest.approx(0.3, abs=0.01)
    np.testing.assert_allclose(ratio[-50:], 1.0, atol=1e-3)  # 17 m = 2.6 depths later


@pytest.mark.parametrize("factor", [0.1, 20.0])
def test_odometry_of_a_scaled_scene_is_the_scaled_odometry(factor):
    """Drift is a fraction of the distance travelled in scene depths: scaling the world
    scales the odometry and nothing else."""
    truth = _straight_line(100)
    scaled = truth.T_WC.clone()
    scaled[:, :3] *= factor
    odometry = simulate_odometry(truth, seed=5, scene_depth=6.5)
    odometry_scaled = simulate_odometry(
        Trajectory(truth.timestamps, scaled), seed=5, scene_depth=6.5 * factor
    )
    torch.testing.assert_close(odometry_scaled.T_WC[:, :3], factor * odometry.T_WC[:, :3])
    torch.testing.assert_close(odometry_scaled.T_WC[:, 3:], odometry.T_WC[:, 3:])


def test_odometry_is_in_its_own_gravity_aligned_frame():
    truth = _straight_line()
    odometry = simulate_odometry(truth, seed=2, noise=ODOMETRY_PRESETS["lio"], scene_depth=6.5)
    np.testing.assert_allclose(odometry.T_WC[0, :3].numpy(), 0.0, atol=1e-12)
    # The frame is turned about gravity only: heights and the camera's tilt are preserved.
    np.testing.assert_allclose(odometry.T_WC[:, 2].numpy(), 0.0, atol=0.05)
    relative_true = sim3_compose(sim3_inverse(truth.T_WC[0]), truth.T_WC[-1])
    relative_odom = sim3_compose(sim3_inverse(odometry.T_WC[0]), odometry.T_WC[-1])
    drift = float((relative_true[:3] - relative_odom[:3]).norm())
    assert 0.0 < drift < 0.02 * 20.0  # LIO: under 2 % of the 20 m travelled


def test_odometry_is_seeded():
    truth = _straight_line(50)
    a, b = (
        simulate_odometry(truth, 3, scene_depth=5.0),
        simulate_odometry(truth, 3, scene_depth=5.0),
    )
    c = simulate_odometry(truth, 4, scene_depth=5.0)
    assert torch.equal(a.T_WC, b.T_WC)
    assert not torch.equal(a.T_WC, c.T_WC)


def test_add_odometry_writes_a_file_open_agent_reads(tmp_path):
    folder = tmp_path / "agent"
    (folder / "rgb").mkdir(parents=True)
    truth = _straight_line(5)
    from PIL import Image

    for k in range(5):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / "rgb" / f"{k:06d}.png")
    write_tum(folder / "groundtruth.txt", truth.timestamps, truth.T_WC)
    with pytest.raises(InputError, match="no depth"):
        add_odometry(folder, seed=0, params="vio")
    path = add_odometry(folder, seed=0, params="vio", scene_depth=5.0)
    assert path == folder / "odometry.txt"
    agent = open_agent(folder)
    assert agent.odometry is not None and len(agent.odometry) == 5
    assert len(frame_odometry(agent)) == 5
    with pytest.raises(InputError, match="unknown odometry model"):
        add_odometry(folder, seed=0, params="wheel", scene_depth=5.0)
    with pytest.raises(InputError, match="groundtruth.txt"):
        add_odometry(tmp_path, seed=0)


def test_frame_odometry_needs_odometry(tmp_path):
    folder = tmp_path / "agent"
    (folder / "rgb").mkdir(parents=True)
    from PIL import Image

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / "rgb" / "0.png")
    with pytest.raises(InputError, match="odometry.txt"):
        frame_odometry(open_agent(folder))


def _frame_odometry_of(trajectory: Trajectory):
    from como3r.decentralized.keyframes import FrameOdometry

    return FrameOdometry(np.arange(len(trajectory)), trajectory.timestamps, trajectory.T_WC)


def test_keyframes_every_distance_travelled():
    odometry = _frame_odometry_of(_straight_line(101, step=0.05))
    keyframes = select_keyframes(odometry, 0.5)
    np.testing.assert_array_equal(keyframes.rows, np.arange(0, 101, 10))
    assert keyframes.up_to(keyframes.timestamps[3]) == 4
    assert keyframes.up_to(-1.0) == 0


def test_frame_poses_follow_the_keyframe_estimates_and_the_odometry():
    odometry = _frame_odometry_of(_straight_line(41, step=0.05))
    keyframes = select_keyframes(odometry, 0.5)
    torch.testing.assert_close(frame_poses(odometry, keyframes, np.zeros((0, 8))), odometry.T_OC)
    # Move the estimated keyframes 1 m up: every frame they cover moves with them, the frames
    # after the last estimated keyframe too (by odometry).
    estimate = keyframes.T_OC[:2].numpy().copy()
    estimate[:, 2] += 1.0
    poses = frame_poses(odometry, keyframes, estimate)
    np.testing.assert_allclose(
        (poses[:, :3] - odometry.T_OC[:, :3]).numpy(), np.tile([0.0, 0.0, 1.0], (41, 1)), atol=1e-9
    )
    assert math.isclose(float(poses[:, 3:7].norm(dim=1).max()), 1.0, abs_tol=1e-12)


def test_scene_odometry_files_exist(scene):
    for path in scene:
        odometry = read_tum(path / "odometry.txt")
        assert len(odometry) == len(read_tum(path / "groundtruth.txt"))
