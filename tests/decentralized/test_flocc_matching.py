"""Reciprocal descriptor matching of the decentralized registration
(decentralized/matching.py, F-Sec. III-B)."""

from __future__ import annotations

import pytest
import torch

from como3r.decentralized.config import RegistrationConfig
from como3r.decentralized.matching import query_grid, reciprocal_matches


def _views(seed: int, H: int, W: int, d: int = 24, noise: float = 0.3):
    """Two views whose descriptors are a shuffled, noisy copy of each other, with confidence
    maps that exclude a few pixels of each."""
    gen = torch.Generator().manual_seed(seed)
    D_i = torch.nn.functional.normalize(torch.randn(H, W, d, generator=gen), dim=-1)
    shuffled = D_i.reshape(-1, d)[torch.randperm(H * W, generator=gen)]
    D_j = torch.nn.functional.normalize(
        shuffled + noise * torch.randn(H * W, d, generator=gen), dim=-1).reshape(H, W, d)
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
    query = torch.tensor([row_of[int(p)] for p in query_grid(H, W, config.match_stride)
                          if int(p) in row_of])
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


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("iterations", [1, 3])
def test_matches_equal_brute_force(seed, iterations):
    D_i, D_j, Q_i, Q_j = _views(seed, 30, 40)
    config = RegistrationConfig(match_stride=3, match_iterations=iterations)
    p_i, p_j = reciprocal_matches(D_i, D_j, Q_i, Q_j, config)
    expected = _brute_force(D_i, D_j, Q_i, Q_j, config)
    assert len(expected) > 20
    assert list(zip(p_i.tolist(), p_j.tolist())) == expected


def test_matches_are_mutual_nearest_neighbours_of_confident_pixels():
    D_i, D_j, Q_i, Q_j = _views(3, 24, 32, noise=0.5)
    config = RegistrationConfig(match_stride=2)
    p_i, p_j = reciprocal_matches(D_i, D_j, Q_i, Q_j, config)
    assert p_i.numel() > 0
    q = config.min_descriptor_confidence
    assert bool((Q_i.reshape(-1)[p_i] > q).all()) and bool((Q_j.reshape(-1)[p_j] > q).all())
    flat_i, flat_j = D_i.reshape(-1, 24), D_j.reshape(-1, 24)
    masked_j = torch.where((Q_j.reshape(-1) > q)[None], flat_i[p_i] @ flat_j.T, -2.0)
    masked_i = torch.where((Q_i.reshape(-1) > q)[None], flat_j[p_j] @ flat_i.T, -2.0)
    assert torch.equal(masked_j.argmax(dim=1), p_j)
    assert torch.equal(masked_i.argmax(dim=1), p_i)


def test_no_confident_pixel_gives_no_match():
    D_i, D_j, Q_i, Q_j = _views(4, 8, 8)
    p_i, p_j = reciprocal_matches(D_i, D_j, torch.ones(8, 8), Q_j, RegistrationConfig())
    assert p_i.numel() == 0 and p_j.numel() == 0 and p_i.dtype == torch.long
