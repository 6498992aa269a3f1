"""Is ``--gt`` in agent order? The agents' estimates should fit their own ground truths best.

``como3r eval`` pairs the i-th ``--gt`` with ``trajectories/agent_<i>.txt``. Given in another
order, every number is still computed, only against the wrong trajectories, and nothing else
says so. Per agent the error hardly shows: a Sim(3) alignment of a short or smooth trajectory
fits another agent's about as well (two agents of 6 frames each on a synthetic scene: ATE
0.94 and 0.93 cm swapped, 0.77 and 0.98 cm in order). The merged ATE shows it, since one
alignment must place all agents: 4.1 cm swapped, 0.94 cm in order. So the merged ATE is
computed again with the ground truths assigned in every other order (every permutation up to
:data:`MAX_PERMUTED` agents, every swap of two beyond), where their timestamps associate, and
the evaluation warns when one assignment fits much better than the one given. A run whose
agents never met (several gauge components in ``graph.json``) has no merged ATE to compare.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator, Sequence
from pathlib import Path

from como3r.errors import InputError
from como3r.evaluation.trajectory import (
    MAX_TIME_DIFF,
    AssociatedPair,
    associate,
    merged_errors,
)
from como3r.io.tum import Trajectory

#: an assignment fits "much better" when its merged ATE is below this fraction of the given's
MUCH_BETTER = 0.5
#: up to this many agents every assignment is tried (119 others); beyond, every swap of two
MAX_PERMUTED = 5


def in_one_frame(est: Path) -> bool:
    """Whether the run folder ``est`` holds its agents in one world frame: its ``graph.json``
    lists one gauge component (True without a readable one: the files are taken as given)."""
    try:
        components = json.loads((est / "graph.json").read_text())["components"]
    except (OSError, ValueError, KeyError, TypeError):
        return True
    return not isinstance(components, list) or len(components) <= 1


def _assignments(n: int) -> Iterator[tuple[int, ...]]:
    """Every order of ``n`` ground truths but the given one (``order[i]``: agent i's)."""
    identity = tuple(range(n))
    if n <= MAX_PERMUTED:
        yield from (p for p in itertools.permutations(identity) if p != identity)
        return
    for i, j in itertools.combinations(identity, 2):
        order = list(identity)
        order[i], order[j] = j, i
        yield tuple(order)


def _merged_ate(pairs: Sequence[AssociatedPair]) -> float | None:
    try:
        return merged_errors(pairs, range(len(pairs))).ate.rmse
    except InputError:  # a degenerate alignment: this assignment does not compare
        return None


def ground_truth_order_warning(
    ests: Sequence[Trajectory], gts: Sequence[Trajectory], max_diff: float = MAX_TIME_DIFF
) -> str | None:
    """One warning line when the ground truths in another order fit the agents' estimates much
    better (:data:`MUCH_BETTER`) under one Sim(3) alignment than in the order given; else None.

    Args:
        ests: the agents' estimates, in agent order, all in one world frame.
        gts: the ground truths as given, the i-th meant for agent i.
    """
    n = len(ests)
    if n < 2 or len(gts) != n:
        return None
    pairs: dict[tuple[int, int], AssociatedPair | None] = {}
    for i, j in itertools.product(range(n), repeat=2):
        try:
            pairs[i, j] = associate(ests[i], gts[j], f"agent {i}", f"--gt #{j + 1}", max_diff)
        except InputError:  # too few timestamps in common: never this agent's ground truth
            pairs[i, j] = None
    given = _merged_ate([pairs[i, i] for i in range(n)])
    if not given:
        return None
    best: tuple[float, tuple[int, ...]] | None = None
    for order in _assignments(n):
        chosen = [pairs[i, j] for i, j in enumerate(order)]
        if any(p is None for p in chosen):
            continue
        ate = _merged_ate(chosen)  # type: ignore[arg-type]
        if ate is not None and (best is None or ate < best[0]):
            best = (ate, order)
    if best is None or best[0] >= MUCH_BETTER * given:
        return None
    ate, order = best
    taken = ", ".join(f"#{j + 1}" for j in order)
    return (
        f"warning: the ground truths fit the agents much better in another order: taking "
        f"--gt {taken} for agents {', '.join(str(i) for i in range(n))}, the merged ATE is "
        f"{ate:.4f} m instead of {given:.4f} m. Is --gt in agent order (the first for "
        f"trajectories/agent_0.txt, the second for agent_1, ...)?"
    )
