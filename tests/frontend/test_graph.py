"""Keyframe-graph factors (frontend/graph.py): noise relative to the scene."""

from __future__ import annotations

import pytest
import torch

from como3r.config import TrackingConfig
from como3r.frontend.graph import make_factors
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_identity, sim3_inverse


def _problem(scale: float, dtype: torch.dtype):
    """Two cameras seeing points 4-8 units away, everything multiplied by ``scale``."""
    g = torch.Generator().manual_seed(3)
    X_i = torch.randn(1, 200, 3, generator=g, dtype=dtype)
    X_i[..., 2] = 4.0 + 4.0 * torch.rand(1, 200, generator=g, dtype=dtype)
    tau = torch.tensor([0.3, -0.1, 0.2, 0.02, -0.03, 0.01, 0.0], dtype=dtype)
    T_ij = sim3_exp(tau)
    # X_j such that T_ij X_j is X_i up to a 2 % range error: the residual is not zero
    noisy = X_i * (1.0 + 0.02 * torch.randn(1, 200, 1, generator=g, dtype=dtype))
    X_j = sim3_act(sim3_inverse(T_ij), noisy)
    poses = torch.stack([sim3_identity(dtype=dtype), T_ij])
    scaled_poses = poses.clone()
    scaled_poses[:, :3] *= scale
    return scale * X_i, scale * X_j, scaled_poses


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ray_range_whitening_is_the_same_at_every_scene_scale(dtype: torch.dtype) -> None:
    whitened = []
    for scale in (0.1, 1.0, 20.0):
        X_i, X_j, poses = _problem(scale, dtype)
        q = torch.ones(1, 200, dtype=dtype)
        valid = torch.ones(1, 200, dtype=torch.bool)
        factors = make_factors(torch.tensor([0]), torch.tensor([1]), X_i, X_j, q, valid,
                               TrackingConfig())
        whitened.append(factors.whitened_residual(poses)[0])
    tol = 1e-4 if dtype == torch.float32 else 1e-9
    assert float(whitened[0][..., 3].abs().max()) > 1e-4  # the range term is not empty
    for other in whitened[1:]:
        assert torch.allclose(other, whitened[0], atol=tol, rtol=1e-3)
