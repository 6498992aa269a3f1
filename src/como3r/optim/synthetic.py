"""Synthetic relative-pose problems with exact ground truth (tests and benchmarks).

A problem is a set of true keyframe poses ``T_WC``, edges (i, j), and per edge P world
points seen by both cameras, expressed as the canonical points ``X_i`` (camera i) and
``X_j`` (camera j) that a :class:`~como3r.optim.match_factors.RayRangeFactors` batch consumes.
Noise-free correspondences make the true poses an exact zero-cost minimum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_identity, sim3_inverse


@dataclass(frozen=True, eq=False)
class SyntheticGraph:
    """Ground truth and correspondences of a synthetic pose graph.

    Attributes:
        poses: ``(N, 8)`` true poses ``T_WC``.
        i, j: ``(E,)`` int64 edge endpoints.
        X_i, X_j: ``(E, P, 3)`` matched points in camera i and camera j.
        q: ``(E, P)`` per-match confidences.
        valid: ``(E, P)`` bool, all true.
    """

    poses: torch.Tensor
    i: torch.Tensor
    j: torch.Tensor
    X_i: torch.Tensor
    X_j: torch.Tensor
    q: torch.Tensor
    valid: torch.Tensor


def random_sim3(
    n: int,
    rotation_deg: float,
    translation: float,
    log_scale: float,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """``(n, 8)`` random similarities ``Exp(v, omega, zeta)`` with uniformly random directions,
    ``|omega|`` = ``rotation_deg`` degrees, ``|v|`` = ``translation``, ``|zeta|`` =
    ``log_scale`` (random signs)."""

    def directions() -> torch.Tensor:
        d = torch.randn(n, 3, generator=generator, dtype=torch.float64)
        return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)

    sign = torch.randint(0, 2, (n, 1), generator=generator).to(torch.float64) * 2 - 1
    tau = torch.cat(
        [translation * directions(), math.radians(rotation_deg) * directions(), sign * log_scale],
        dim=-1,
    )
    return sim3_exp(tau).to(dtype)


def chain_loop_edges(
    num_poses: int, loop_every: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sequential edges (k, k+1), skip edges (k, k+2) and one loop edge every
    ``loop_every`` keyframes to a random keyframe at least 10 back: 2 + 1/loop_every edges
    per keyframe, as in a keyframe graph with loop closures."""
    k = torch.arange(num_poses - 1)
    i = [k, torch.arange(num_poses - 2)]
    j = [k + 1, torch.arange(2, num_poses)]
    sources = torch.arange(10, num_poses, loop_every)
    if len(sources):
        back = torch.randint(10, 10_000, (len(sources),), generator=generator)
        i.append(sources - 10 - back % (sources - 9))
        j.append(sources)
    return torch.cat(i), torch.cat(j)


def synthetic_graph(
    poses: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    points_per_edge: int,
    generator: torch.Generator,
    depth_range: tuple[float, float] = (5.0, 20.0),
    half_fov_deg: float = 35.0,
) -> SyntheticGraph:
    """Correspondences of every edge: P points in front of camera i (depth in
    ``depth_range`` along its optical axis, within a cone of ``half_fov_deg``), seen by
    camera j through the true relative pose.

    Args:
        poses: ``(N, 8)`` true poses ``T_WC``.
        i, j: ``(E,)`` edges.
        points_per_edge: P.
        generator: seeded random generator.
    """
    dtype = poses.dtype
    num_edges = len(i)
    shape = (num_edges, points_per_edge)
    depth = depth_range[0] + (depth_range[1] - depth_range[0]) * torch.rand(
        shape, generator=generator, dtype=torch.float64
    )
    extent = math.tan(math.radians(half_fov_deg))
    xy = extent * (2 * torch.rand(*shape, 2, generator=generator, dtype=torch.float64) - 1)
    X_i = torch.cat([xy, torch.ones(*shape, 1, dtype=torch.float64)], -1) * depth[..., None]
    T_ij = sim3_compose(sim3_inverse(poses[i]), poses[j]).to(torch.float64)
    X_j = sim3_act(sim3_inverse(T_ij)[:, None, :], X_i)
    q = 1.5 + torch.rand(shape, generator=generator, dtype=torch.float64)
    return SyntheticGraph(
        poses=poses,
        i=i.to(torch.int64),
        j=j.to(torch.int64),
        X_i=X_i.to(dtype),
        X_j=X_j.to(dtype),
        q=q.to(dtype),
        valid=torch.ones(shape, dtype=torch.bool),
    )


def chain_poses(
    num_poses: int, generator: torch.Generator, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """``(N, 8)`` keyframe poses along a smooth loop (radius ~ N/2 m) with small random
    rotations and per-keyframe scales within +-10 %; pose 0 is the identity."""
    angle = torch.linspace(0, 2 * math.pi, num_poses + 1, dtype=torch.float64)[:-1]
    radius = max(2.0, num_poses / (2 * math.pi))
    centre = torch.stack(
        [radius * angle.sin(), 0.1 * torch.sin(5 * angle), radius * (1 - angle.cos())], dim=-1
    )
    yaw = torch.zeros(num_poses, 3, dtype=torch.float64)
    yaw[:, 1] = -angle
    jitter = 0.05 * torch.randn(num_poses, 3, generator=generator, dtype=torch.float64)
    log_scale = 0.1 * (2 * torch.rand(num_poses, 1, generator=generator, dtype=torch.float64) - 1)
    log_scale[0] = 0.0
    tau = torch.cat([torch.zeros_like(centre), yaw + jitter, log_scale], dim=-1)
    tau[0] = 0.0
    poses = sim3_exp(tau)
    poses[:, :3] = centre - centre[0]
    poses[0] = sim3_identity(dtype=torch.float64)
    return poses.to(dtype)
