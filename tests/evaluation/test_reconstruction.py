"""Tests of como3r.evaluation.reconstruction."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.evaluation.reconstruction import (
    VoxelCentroids,
    cloud_from_depth,
    evaluate_maps,
    ground_truth_cloud,
    keyframe_cloud,
    reconstruction_metrics,
    voxel_downsample,
)
from como3r.evaluation.trajectory import Sim3Alignment
from como3r.geometry.camera import intrinsics_matrix
from como3r.geometry.lie import sim3_act, sim3_exp
from como3r.io.tum import write_tum


def grid(n: int = 5, spacing: float = 1.0) -> np.ndarray:
    """``(n^3, 3)`` points of a cubic grid."""
    axis = np.arange(n) * spacing
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def test_identical_clouds_are_perfect():
    points = grid()
    m = reconstruction_metrics(points, points, threshold=0.1)
    assert (m.accuracy, m.completeness, m.chamfer) == (0.0, 0.0, 0.0)
    assert (m.precision, m.recall, m.fscore) == (1.0, 1.0, 1.0)
    assert m.num_estimated == m.num_ground_truth == 125


def test_shifted_copy_has_the_shift_as_every_distance():
    gt = grid()
    est = gt + np.array([0.0, 0.3, 0.4])  # |shift| = 0.5: every nearest neighbour is its copy
    m = reconstruction_metrics(est, gt, threshold=0.6)
    assert m.accuracy == pytest.approx(0.5)
    assert m.completeness == pytest.approx(0.5)
    assert m.chamfer == pytest.approx(0.5)
    assert (m.precision, m.recall) == (1.0, 1.0)
    far = reconstruction_metrics(est, gt, threshold=0.4)
    assert (far.precision, far.recall, far.fscore) == (0.0, 0.0, 0.0)


def test_partial_estimate_is_accurate_but_incomplete():
    gt = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], 1)
    est = gt[:5]
    m = reconstruction_metrics(est, gt, threshold=0.5)
    assert m.accuracy == 0.0
    assert m.completeness == pytest.approx((1 + 2 + 3 + 4 + 5) / 10)
    assert m.chamfer == pytest.approx(0.75)
    assert (m.precision, m.recall) == (1.0, 0.5)
    assert m.fscore == pytest.approx(2 * 0.5 / 1.5)


def test_alignment_is_applied_to_the_estimate():
    gt = grid(4, 0.5)
    rotation = Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix()
    alignment = Sim3Alignment(rotation, np.array([1.0, -2.0, 0.5]), 2.5)
    est = ((gt - alignment.translation) @ rotation) / alignment.scale  # inverse of apply
    assert reconstruction_metrics(est, gt).accuracy > 0.1
    m = reconstruction_metrics(est, gt, alignment=alignment)
    assert m.accuracy == pytest.approx(0.0, abs=1e-9)
    assert m.completeness == pytest.approx(0.0, abs=1e-9)


def test_voxel_downsample_averages_each_voxel():
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [1.5, 0.2, 0.2], [-0.2, 0.0, 0.0]])
    down = voxel_downsample(points, 1.0)
    assert down.shape == (3, 3)
    expected = {(-0.2, 0.0, 0.0), (0.2, 0.1, 0.1), (1.5, 0.2, 0.2)}
    assert {tuple(np.round(p, 9)) for p in down} == expected
    np.testing.assert_array_equal(voxel_downsample(points, 0.0), points)


def test_voxel_centroids_given_in_pieces_equal_the_whole_cloud_downsampled():
    points = np.random.default_rng(1).normal(size=(5000, 3)) * [4.0, 2.0, 1.0]
    voxels = VoxelCentroids(0.5, buffer_points=700)  # merges 7 times, across voxels
    for piece in np.array_split(points, 13):
        voxels.add(piece)
    whole = voxel_downsample(points, 0.5)
    np.testing.assert_allclose(voxels.centroids(), whole, rtol=0, atol=1e-12)
    assert voxels._counts.sum() == 5000 and len(voxels._pending) == 0
    with pytest.raises(InputError, match="voxel size must be positive"):
        VoxelCentroids(0.0)


@pytest.mark.parametrize("extent", ["small", "beyond one int64 key"])
def test_unique_voxel_rows_are_those_of_the_row_wise_sort(extent):
    from como3r.evaluation.reconstruction import unique_rows

    cells = np.random.default_rng(2).integers(-5, 5, size=(2000, 3))
    if extent != "small":
        cells[0] = [2**40, -(2**40), 2**40]
    unique, inverse = unique_rows(cells)
    expected, expected_inverse = np.unique(cells, axis=0, return_inverse=True)
    np.testing.assert_array_equal(unique, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))


def test_voxel_size_evens_out_density():
    sparse = grid(3, 1.0)
    dense_corner = np.random.default_rng(0).uniform(0, 0.2, size=(500, 3))
    gt = np.concatenate([sparse, dense_corner])
    est = sparse
    assert reconstruction_metrics(est, gt, voxel_size=0.5).num_ground_truth == 27


def test_invalid_clouds_raise_input_error():
    with pytest.raises(InputError, match="estimated cloud must be"):
        reconstruction_metrics(np.zeros((4, 2)), grid())
    with pytest.raises(InputError, match="ground-truth cloud is empty"):
        reconstruction_metrics(grid(), np.full((2, 3), np.nan))
    with pytest.raises(InputError, match="threshold"):
        reconstruction_metrics(grid(), grid(), threshold=0.0)


def test_keyframe_cloud_thresholds_confidence_and_lifts_to_world():
    X = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 0.0, 2.0]]])
    C = torch.tensor([[3.0, 1.0]])
    T_WC = sim3_exp(torch.tensor([[1.0, 2.0, 3.0, 0.0, 0.0, 0.5, 0.2]]))
    cloud = keyframe_cloud([X], [C], T_WC, min_confidence=1.5)
    expected = sim3_act(T_WC[0].double(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    np.testing.assert_allclose(cloud, expected.numpy()[None], atol=1e-6)


def test_cloud_from_depth_unprojects_z_depth():
    K = intrinsics_matrix(10.0, 10.0, 2.0, 1.0, dtype=torch.float64)
    depth = np.full((3, 5), 2.0)
    depth[0, 0] = 0.0  # no depth
    T_WC = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0], dtype=torch.float64)
    points = cloud_from_depth(depth, K, T_WC)
    assert points.shape == (14, 3)
    np.testing.assert_allclose(points[:, 2], 3.0)
    # Pixel (u=2, v=1) is the principal point: straight ahead.
    assert np.any(np.all(np.isclose(points, [0.0, 0.0, 3.0]), axis=1))
    assert cloud_from_depth(depth, K, T_WC, max_depth=1.0).shape == (0, 3)
    assert cloud_from_depth(depth, K, T_WC, pixel_stride=2).shape == (5, 3)


def write_agent(root: Path, n: int = 3, with_depth: bool = True) -> Path:
    """An agent folder whose frames see a wall at z = 2 from positions x = 0, 0.1, 0.2."""
    (root / "rgb").mkdir(parents=True)
    if with_depth:
        (root / "depth").mkdir()
    for i in range(n):
        Image.fromarray(np.zeros((6, 8, 3), dtype=np.uint8)).save(root / "rgb" / f"{i:04d}.png")
        if with_depth:
            np.save(root / "depth" / f"{i:04d}.npy", np.full((6, 8), 2.0, dtype=np.float32))
    (root / "calib.txt").write_text("8 8 3.5 2.5\n")
    poses = torch.zeros(n, 8, dtype=torch.float64)
    poses[:, 0] = 0.1 * torch.arange(n)
    poses[:, 6] = poses[:, 7] = 1.0
    write_tum(root / "groundtruth.txt", np.arange(n) / 30.0, poses)
    return root


def test_ground_truth_cloud_from_agent_folders(tmp_path):
    agent = write_agent(tmp_path / "a")
    cloud = ground_truth_cloud([agent])
    assert cloud.shape == (3 * 48, 3)
    np.testing.assert_allclose(cloud[:, 2], 2.0, atol=1e-6)
    # Leftmost point: column 0 of frame 0 (at x = 0); rightmost: column 7 of frame 2 (x = 0.2).
    assert cloud[:, 0].min() == pytest.approx(2.0 * (0 - 3.5) / 8, abs=1e-6)
    assert cloud[:, 0].max() == pytest.approx(0.2 + 2.0 * (7 - 3.5) / 8, abs=1e-6)
    strided = ground_truth_cloud([agent], frame_stride=2, pixel_stride=2)
    assert strided.shape == (2 * 12, 3)
    voxels = ground_truth_cloud([agent], voxel_size=10.0)
    assert voxels.shape[0] == len(np.unique(np.floor(cloud / 10.0), axis=0))


def test_map_metrics_of_an_estimate_in_pieces_equal_those_of_the_whole(tmp_path):
    """evaluate_maps reduces each estimate to voxels piece by piece (a long run's map is
    never held whole): the metrics are those of the whole cloud aligned and downsampled."""
    from como3r.data.agent import open_agent
    from como3r.evaluation.reconstruction import MAP_THRESHOLD_RATIO, MAP_VOXEL_RATIO

    agent = open_agent(write_agent(tmp_path / "a", n=3))
    alignment = Sim3Alignment(
        Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix(), np.array([0.5, -1.0, 0.2]), 1.7
    )
    truth = ground_truth_cloud([agent])
    rng = np.random.default_rng(0)
    estimate = (
        (truth + rng.normal(scale=0.01, size=truth.shape) - alignment.translation)
        @ alignment.rotation
        / alignment.scale
    )
    estimate[5] = np.nan  # dropped
    scores = evaluate_maps(
        [agent], {"whole": [estimate], "pieces": np.array_split(estimate, 7)}, alignment
    )
    assert scores["pieces"] == scores["whole"]
    reference = reconstruction_metrics(
        estimate, truth, MAP_THRESHOLD_RATIO * 2.0, alignment, MAP_VOXEL_RATIO * 2.0
    )  # median depth: 2 m
    assert scores["whole"].num_estimated == reference.num_estimated
    assert scores["whole"].accuracy == pytest.approx(reference.accuracy, rel=1e-9)
    assert scores["whole"].fscore == pytest.approx(reference.fscore, rel=1e-9)


def test_ground_truth_cloud_needs_depth(tmp_path):
    agent = write_agent(tmp_path / "nodepth", with_depth=False)
    with pytest.raises(InputError, match="needs depth/"):
        ground_truth_cloud([agent])


def test_map_metrics_are_relative_to_the_median_ground_truth_depth() -> None:
    from types import SimpleNamespace

    from como3r.evaluation.reconstruction import median_ground_truth_depth

    def agent(scale: float) -> SimpleNamespace:
        depths = [np.full((4, 5), 2.0 + k, dtype=np.float32) * scale for k in range(10)]
        depths[3][0, 0] = 0.0  # no depth: ignored
        return SimpleNamespace(
            has_gt_pose=np.ones(10, dtype=bool),
            load_frame=lambda i: SimpleNamespace(depth=depths[i]),
        )

    base = median_ground_truth_depth([agent(1.0)])
    assert 2.0 < base < 12.0
    assert median_ground_truth_depth([agent(20.0)]) == pytest.approx(20.0 * base)
    with pytest.raises(InputError, match="no frame with a valid"):
        median_ground_truth_depth([agent(0.0)])
