"""The least-squares sweep over log focal lengths that closes loops of agents (issue 41;
:func:`como3r.coordination.focal_alignment.solve_log_focals`)."""

from __future__ import annotations

import pytest

from como3r.coordination.focal_alignment import solve_log_focals


def test_a_loops_misclosure_is_spread_over_its_pairs() -> None:
    """Four agents in a ring, each pair saying +0.02 but the closing one 0: the 0.06
    misclosure goes a quarter to every pair, the anchor stays."""
    rows = [(0, 1, 0.02, 1), (1, 2, 0.02, 1), (2, 3, 0.02, 1), (0, 3, 0.0, 1)]
    solved = solve_log_focals(rows, {0})
    assert set(solved) == {1, 2, 3}
    assert [solved[a] for a in (1, 2, 3)] == pytest.approx([0.005, 0.010, 0.015])


def test_a_tree_of_pairs_is_met_exactly_and_weights_count() -> None:
    tree = solve_log_focals([(0, 1, 0.03, 1), (1, 2, -0.05, 2), (0, 4, 0.01, 1)], {0})
    assert tree == pytest.approx({1: 0.03, 2: -0.02, 4: 0.01})
    # two rows on one difference: the heavier one wins in proportion
    weighted = solve_log_focals([(0, 1, 0.0, 1), (0, 1, 0.04, 3)], {0})
    assert weighted[1] == pytest.approx(0.03)


def test_held_and_unconnected_agents_keep_their_focal_lengths() -> None:
    rows = [(0, 1, 0.02, 1), (2, 3, 0.05, 1), (1, 5, 0.01, 1)]
    solved = solve_log_focals(rows, {0, 5})
    assert set(solved) == {1}  # 2 and 3 meet only each other; 0 and 5 are held
    assert solved[1] == pytest.approx(0.005)  # between 0.02 (from 0) and -0.01 (from 5)
    assert solve_log_focals(rows, set()) == {}
