"""Tests of como3r/prior/mast3r/rope.py against the formula of MAST3R_SPEC.md §3.3."""

from __future__ import annotations

import math

import pytest
import torch

from como3r.prior.mast3r.rope import RoPE2D, grid_positions


def reference_rope(t: torch.Tensor, positions: torch.Tensor, base: float) -> torch.Tensor:
    """Spec §3.3 written out element by element (independent of the implementation).

    ``t`` is ``(N, D)``; dims ``[0, D/2)`` rotate with the row, ``[D/2, D)`` with the column;
    inside a half the pair ``(k, k + D/4)`` rotates by ``p * base**(-k / (D/4))``.
    """
    n_tokens, dim = t.shape
    quarter = dim // 4
    out = t.clone()
    for n in range(n_tokens):
        for half, coordinate in ((0, positions[n, 0]), (1, positions[n, 1])):
            offset = half * dim // 2
            for k in range(quarter):
                theta = float(coordinate) * base ** (-k / quarter)
                u, v = t[n, offset + k].item(), t[n, offset + quarter + k].item()
                out[n, offset + k] = u * math.cos(theta) - v * math.sin(theta)
                out[n, offset + quarter + k] = v * math.cos(theta) + u * math.sin(theta)
    return out


def test_grid_positions_are_row_major_row_then_column():
    positions = grid_positions((3, 5))
    assert positions.dtype == torch.int64 and positions.shape == (15, 2)
    for n in range(15):
        assert positions[n].tolist() == [n // 5, n % 5]


@pytest.mark.parametrize(("grid", "head_dim", "base"), [((3, 5), 16, 100.0), ((4, 2), 8, 10.0)])
def test_rope_matches_the_formula_in_float64(grid, head_dim, base):
    generator = torch.Generator().manual_seed(0)
    t = torch.randn(2, 3, grid[0] * grid[1], head_dim, generator=generator, dtype=torch.float64)
    rotated = RoPE2D(base).apply(t, grid)
    assert rotated.dtype == torch.float64
    positions = grid_positions(grid)
    for b in range(2):
        for h in range(3):
            expected = reference_rope(t[b, h], positions, base)
            torch.testing.assert_close(rotated[b, h], expected, rtol=0, atol=1e-6)


def test_rope_of_large_grid_keeps_float32_precision():
    # positions up to 31 with base 100: angles up to 31 rad; tables computed in float64
    grid, dim = (21, 32), 64
    t = torch.randn(1, 1, grid[0] * grid[1], dim, dtype=torch.float64)
    exact = RoPE2D(100.0).apply(t, grid)
    single = RoPE2D(100.0).apply(t.float(), grid)
    torch.testing.assert_close(single.double(), exact, rtol=0, atol=1e-5)


def test_rope_is_a_rotation_that_encodes_relative_position():
    rope = RoPE2D(100.0)
    grid = (4, 6)
    q = torch.randn(1, 1, 1, 16, dtype=torch.float64).expand(1, 1, 24, 16)
    k = torch.randn(1, 1, 1, 16, dtype=torch.float64).expand(1, 1, 24, 16)
    rq, rk = rope.apply(q, grid), rope.apply(k, grid)
    torch.testing.assert_close(rq.norm(dim=-1), q.norm(dim=-1))
    scores = rq[0, 0] @ rk[0, 0].T
    # same displacement (1 row, 2 columns) from two different tokens: same score
    first = scores[0 * 6 + 0, 1 * 6 + 2]
    second = scores[2 * 6 + 3, 3 * 6 + 5]
    torch.testing.assert_close(first, second)


def test_bfloat16_is_rotated_in_float32_and_tables_are_cached():
    rope = RoPE2D(100.0)
    t = torch.randn(1, 2, 12, 16)
    rotated = rope.apply(t.bfloat16(), (3, 4))
    assert rotated.dtype == torch.bfloat16
    torch.testing.assert_close(
        rotated.float(), rope.apply(t.bfloat16().float(), (3, 4)), rtol=1e-2, atol=1e-2
    )
    table = rope.table((3, 4), 16, torch.device("cpu"), torch.float32)
    assert rope.table((3, 4), 16, torch.device("cpu"), torch.float32)[0] is table[0]
