"""Keyframe linking reuses the tracking's decode and matches for the sequential edge."""

from __future__ import annotations

import pytest

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.prior.simulated import SimulatedPrior

pytestmark = pytest.mark.slow

WIDTH, HEIGHT, FRAMES = 96, 72, 16


class CountingPrior:
    """A prior that counts the ordered pairs it decodes."""

    def __init__(self, prior: SimulatedPrior) -> None:
        self.prior = prior
        self.decoded = 0
        self.paired = 0  # of them through decode_pairs (loop candidates, screened)

    def __getattr__(self, name):
        return getattr(self.prior, name)

    def decode(self, enc_i, enc_j):
        self.decoded += 1
        return self.prior.decode(enc_i, enc_j)

    def decode_pairs(self, pairs):
        self.decoded += len(pairs)
        self.paired += len(pairs)
        return self.prior.decode_pairs(pairs)

    def decode_symmetric(self, pairs):
        self.decoded += 2 * len(pairs)
        return self.prior.decode_symmetric(pairs)


@pytest.fixture(scope="module")
def run(tmp_path_factory, process_frames):
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=5,
        overlap=0.2,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
        progress=None,
    )
    agent = open_agent(root / "agent_0")
    config = apply_overrides(
        Config(), [f"input.long_side={WIDTH}", "input.subsample=1", "simulated_prior.model=easy"]
    )
    prior = CountingPrior(
        SimulatedPrior(config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side))
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(frontend, agent, WIDTH, range(agent.num_frames))
    return frontend, prior, outcomes


def test_the_sequential_edge_costs_one_decode_beyond_tracking(run) -> None:
    frontend, prior, outcomes = run
    assert outcomes.count("keyframe") >= 3 and "lost" not in outcomes
    stats = frontend.stats
    # the first frame decodes with itself, every later frame once for tracking, every new
    # keyframe once more for (kf - 1, kf)
    assert prior.decoded - prior.paired == 1 + (stats.frames - 1) + (stats.keyframes - 1)
    # every loop candidate once, and the reverse only of those whose first direction passes
    # (every loop edge, at least)
    assert stats.loop_candidates + stats.loop_edges <= prior.paired <= 2 * stats.loop_candidates


def test_every_keyframe_has_both_sequential_directions_over_all_pixels(run) -> None:
    frontend, _, _ = run
    sequential = {(e.i, e.j): e.matches for e in frontend.edges if e.kind == "sequential"}
    for kf in range(1, len(frontend.keyframes)):
        for i, j in ((kf - 1, kf), (kf, kf - 1)):
            matches = sequential[(i, j)]
            height, width = frontend.keyframes[j].shape
            assert matches.idx.numel() == height * width
            assert matches.match_fraction > 0.1
