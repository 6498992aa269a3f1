"""Link tests decided one direction at a time (what lets loop verification stop early)."""

from __future__ import annotations

import itertools

import pytest
import torch

from como3r.frontend.pairs import (
    DirectedMatches,
    PairLink,
    _quantiles,
    direction_passes,
    matched_points,
)


def _matches(fraction: float, n: int = 100) -> DirectedMatches:
    valid = torch.arange(n) < round(fraction * n)
    return DirectedMatches(idx=torch.arange(n), valid=valid, q=torch.full((n,), 2.0))


def test_a_link_passes_exactly_when_both_directions_pass() -> None:
    fractions = (0.0, 0.05, 0.1, 0.3, 0.8)
    covisible = (0.0, 0.1, 0.4, 1.0)
    for nu_ij, nu_ji, c_ij, c_ji in itertools.product(fractions, fractions, covisible, covisible):
        link = PairLink(_matches(nu_ij), _matches(nu_ji), c_ij, c_ji)
        whole = link.min_match_fraction >= 0.1 and link.covisible_ratio >= 0.7
        split = direction_passes(link.ij, c_ij, 0.1, 0.7) and direction_passes(
            link.ji, c_ji, 0.1, 0.7
        )
        assert whole == split, (nu_ij, nu_ji, c_ij, c_ji)


def test_without_covisibility_only_the_match_fraction_counts() -> None:
    assert direction_passes(_matches(0.2), None, 0.1, 0.7)
    assert not direction_passes(_matches(0.05), None, 0.1, 0.7)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 2, 7, 1001])
def test_field_of_view_quantiles_equal_torch_quantile(dtype, n):
    """The selection-based bounds of covisible_fraction are torch.quantile's, interpolation
    included (a sorted copy per call cost 79 ms at 512x384)."""
    x = torch.randn(n, 2, generator=torch.Generator().manual_seed(n), dtype=dtype)
    qs = (0.01, 0.99)
    expected = torch.quantile(x, torch.tensor(qs, dtype=dtype), dim=0)
    got = _quantiles(x, qs)
    assert got.dtype == dtype and got.shape == (2, 2)
    torch.testing.assert_close(got, expected, rtol=0, atol=4 * torch.finfo(dtype).eps)


@pytest.mark.parametrize("most", [0, 5, 64, 1000])
def test_an_edges_matched_points_are_evenly_subsampled_to_the_cap(most) -> None:
    """``gauge.max_correspondences``, a focal pair's ``max_matches``: at most ``most`` of the valid matches, spread evenly
    over them, each point with its own match and confidence; 0 keeps all."""
    H, W = 12, 10
    X_source = torch.arange(H * W * 3, dtype=torch.float32).reshape(H, W, 3)
    X_target = -X_source
    valid = torch.arange(H * W) % 3 != 0  # 80 valid pixels
    idx = torch.arange(H * W).flip(0)
    q = torch.linspace(1.0, 2.0, H * W)
    target, source, conf = matched_points(DirectedMatches(idx, valid, q), X_target, X_source, most)
    pixels = torch.nonzero(valid).flatten()
    expected = pixels if most == 0 or most >= pixels.numel() else None
    assert source.shape[0] == (pixels.numel() if expected is not None else most)
    chosen = (source[:, 0] / 3).long()  # each source point's own pixel
    assert valid[chosen].all() and torch.equal(conf, q[chosen])
    assert torch.equal(target, X_target.reshape(-1, 3)[idx[chosen]])
    if expected is not None:
        assert torch.equal(chosen, expected)
    else:  # first and last valid pixel kept, the rest spread over the valid ones
        assert chosen[0] == pixels[0] and chosen[-1] == pixels[-1]
        positions = torch.searchsorted(pixels, chosen).double()
        assert float(positions.diff().max() - positions.diff().min()) <= 1.0
