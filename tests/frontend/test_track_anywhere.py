"""One agent on the realistic simulated prior with the default configuration, at two scene
scales and two image sizes (the small in-suite subset of benchmarks/robustness.py).

The only setting chosen here is ``input.long_side``, equal to the rendered width so the
suite stays within minutes on two CPU cores; every threshold is the default. Measured at
commit time (tracked / processed frames, ATE % of path): 0.1x 96 px 20/20, 3.1 %; 1x 96 px
20/20, 3.3 %; 0.1x 160 px 20/20, 3.5 %; 1x 160 px 20/20, 3.6 %. The bounds are about twice
that; the issue's goal (<= 1 %) is not reached yet.
"""

from __future__ import annotations

import pytest

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3
from como3r.prior.simulated import SimulatedPrior

FRAMES = 40


@pytest.mark.parametrize("scale", [0.1, 1.0])
@pytest.mark.parametrize("width", [96, 160])
def test_default_configuration_tracks_on_the_realistic_prior(tmp_path, process_frames,
                                                             scale: float, width: int) -> None:
    synthesize(tmp_path, agents=1, seed=0, overlap=0.2, frames=FRAMES, preset="default",
               width=width, height=width * 3 // 4, progress=None, scale=scale)
    agent = open_agent(tmp_path / "agent_0")
    config = apply_overrides(Config(), [f"input.long_side={width}"])
    assert config.simulated_prior.model == "realistic"
    prior = SimulatedPrior(config.simulated_prior)
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(frontend, agent, width,
                              range(0, agent.num_frames, config.input.subsample))
    tracked = sum(o != "lost" for o in outcomes)
    assert tracked >= 0.95 * len(outcomes), outcomes
    assert len(frontend.keyframes) < len(outcomes)
    indices, _, T_WC = frontend.trajectory()
    gt = agent.groundtruth.T_WC[indices, :3]
    est = T_WC[:, :3].double()
    path = float((gt[1:] - gt[:-1]).norm(dim=-1).sum())
    ate = umeyama_rmse(umeyama_sim3(est, gt), est, gt)
    assert ate <= 0.07 * path, (ate / path, outcomes)
