"""Reciprocal descriptor matching of the decentralized registration
(decentralized/matching.py, F-Sec. III-B)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from como3r.config_decentralized import DecentralizedConfig, RegistrationConfig, check_config
from como3r.decentralized.matching import query_grid, reciprocal_matches
from como3r.errors import ConfigError


def _views(seed: int, H: int, W: int, d: int = 24, noise: float = 0.3):
    """Two views whose descriptors are a shuffled, noisy copy of each other, with confidence
    maps that exclude a few pixels of each."""
    gen = torch.Generator().manual_seed(seed)
    D_i = torch.nn.functional.normalize(torch.randn(H, W, d, generator=gen), dim=-1)
    shuffled = D_i.reshape(-1, d)[torch.randperm(H * W, generator=gen)]
    D_j = torch.nn.functional.normalize(
        shuffled + noise * torch.randn(H * W, d, generator=gen), dim=-1
    ).reshape(H, W, d)
    Q_i = 1.0 + 4.0 * torch.rand(H, W, generator=gen)
    Q_j = 1.0 + 4.0 * torch.rand(H, W, generator=gen)
    return D_i, D_j, Q_i, Q_j


def _brute_force(D_i, D_j, Q_i, Q_j, config: RegistrationConfig):
    """The matching of the module docstring with the full score matrix (float64 argmax)."""
    H, W, d = D_i.shape
    pixels_i = torch.nonzero(Q_i.reshape(-1) > config.min_descriptor_confidence)[:, 0]
    pixels_j = torch.nonzero(Q_j.reshape(-1) > config.min_descriptor_confidence)[:, 0]
    scores = D_i.reshape(-1, d)[pixels_i].double() @ D_j.reshape(-1, d)[pixels_j].double().T
    i_to_j, j_to_i = scores.argmax(dim=1), scores.argmax(dim=0)
    row_of = {int(p): r for r, p in enumerate(pixels_i)}
    query = torch.tensor(
        [row_of[int(p)] for p in query_grid(H, W, config.match_stride_ratio) if int(p) in row_of]
    )
    pairs = set()
    for _ in range(config.match_iterations):
        if query.numel() == 0:
            break
        in_j = i_to_j[query]
        back = j_to_i[in_j]
        converged = back == query
        pairs |= {(int(a), int(b)) for a, b in zip(query[converged], in_j[converged])}
        query = torch.unique(back[~converged])
    return sorted((int(pixels_i[a]), int(pixels_j[b])) for a, b in pairs)


def _shifted_views(seed: int, H: int, W: int, shift: tuple[int, int], d: int = 24):
    """Two views of one smooth descriptor field (random at an eighth of the resolution,
    bilinearly upsampled), view j seeing it moved by ``shift`` = (dy, dx) pixels: pixel
    (y, x) of view i is pixel (y - dy, x - dx) of view j. Confidences exclude a few pixels."""
    gen = torch.Generator().manual_seed(seed)
    dy, dx = shift
    coarse = torch.randn(1, d, (H + dy) // 8 + 2, (W + dx) // 8 + 2, generator=gen)
    field = torch.nn.functional.interpolate(
        coarse, size=(H + dy, W + dx), mode="bilinear", align_corners=False
    )[0].permute(1, 2, 0)
    field = torch.nn.functional.normalize(field, dim=-1)
    D_i, D_j = field[:H, :W].contiguous(), field[dy:, dx:].contiguous()
    Q_i = 1.0 + 4.0 * torch.rand(H, W, generator=gen)
    Q_j = 1.0 + 4.0 * torch.rand(H, W, generator=gen)
    return D_i, D_j, Q_i, Q_j


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("iterations", [1, 3])
def test_one_pixel_grid_matches_equal_exact_brute_force(seed, iterations):
    """With a grid of one pixel the coarse level is every pixel: the search is exact."""
    D_i, D_j, Q_i, Q_j = _views(seed, 30, 40)
    config = RegistrationConfig(match_stride_ratio=1 / 40, match_iterations=iterations)
    p_i, p_j = reciprocal_matches(D_i, D_j, Q_i, Q_j, config)
    expected = _brute_force(D_i, D_j, Q_i, Q_j, config)
    assert len(expected) > 20
    assert list(zip(p_i.tolist(), p_j.tolist())) == expected


@pytest.mark.parametrize("seed", [0, 1])
def test_coarse_to_fine_finds_the_true_pixels_off_the_grid(seed):
    """A smooth field seen moved by (3, 5) px, off the 4 px grid: the coarse level only
    holds grid pixels, the full-resolution refinement lands on the true ones."""
    H, W, shift = 48, 64, (3, 5)
    D_i, D_j, Q_i, Q_j = _shifted_views(seed, H, W, shift)
    config = RegistrationConfig(match_stride_ratio=4 / 64)
    p_i, p_j = reciprocal_matches(D_i, D_j, Q_i, Q_j, config)
    q = config.min_descriptor_confidence
    assert bool((Q_i.reshape(-1)[p_i] > q).all()) and bool((Q_j.reshape(-1)[p_j] > q).all())
    y, x = p_i // W - shift[0], p_i % W - shift[1]
    true = (p_j // W == y) & (p_j % W == x)
    assert float(true.float().mean()) > 0.9
    # queries on view i's grid whose true pixel is in view j and confident
    grid = query_grid(H, W, config.match_stride_ratio)
    gy, gx = grid // W - shift[0], grid % W - shift[1]
    seen = (gy >= 0) & (gx >= 0) & (Q_i.reshape(-1)[grid] > q)
    seen[seen.clone()] &= Q_j.reshape(-1)[gy[seen] * W + gx[seen]] > q
    assert int(true.sum()) >= 0.8 * int(seen.sum())
    on_grid_j = torch.isin(p_j[true], grid)
    assert float(on_grid_j.float().mean()) < 0.5


def test_no_confident_pixel_gives_no_match():
    D_i, D_j, _, Q_j = _views(4, 8, 8)
    p_i, p_j = reciprocal_matches(D_i, D_j, torch.ones(8, 8), Q_j, RegistrationConfig())
    assert p_i.numel() == 0 and p_j.numel() == 0 and p_i.dtype == torch.long


def test_query_grid_at_512_is_the_official_subsampling_by_8():
    rows, cols = np.mgrid[4:384:8, 4:512:8].reshape(2, -1)
    grid = query_grid(384, 512, RegistrationConfig().match_stride_ratio)
    assert grid.tolist() == (rows * 512 + cols).tolist()


@pytest.mark.parametrize(("height", "width"), [(120, 160), (72, 96), (300, 400)])
def test_query_grid_is_the_same_at_every_resolution(height, width):
    """The default grid has 64 x 48 queries whatever the image size, at the places of the
    512x384 grid scaled to the image, to within one of its pixels."""
    ratio = RegistrationConfig().match_stride_ratio
    grid, at_512 = query_grid(height, width, ratio), query_grid(384, 512, ratio)
    assert grid.numel() == at_512.numel() == 64 * 48
    spacing = width / 64
    for got, reference in ((grid // width, at_512 // 512), (grid % width, at_512 % 512)):
        assert float((got / spacing - reference / 8).abs().max()) < 1 / spacing
    assert query_grid(width, height, ratio).numel() == 64 * 48  # portrait


def test_query_grid_is_at_least_one_pixel_and_one_query():
    assert query_grid(24, 32, 1 / 64).tolist() == list(range(24 * 32))  # 0.5 px -> every pixel
    assert query_grid(10, 512, 1.0).tolist() == [9 * 512 + 256]  # one query, inside the view


@pytest.mark.parametrize("value", [0.0, -0.1, 1.5, float("nan")])
def test_bad_match_stride_ratio_is_one_clear_error(value):
    config = DecentralizedConfig(registration=RegistrationConfig(match_stride_ratio=value))
    with pytest.raises(
        ConfigError,
        match=r"^decentralized\.registration\.match_stride_ratio "
        r"must be in \(0, 1\], got",
    ):
        check_config(config)


def test_bad_match_coarse_candidates_is_one_clear_error():
    config = DecentralizedConfig(registration=RegistrationConfig(match_coarse_candidates=0))
    with pytest.raises(
        ConfigError,
        match=r"^decentralized\.registration\.match_coarse_candidates "
        r"must be >= 1, got 0$",
    ):
        check_config(config)


def test_bad_match_iterations_is_one_clear_error():
    config = DecentralizedConfig(registration=RegistrationConfig(match_iterations=0))
    with pytest.raises(
        ConfigError,
        match=r"^decentralized\.registration\.match_iterations must "
        r"be >= 1, got 0$",
    ):
        check_config(config)
