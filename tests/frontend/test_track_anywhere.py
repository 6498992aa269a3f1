"""One agent on the realistic simulated prior with the default configuration, at two scene
scales and two image sizes (the small in-suite subset of benchmarks/robustness.py).

The only setting chosen here is ``input.long_side``, equal to the rendered width so the
suite stays within minutes on two CPU cores; every threshold is the default. The scene
turns 20 deg per processed frame. Measured at commit time (tracked / processed frames, ATE %
of path): 0.1x 96 px 20/20, 1.39 %; 1x 96 px 19/20, 1.75 %; 0.1x 160 px 20/20, 1.36 %; 1x
160 px 19/20, 1.39 % (the paper's uncalibrated mode, ``tracking.self_calibration=false``:
8.1, 7.1, 8.6, 7.5 %). The prior's default seed happens to draw a first frame whose focal
length is nearly right; seeds 1 and 2 give 1.8-3.0 % here. The bounds are about twice the
default's; the issue's goal (<= 1 %) is met on slower motion (3.6 deg per frame: 0.4-1.35 %
over three prior seeds, frontend.calibration), not yet here.
"""

from __future__ import annotations

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3
from como3r.prior.simulated import SimulatedPrior

FRAMES = 40


def _track(root, process_frames, scale: float, width: int,
           overrides: tuple[str, ...] = ()) -> tuple[float, list[str], AgentFrontend]:
    """One agent's run on a fresh scene: (ATE as a fraction of the path, outcomes, front-end)."""
    synthesize(root, agents=1, seed=0, overlap=0.2, frames=FRAMES, preset="default",
               width=width, height=width * 3 // 4, progress=None, scale=scale)
    agent = open_agent(root / "agent_0")
    config = apply_overrides(Config(), [f"input.long_side={width}", *overrides])
    assert config.simulated_prior.model == "realistic"
    prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side))
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(frontend, agent, width,
                              range(0, agent.num_frames, config.input.subsample))
    indices, _, T_WC = frontend.trajectory()
    gt = agent.groundtruth.T_WC[indices, :3]
    est = T_WC[:, :3].double()
    path = float((gt[1:] - gt[:-1]).norm(dim=-1).sum())
    return umeyama_rmse(umeyama_sim3(est, gt), est, gt) / path, outcomes, frontend


@pytest.mark.parametrize("scale", [0.1, 1.0])
@pytest.mark.parametrize("width", [96, 160])
def test_default_configuration_tracks_on_the_realistic_prior(tmp_path, process_frames,
                                                             scale: float, width: int) -> None:
    ate, outcomes, frontend = _track(tmp_path, process_frames, scale, width)
    tracked = sum(o != "lost" for o in outcomes)
    assert tracked >= 0.95 * len(outcomes), outcomes
    assert len(frontend.keyframes) < len(outcomes)
    assert ate <= 0.035, (ate, outcomes)


def test_self_calibration_beats_the_papers_uncalibrated_mode(tmp_path, process_frames) -> None:
    paper, _, frontend = _track(tmp_path, process_frames, 1.0, 96,
                                ("tracking.self_calibration=false",))
    assert frontend.stats.estimated_focal is None
    # measured: 7.2 % (paper's mode) against 1.6-2.0 % (the default, previous test)
    assert paper > 0.035, paper


def test_a_frame_the_motion_outran_becomes_a_keyframe_late(tmp_path, process_frames) -> None:
    """With this draw of the prior's errors, frame 2 still overlaps keyframe 0 by 36 % (no
    keyframe due) and frame 4 by 4 %: without the late promotion of frame 2 the agent lost
    track at frame 4 and tracked 4 of 20 frames (measured)."""
    ate, outcomes, frontend = _track(tmp_path, process_frames, 1.0, 96,
                                     ("simulated_prior.seed=1",))
    assert frontend.stats.late_keyframes >= 1
    # a promoted frame is where its keyframe is (it was tracked before the camera settled:
    # its first solution, relative to the previous keyframe, must not come back)
    indices, _, T_WC = frontend.trajectory()
    row = {int(i): k for k, i in enumerate(indices)}
    for kf in frontend.keyframes:
        torch.testing.assert_close(T_WC[row[kf.frame_index]], kf.T_WC.to(T_WC))
    assert sum(o != "lost" for o in outcomes) >= 0.95 * len(outcomes), outcomes
    assert ate <= 0.02, ate  # measured 0.96 % (2.2 % while its first solution came back)
