"""Scene units (geometry/units.py): relative lengths and pixel quantities."""

from __future__ import annotations

import pytest
import torch

from como3r.geometry.units import median_point_range, median_range, pixels_at, scene_depth


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_median_range_scales_with_the_scene(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    X = torch.randn(2, 6, 8, 3, generator=g, dtype=dtype) + torch.tensor(
        [0.0, 0.0, 5.0], dtype=dtype
    )
    base = median_range(X)
    assert base.shape == (2,)
    assert torch.allclose(median_range(20.0 * X), 20.0 * base)
    assert torch.allclose(median_point_range(X.reshape(2, 48, 3)), base)


def test_median_range_ignores_invalid_points_and_has_a_fallback() -> None:
    X = torch.zeros(1, 2, 2, 3)
    X[0, 0, 0] = torch.tensor([0.0, 0.0, 2.0])
    X[0, 0, 1] = torch.tensor([0.0, 0.0, float("nan")])
    valid = torch.ones(1, 2, 2, dtype=torch.bool)
    assert float(median_range(X, valid)[0]) == pytest.approx(2.0)
    assert float(median_range(X, torch.zeros_like(valid))[0]) == 1.0


@pytest.mark.parametrize(
    ("value", "long_side", "expected"),
    [(3, 512, 3), (5, 512, 5), (3, 1024, 6), (3, 256, 2), (3, 64, 1)],
)
def test_pixels_scale_with_the_long_side(value: int, long_side: int, expected: int) -> None:
    assert pixels_at(value, long_side) == expected


def test_scene_depth_is_the_median_keyframe_depth_in_world_units() -> None:
    X = torch.zeros(3, 4, 5, 3)
    X[..., 2] = torch.tensor([1.0, 2.0, 4.0])[:, None, None]  # median ranges 1, 2, 4
    T_WC = torch.zeros(3, 8)
    T_WC[:, 6] = 1.0
    T_WC[:, 7] = torch.tensor([3.0, 1.0, 0.5])  # world depths 3, 2, 2
    assert scene_depth(T_WC, X) == pytest.approx(2.0)
    assert scene_depth([], []) == 1.0
