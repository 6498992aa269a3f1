"""Tests of como3r.geometry.camera: pinhole intrinsics, pixel grid, (un)projection."""

from __future__ import annotations

import torch

from como3r.geometry.camera import (
    crop_intrinsics,
    estimate_focal,
    intrinsics_matrix,
    pixel_grid,
    project,
    rays_from_intrinsics,
    scale_intrinsics,
    unproject_depth,
)
from como3r.geometry.residuals import psi

F64 = torch.float64


def tol(dtype: torch.dtype) -> dict[str, float]:
    return {"rtol": 1e-12, "atol": 1e-9} if dtype == F64 else {"rtol": 1e-5, "atol": 1e-3}


def test_intrinsics_matrix(dtype, device):
    K = intrinsics_matrix(500.0, 480.0, 320.5, 240.25, dtype=dtype, device=device)
    expected = torch.tensor(
        [[500.0, 0, 320.5], [0, 480.0, 240.25], [0, 0, 1]], dtype=dtype, device=device
    )
    assert K.dtype == dtype
    torch.testing.assert_close(K, expected, rtol=0.0, atol=0.0)


def test_pixel_grid_is_column_row(dtype, device):
    grid = pixel_grid(4, 6, dtype=dtype, device=device)
    assert grid.shape == (4, 6, 2) and grid.dtype == dtype
    for row, col in [(0, 0), (3, 5), (2, 1)]:
        assert grid[row, col].tolist() == [col, row]


def test_unproject_then_project_returns_pixel_grid(dtype, device):
    K = intrinsics_matrix(50.0, 45.0, 15.5, 11.0, dtype=dtype, device=device)
    depth = 1.0 + torch.rand(
        24, 32, dtype=dtype, device=device, generator=torch.Generator(device=device).manual_seed(0)
    )
    X = unproject_depth(depth, K)
    assert X.shape == (24, 32, 3)
    torch.testing.assert_close(X[..., 2], depth, rtol=0.0, atol=0.0)
    torch.testing.assert_close(
        project(X, K), pixel_grid(24, 32, dtype=dtype, device=device), **tol(dtype)
    )


def test_unproject_and_project_batched_intrinsics(dtype, device):
    K = torch.stack(
        [
            intrinsics_matrix(50.0, 45.0, 15.5, 11.0, dtype=dtype, device=device),
            intrinsics_matrix(20.0, 25.0, 10.0, 8.0, dtype=dtype, device=device),
        ]
    )
    K[1, 0, 1] = 0.5  # skew
    depth = torch.full((2, 16, 20), 2.0, dtype=dtype, device=device)
    X = unproject_depth(depth, K)
    assert X.shape == (2, 16, 20, 3)
    uv = project(X, K[:, None, None])
    grid = pixel_grid(16, 20, dtype=dtype, device=device)
    torch.testing.assert_close(uv, grid.expand(2, -1, -1, -1), **tol(dtype))
    torch.testing.assert_close(X[0], unproject_depth(depth[0], K[0]))


def test_project_known_point(dtype, device):
    K = intrinsics_matrix(100.0, 200.0, 30.0, 40.0, dtype=dtype, device=device)
    x = torch.tensor([0.5, -0.25, 2.0], dtype=dtype, device=device)
    torch.testing.assert_close(
        project(x, K), torch.tensor([55.0, 15.0], dtype=dtype, device=device)
    )


def test_rays_are_unit_pixel_bearings(dtype, device):
    K = intrinsics_matrix(40.0, 40.0, 9.5, 7.5, dtype=dtype, device=device)
    rays = rays_from_intrinsics(16, 20, K)
    assert rays.shape == (16, 20, 3)
    torch.testing.assert_close(rays.norm(dim=-1), torch.ones(16, 20, dtype=dtype, device=device))
    X = unproject_depth(torch.full((16, 20), 3.0, dtype=dtype, device=device), K)
    torch.testing.assert_close(rays, psi(X), **tol(dtype))
    # The principal point sits between the four centre pixels: their rays are symmetric.
    torch.testing.assert_close(rays[7, 9, :2], -rays[8, 10, :2], **tol(dtype))


def test_scale_intrinsics_maps_pixel_footprints(dtype, device):
    K = intrinsics_matrix(100.0, 90.0, 31.5, 23.5, dtype=dtype, device=device)
    x = torch.tensor([[0.1, 0.2, 1.0], [-0.3, 0.05, 2.0]], dtype=dtype, device=device)
    uv = project(x, K)
    half = scale_intrinsics(K, 0.5, 0.5)
    # Halving merges old pixels 2k and 2k + 1 into new pixel k, whose centre is old 2k + 0.5.
    torch.testing.assert_close(project(x, half), (uv - 0.5) / 2, **tol(dtype))
    double = scale_intrinsics(K, 2.0, 3.0)
    torch.testing.assert_close(project(x, double)[:, 0], 2.0 * (uv[:, 0] + 0.5) - 0.5, **tol(dtype))
    torch.testing.assert_close(project(x, double)[:, 1], 3.0 * (uv[:, 1] + 0.5) - 0.5, **tol(dtype))
    torch.testing.assert_close(scale_intrinsics(K, 1.0, 1.0), K)


def test_crop_intrinsics_shifts_pixels(dtype, device):
    K = intrinsics_matrix(100.0, 90.0, 31.5, 23.5, dtype=dtype, device=device)
    x = torch.tensor([[0.1, 0.2, 1.0], [-0.3, 0.05, 2.0]], dtype=dtype, device=device)
    cropped = crop_intrinsics(K, 8, 4)
    shift = torch.tensor([8.0, 4.0], dtype=dtype, device=device)
    torch.testing.assert_close(project(x, cropped), project(x, K) - shift, **tol(dtype))
    assert float(K[0, 2]) == 31.5  # the input is not modified


def test_estimate_focal_recovers_the_pinhole_and_ignores_outliers(dtype, device):
    K = intrinsics_matrix(180.0, 180.0, 47.5, 35.5, dtype=dtype, device=device)
    generator = torch.Generator().manual_seed(0)
    depth = (1.0 + 4.0 * torch.rand(72, 96, generator=generator)).to(dtype=dtype, device=device)
    X = unproject_depth(depth, K)
    torch.testing.assert_close(
        estimate_focal(X), torch.tensor(180.0, dtype=dtype, device=device), rtol=1e-4, atol=0.0
    )
    # a tenth of the points thrown sideways (flying pixels) and some behind the camera
    wild = torch.rand(72, 96, generator=generator).to(device) < 0.1
    X_wild = torch.where(
        wild[..., None], X * torch.tensor([3.0, -2.0, 1.0], dtype=dtype, device=device), X
    )
    X_wild[:4, :, 2] = -1.0
    assert abs(float(estimate_focal(X_wild)) - 180.0) < 0.05 * 180.0
    # least squares, the Weiszfeld start, is pulled far off by the same outliers
    assert abs(float(estimate_focal(X_wild, iterations=0)) - 180.0) > 0.2 * 180.0


def test_estimate_focal_without_points_in_front_is_nan(dtype, device):
    X = torch.zeros(8, 8, 3, dtype=dtype, device=device)
    X[..., 2] = -1.0
    assert bool(torch.isnan(estimate_focal(X)))
