"""Tests of como3r.backend.segments (C-Sec. A.6)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from como3r.backend.segments import (
    geometry_features,
    labels_in_order,
    parameter_labels,
    pixel_labels,
    segment_keyframe,
)
from como3r.config import DepthRefinementConfig
from como3r.errors import InputError

H, W, F = 72, 96, 80.0
STEP_COLUMN = 45


def pinhole_rays(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(H, W, 3)`` rays with unit z of a pinhole camera."""
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return torch.stack([(u - W / 2) / F, (v - H / 2) / F, torch.ones_like(u)], dim=-1)


def two_planes(dtype: torch.dtype, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """Fronto-parallel planes at z = 2 (left of STEP_COLUMN) and z = 3 (right)."""
    rays = pinhole_rays(torch.float64)
    z = torch.where(torch.arange(W) < STEP_COLUMN, 2.0, 3.0).expand(H, W)
    X = rays * z[..., None]
    if noise:
        generator = torch.Generator().manual_seed(seed)
        X = X * (1 + noise * torch.randn(H, W, 1, generator=generator, dtype=torch.float64))
    return X.to(dtype)


def test_features_normals_and_log_range(dtype):
    X = two_planes(dtype)
    features = geometry_features(X)
    assert features.shape == (H, W, 4)
    # Away from the step, both planes face the camera: normal (0, 0, -1).
    np.testing.assert_allclose(features[10, 5, :3], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(features[10, -5, :3], [0, 0, -1], atol=1e-6)
    log_range = features[..., 3]
    assert log_range.min() == pytest.approx(0.0) and log_range.max() == pytest.approx(1.0)
    assert log_range[:, STEP_COLUMN + 1 :].min() > log_range[:, : STEP_COLUMN - 1].max()


def test_features_of_non_finite_points_are_zero():
    X = two_planes(torch.float32)
    X[3, 4] = float("nan")
    features = geometry_features(X)
    assert np.isfinite(features).all()
    np.testing.assert_array_equal(features[3, 4], 0.0)


def test_segment_count_near_target_and_contiguous(dtype):
    X = two_planes(dtype, noise=0.002)
    config = DepthRefinementConfig()
    labels = segment_keyframe(X, torch.full((H, W), 3.0, dtype=dtype), config)
    assert labels.dtype == torch.int64 and labels.shape == (H, W)
    ids = torch.unique(labels)
    assert torch.equal(ids, torch.arange(int(ids.max()) + 1))
    assert 0.6 * config.slic_segments <= ids.numel() <= 1.4 * config.slic_segments


def test_low_confidence_pixels_are_labelled_invalid():
    X = two_planes(torch.float32)
    C = torch.full((H, W), 3.0)
    C[:10, :] = 1.0  # below slic_min_confidence = 1.5
    C[40, 40] = 1.49
    labels = segment_keyframe(X, C, DepthRefinementConfig())
    assert (labels[:10] == -1).all()
    assert labels[40, 40] == -1
    assert (labels[10:] >= 0).float().mean() > 0.95


def test_no_segment_below_min_valid_pixels():
    X = two_planes(torch.float32, noise=0.002)
    generator = torch.Generator().manual_seed(1)
    # Spatially noisy confidence leaves many segments with only a few valid pixels.
    C = torch.where(torch.rand(H, W, generator=generator) < 0.7, 1.0, 3.0)
    config = DepthRefinementConfig()
    labels = segment_keyframe(X, C, config)
    counts = torch.bincount(labels[labels >= 0])
    assert counts.numel() > 0
    assert int(counts.min()) >= config.min_valid_pixels
    assert (labels[C < config.slic_min_confidence] == -1).all()
    threshold = int(counts.float().median()) + 1
    strict = segment_keyframe(X, C, dataclasses.replace(config, min_valid_pixels=threshold))
    strict_counts = torch.bincount(strict[strict >= 0])
    assert int(strict_counts.min()) >= threshold
    assert strict_counts.numel() < counts.numel()


def test_boundaries_follow_a_depth_discontinuity():
    X = two_planes(torch.float32, noise=0.002)
    labels = segment_keyframe(X, torch.full((H, W), 3.0), DepthRefinementConfig()).numpy()
    columns = np.broadcast_to(np.arange(W), (H, W))
    # Central differences mark the two columns at the step; allow one pixel either side.
    away = np.abs(columns - STEP_COLUMN + 0.5) > 2
    left = columns < STEP_COLUMN
    mixed = 0
    for g in np.unique(labels):
        in_segment = (labels == g) & away
        mixed += min(int((in_segment & left).sum()), int((in_segment & ~left).sum()))
    assert mixed == 0


def test_pixel_labels_number_valid_pixels_in_raster_order():
    X = two_planes(torch.float32)
    C = torch.full((H, W), 3.0)
    C[0, :3] = 1.0
    labels = pixel_labels(X, C, DepthRefinementConfig())
    assert (labels[0, :3] == -1).all()
    assert labels[0, 3] == 0 and labels[-1, -1] == H * W - 4
    pixel_config = DepthRefinementConfig(variant="pixel_laplacian")
    assert torch.equal(parameter_labels(X, C, pixel_config), labels)


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError, match="pointmap"):
        segment_keyframe(torch.zeros(4, 4), torch.ones(4, 4), DepthRefinementConfig())
    with pytest.raises(InputError, match="confidence"):
        segment_keyframe(torch.zeros(4, 4, 3), torch.ones(4, 5), DepthRefinementConfig())


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_label_maps_come_in_order_from_any_number_of_threads(workers):
    """Five keyframes segmented on ``workers`` threads: each its own label map, in the order
    given, and never more than ``workers`` pointmaps read ahead of the labels handed out."""
    config = DepthRefinementConfig()
    keyframes = [two_planes(torch.float32, noise=0.002, seed=seed) for seed in range(5)]
    C = torch.full((H, W), 3.0)
    read = []

    def pointmaps():
        for key, X in zip("abcde", keyframes):
            read.append(key)
            yield key, X, C

    handed_out = []
    for key, labels in labels_in_order(pointmaps(), config, workers):
        assert len(read) - len(handed_out) <= workers
        handed_out.append(key)
        assert torch.equal(labels, segment_keyframe(keyframes["abcde".index(key)], C, config))
    assert handed_out == list("abcde")
