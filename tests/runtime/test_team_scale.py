"""A team of eight agents, centralized (issue 41; the measured scaling is
benchmarks/team_scale.py). The single-process runner hands every keyframe to the
coordinator as it is made, in the multi-process runtime's order, so the coordinator's work
is the same as there; agent processes would only add their start-up (a few seconds of CPU
each) to the suite. The runtime's backlog is tested with its free-running run in
test_processes.py."""

from __future__ import annotations

import json

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.io.tum import read_tum
from como3r.runtime.pipeline import PriorSpec, run

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

AGENTS, FRAMES = 8, 8
# small global solves, one cleanup pass and no depth refinement keep it short; they do not
# change what is tested
OVERRIDES = [
    "input.long_side=64",
    "global_ba.max_iters_stream=5",
    "global_ba.max_iters_cleanup=10",
    "global_ba.cleanup_passes=1",
    "depth.alternation_rounds=0",
]


@pytest.mark.slow
def test_eight_agents_keep_the_decode_budget_and_merge_with_their_neighbours(
    tiny_scene, tmp_path
) -> None:
    """Every agent's trajectory is written; the coordinator's decodes stay within the
    per-keyframe budget and each keyframe is handled as it comes (a batch of one: nothing
    waits at the end); on the ring only neighbours meet, and every agent that met one
    shares its map."""
    scene = tiny_scene(FRAMES, 0, 0.6, agents=AGENTS)
    config = apply_overrides(Config(), OVERRIDES)
    out = tmp_path / "out"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run([scene / f"agent_{a}" for a in range(AGENTS)], out, config, PriorSpec("simulated"))
    finally:
        torch.set_num_threads(threads)
    metrics = json.loads((out / "metrics.json").read_text())
    for agent in range(AGENTS):
        trajectory = read_tum(out / "trajectories" / f"agent_{agent}.txt")
        assert len(trajectory.timestamps) == metrics["agents"][agent]["tracked"] > 0
    coordinator = metrics["coordinator"]
    budget = config.verification.max_decodes_per_keyframe
    assert coordinator["keyframes"] >= AGENTS
    assert 0 < coordinator["prior_decodes"] <= budget * coordinator["keyframes"]
    assert coordinator["batches"] == coordinator["keyframes"]
    assert coordinator["largest_batch"] == 1
    merged = [c for c in metrics["components"] if len(c) > 1]
    assert sum(len(c) for c in merged) >= AGENTS // 2, metrics["components"]
    for component in merged:  # each member met a neighbour on the ring
        for a in component:
            assert any((a - b) % AGENTS in (1, AGENTS - 1) for b in component), component
        rows = [r for r in metrics["ate"]["merged_components"] if r["agents"] == component]
        assert rows and rows[0]["ate"]["rmse"] < 0.05  # one consistent map [m]
