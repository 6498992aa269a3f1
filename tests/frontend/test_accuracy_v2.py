"""One agent's front-end on the hardest simulated prior (``v2``, issue 37) with the default
configuration: its tracked fraction and ATE, the single-agent cell of
benchmarks/robustness.py in small.

The scene and configuration are tests/conftest.py's ``v2_case``: the ``room`` family at
160x120, ``input.long_side`` 160, every threshold the default; the agent runs FRAMES
frames (every other one processed) of a path laid out for 100. The easy-prior front-end
tests (test_agent.py) check what needs exact pointmaps; the accuracy bound is here.

Measured at commit time (scene seed 0, ATE % of the path of ``scene.json``, Sim(3)
alignment of every tracked frame; all 20 tracked, 7-8 keyframes), prior seed 0 / 1 / 2:
0.27 / 0.22 / 0.56 %. The bound is about twice seed 0's (above seed 2's). On 24 frames
(half the CPU) seed 2 drew 1.06 % against 0.19 and 0.29.
"""

from __future__ import annotations

import pytest

from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.frontend.agent import AgentFrontend
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3
from como3r.prior.simulated import SimulatedPrior

pytestmark = pytest.mark.slow

FRAMES = 40


@pytest.fixture(scope="module")
def tracked(v2_case, process_frames) -> tuple[list[str], float]:
    """The agent's outcome per processed frame and its ATE as a fraction of its path."""
    (folder,), path, config = v2_case(agents=1, frames=FRAMES, scene_seed=0, prior_seed=0)
    assert config.simulated_prior.model == "v2"
    agent = open_agent(folder)
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(
        frontend, agent, config.input.long_side, range(0, agent.num_frames, config.input.subsample)
    )
    indices, _, T_WC = frontend.trajectory()
    gt = agent.groundtruth.T_WC[indices, :3]
    est = T_WC[:, :3].double()
    return outcomes, umeyama_rmse(umeyama_sim3(est, gt), est, gt) / path


def test_one_agent_tracks_its_frames_on_the_v2_prior(tracked) -> None:
    outcomes, _ = tracked
    assert len(outcomes) == FRAMES // 2
    assert sum(o != "lost" for o in outcomes) >= 0.95 * len(outcomes), outcomes


def test_one_agent_ate_on_the_v2_prior(tracked) -> None:
    _, ate = tracked
    assert ate <= 0.0060, ate
