"""The compiled CPU loops of dense matching give the vectorised PyTorch path's results."""

from __future__ import annotations

import math

import pytest
import torch

from como3r.frontend import cpu_kernels, cpu_window_search, matching
from como3r.geometry.camera import intrinsics_matrix, unproject_depth
from como3r.geometry.lie import sim3_act, sim3_exp


@pytest.fixture(params=[1, 2], ids=["serial", "parallel"])
def threads(request):
    """Run under one PyTorch thread (the serial loop) and two (the parallel one)."""
    before = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(before)


def _descriptor_problem(B: int, H: int, W: int, dim: int, flow: int, seed: int):
    """Unit descriptors ``(B, H, W, d)``, noisy queries of every pixel ``(B, H*W, d)`` and
    start pixels up to ``flow`` px off ``(B, H*W, 2)``."""
    gen = torch.Generator().manual_seed(seed)
    D = torch.nn.functional.normalize(torch.randn(B, H, W, dim, generator=gen), dim=-1)
    noise = 0.3 * torch.randn(B, H * W, dim, generator=gen)
    D_query = torch.nn.functional.normalize(D.reshape(B, -1, dim) + noise, dim=-1)
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pixel = torch.stack([u.reshape(-1), v.reshape(-1)], -1).expand(B, -1, -1)
    jitter = torch.randint(-flow, flow + 1, pixel.shape, generator=gen)
    pixel = (pixel + jitter).clamp(min=0).minimum(torch.tensor([W - 1, H - 1]))
    return D, D_query, pixel


@pytest.mark.parametrize("size", [(2, 24, 32), (1, 7, 9)], ids=["batch", "window-over-image"])
def test_descriptor_window_search_equals_the_vectorised_path(threads, size) -> None:
    """Same refined pixel for every match (same candidate order, same first-maximum rule),
    also where the dilated window reaches far past the image (7x9 px, reach 15 px)."""
    B, H, W = size
    D, D_query, pixel = _descriptor_problem(B, H, W, dim=24, flow=6, seed=threads)
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, 3, 5, None)
    vectorised = matching._refine_vectorised(D, D_query, pixel, 3, 5, None)
    assert compiled.dtype == torch.int64 and compiled.shape == (B, H * W, 2)
    assert torch.equal(compiled, vectorised)
    moved = (compiled != pixel).any(-1).float().mean()
    assert moved > 0.5  # the search did work: most starts were off


def test_descriptor_window_search_on_every_device(device) -> None:
    """The window search where the pointmaps live (a GPU: the vectorised path in its large
    chunks) picks the compiled CPU loop's pixels; a GPU's float32 sums may order their terms
    otherwise, so a near-tie of scores could differ (none expected in random descriptors)."""
    D, D_query, pixel = _descriptor_problem(2, 40, 56, dim=24, flow=6, seed=11)
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, 3, 5, None)
    on_device = matching.refine_with_descriptors(
        D.to(device), D_query.to(device), pixel.to(device), 3, 5
    )
    assert on_device.device.type == device.type
    assert (on_device.cpu() == compiled).all(-1).float().mean() >= 0.999
    assert (compiled != pixel).any(-1).float().mean() > 0.5


@pytest.mark.parametrize("chunk", [7, 512, 1 << 16])
def test_descriptor_window_search_does_not_depend_on_the_chunk(chunk) -> None:
    """The vectorised path refines its matches ``chunk`` at a time (small on a CPU, large on
    a GPU) with the same result, also where the last chunk is partial."""
    D, D_query, pixel = _descriptor_problem(2, 24, 32, dim=24, flow=6, seed=4)
    active = torch.rand(pixel.shape[:2], generator=torch.Generator().manual_seed(2)) < 0.7
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, 3, 4, active)
    vectorised = matching._refine_vectorised(D, D_query, pixel, 3, 4, active, chunk=chunk)
    assert torch.equal(compiled, vectorised)


@pytest.mark.parametrize(
    "dim, radius, dilation_max",
    [(12, 3, 5), (24, 4, 2), (5, 1, 3)],
    ids=["dim-12", "two-lane-groups", "dim-5-radius-1"],
)
def test_descriptor_window_search_of_any_width_and_radius(
    threads, dim, radius, dilation_max
) -> None:
    """Descriptors whose width is not a multiple of 8 (zero-padded), windows wider than the
    8 lanes of one group of candidates (radius 4: 9 columns) and the smallest window."""
    D, D_query, pixel = _descriptor_problem(2, 18, 26, dim=dim, flow=5, seed=dim + radius)
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, radius, dilation_max, None)
    vectorised = matching._refine_vectorised(D, D_query, pixel, radius, dilation_max, None)
    assert torch.equal(compiled, vectorised)
    assert (compiled != pixel).any(-1).float().mean() > 0.3


def test_descriptor_window_search_breaks_ties_by_window_order(threads) -> None:
    """Descriptors drawn from three vectors: most windows hold exactly equal best scores,
    and the first in row-major window order wins, as in the PyTorch path."""
    B, H, W = 1, 16, 21
    gen = torch.Generator().manual_seed(3)
    palette = torch.nn.functional.normalize(torch.randn(3, 24, generator=gen), dim=-1)
    D = palette[torch.randint(0, 3, (B, H, W), generator=gen)]
    D_query = palette[torch.randint(0, 3, (B, H * W), generator=gen)]
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pixel = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[None]
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, 3, 3, None)
    assert torch.equal(compiled, matching._refine_vectorised(D, D_query, pixel, 3, 3, None))


def test_descriptor_window_search_leaves_inactive_matches(threads) -> None:
    D, D_query, pixel = _descriptor_problem(2, 20, 30, dim=16, flow=4, seed=5)
    active = torch.rand(pixel.shape[:2], generator=torch.Generator().manual_seed(1)) < 0.5
    compiled = cpu_window_search.refine_windows(D, D_query, pixel, 2, 3, active)
    assert torch.equal(compiled[~active], pixel[~active])
    assert torch.equal(compiled, matching._refine_vectorised(D, D_query, pixel, 2, 3, active))


def test_descriptor_window_search_takes_half_precision_descriptors() -> None:
    """bf16 descriptors (a bf16 prior) are scored in float32, as the PyTorch path does."""
    D, D_query, pixel = _descriptor_problem(1, 16, 20, dim=24, flow=4, seed=2)
    D, D_query = D.to(torch.bfloat16), D_query.to(torch.bfloat16)
    assert torch.equal(
        cpu_window_search.refine_windows(D, D_query, pixel, 3, 2, None),
        matching._refine_vectorised(D, D_query, pixel, 3, 2, None),
    )


def _ray_problem(dtype: torch.dtype, turn_deg: float):
    """Rays with gradients of a curved surface seen by camera A ``(1, H, W, 9)``, the rays of
    camera B's points in A ``(1, P, 3)`` (B turned by ``turn_deg``) and start pixels."""
    H, W = 30, 40
    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    depth = 5.0 + 0.03 * u + 0.3 * torch.sin(u / 9) * torch.cos(v / 7)
    X_A = unproject_depth(depth, K)
    T_AB = sim3_exp(
        torch.tensor([0.1, -0.05, 0.1, 0.01, math.radians(turn_deg), 0.0, 0.0], dtype=torch.float64)
    )
    X_B_in_A = sim3_act(T_AB[None, None], unproject_depth(depth.flip(1), K))
    rays_grad = matching.ray_image_with_gradients(X_A[None].to(dtype))
    target = torch.nn.functional.normalize(X_B_in_A.reshape(1, -1, 3), dim=-1).to(dtype)
    p_init = torch.stack([u, v], -1).reshape(1, -1, 2).to(dtype)
    return rays_grad, target, p_init


@pytest.mark.parametrize("turn_deg", [2.0, 30.0], ids=["overlapping", "a-third-outside"])
def test_ray_projection_equals_the_vectorised_path(threads, turn_deg) -> None:
    """Same converged set, and the converged pixels within float rounding of the
    PyTorch path's (the loop accumulates in float64)."""
    rays_grad, target, p_init = _ray_problem(torch.float64, turn_deg)
    args = (rays_grad, target, p_init, 10, 1e-8, 1e-6)
    p, pixel, converged = cpu_kernels.project_rays(*args)
    p_ref, converged_ref = matching._project_vectorised(*args)
    assert p.dtype == p_init.dtype and p.shape == p_init.shape
    assert converged.float().mean() > 0.4
    assert torch.equal(converged, converged_ref)
    assert torch.allclose(p[converged], p_ref[converged], atol=1e-6)
    nearest = matching._nearest_ray_pixel(rays_grad[..., :3], p_ref, target)
    assert pixel.dtype == torch.int64 and torch.equal(pixel[converged], nearest[converged])


def test_ray_projection_of_float32_pointmaps_matches_to_a_hundredth_of_a_pixel() -> None:
    rays_grad, target, p_init = _ray_problem(torch.float32, 2.0)
    args = (rays_grad, target, p_init, 10, 1e-8, 1e-6)
    p, pixel, converged = cpu_kernels.project_rays(*args)
    p_ref, converged_ref = matching._project_vectorised(*args)
    both = converged & converged_ref
    assert both.float().mean() > 0.9 * converged_ref.float().mean()
    assert (p[both] - p_ref[both]).abs().max() < 1e-2
    nearest = matching._nearest_ray_pixel(rays_grad[..., :3], p_ref, target)
    assert (pixel[both] == nearest[both]).all(-1).float().mean() > 0.99


def test_ray_image_with_gradients_equals_pytorch_to_an_ulp(threads) -> None:
    """One compiled pass gives the rays and their central differences (one-sided at the
    border) of the PyTorch expression, to float32 rounding of the norm."""
    gen = torch.Generator().manual_seed(4)
    X = torch.randn(2, 13, 17, 3, generator=gen) + torch.tensor([0.0, 0.0, 4.0])
    X[0, 3, 5] = 0.0  # the camera centre: a zero ray, as psi's clamped norm gives
    rays = torch.nn.functional.normalize(X, dim=-1, eps=1e-12)
    reference = torch.cat(
        [rays, torch.gradient(rays, dim=2)[0], torch.gradient(rays, dim=1)[0]], dim=-1
    )
    image = cpu_kernels.ray_image_with_gradients(X)
    assert image.shape == (2, 13, 17, 9) and image.dtype == torch.float32
    torch.testing.assert_close(image, reference, rtol=0, atol=3e-7)
    assert torch.equal(image[0, 3, 5, :3], torch.zeros(3))


def test_match_validity_equals_pytorch(threads) -> None:
    """Converged, finite and not occluded: the end of match_pointmaps in one pass."""
    gen = torch.Generator().manual_seed(5)
    B, H, W = 2, 12, 16
    X_search = torch.randn(B, H, W, 3, generator=gen) + torch.tensor([0.0, 0.0, 3.0])
    queries = X_search.reshape(B, -1, 3) + 0.6 * torch.randn(B, H * W, 3, generator=gen)
    queries[0, :4] = float("nan")
    queries[1, 4] = float("inf")
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    own = torch.stack([u.reshape(-1), v.reshape(-1)], -1).expand(B, -1, -1)
    elsewhere = torch.stack(
        [
            torch.randint(0, W, (B, H * W), generator=gen),
            torch.randint(0, H, (B, H * W), generator=gen),
        ],
        -1,
    )
    pixel = torch.where(torch.rand(B, H * W, 1, generator=gen) < 0.5, own, elsewhere)
    converged = torch.rand(B, H * W, generator=gen) < 0.8
    idx, valid = cpu_kernels.match_validity(X_search, queries, pixel, converged, 0.3)
    assert torch.equal(idx, pixel[..., 1] * W + pixel[..., 0])
    matched = torch.gather(X_search.reshape(B, -1, 3), 1, idx[..., None].expand(-1, -1, 3))
    reference = (
        converged
        & ((matched - queries).norm(dim=-1) < 0.3 * queries.norm(dim=-1))
        & torch.isfinite(queries).all(-1)
    )
    assert torch.equal(valid, reference)
    assert 0.2 < valid.float().mean() < 0.8
