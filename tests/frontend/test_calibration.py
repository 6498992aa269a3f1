"""Self-calibration of an uncalibrated agent (como3r.frontend.calibration)."""

from __future__ import annotations

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.errors import GeometryError
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.calibration import estimate_intrinsics
from como3r.geometry.camera import intrinsics_matrix, unproject_depth
from como3r.prior.simulated import SimulatedPrior


def test_estimate_intrinsics_takes_the_focal_and_the_image_centre():
    K = intrinsics_matrix(150.0, 150.0, 31.5, 23.5)
    X = unproject_depth(torch.full((48, 64), 2.0), K)
    estimate = estimate_intrinsics(X, torch.ones(48, 64))
    assert abs(float(estimate[0, 0]) - 150.0) < 1.0
    assert float(estimate[0, 0]) == float(estimate[1, 1])
    assert (float(estimate[0, 2]), float(estimate[1, 2])) == (31.5, 23.5)
    with pytest.raises(GeometryError, match="no point in front"):
        estimate_intrinsics(-X, torch.ones(48, 64))


@pytest.mark.parametrize("self_calibration", [True, False])
def test_an_uncalibrated_agent_locks_every_keyframe_to_one_estimated_camera(
        tmp_path, process_frames, self_calibration: bool) -> None:
    synthesize(tmp_path, agents=1, seed=0, overlap=0.2, frames=12, preset="default",
               width=96, height=72, progress=None)
    agent = open_agent(tmp_path / "agent_0")
    config = apply_overrides(Config(), ["input.long_side=96",
                                        f"tracking.self_calibration={self_calibration}"])
    prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side))
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    process_frames(frontend, agent, 96, range(0, 12, 2))
    assert len(frontend.keyframes) >= 2
    intrinsics = [kf.K for kf in frontend.keyframes]
    if not self_calibration:
        assert all(K is None for K in intrinsics) and frontend.stats.estimated_focal is None
        return
    for K in intrinsics:
        torch.testing.assert_close(K, intrinsics[0])
    true_focal = float(agent.calib[0])  # the rendered width is the network width
    assert abs(frontend.stats.estimated_focal / true_focal - 1.0) < 0.25
    for kf in frontend.keyframes:  # the canonical pointmap is on the camera's rays
        u = kf.K[0, 0] * kf.X_hat[..., 0] / kf.X_hat[..., 2] + kf.K[0, 2]
        columns = torch.arange(96, dtype=u.dtype).expand_as(u)
        assert float((u - columns).abs().max()) < 1e-3
