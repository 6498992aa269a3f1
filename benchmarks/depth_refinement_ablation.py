"""Depth parameterisations of the terminal depth refinement (C-Tab. 5) on a synthetic scene.

A small room (floor, two walls, a box) is ray-cast from N keyframes on a forward-sideways
path. Each keyframe's prior pointmap is the true one with the simulated prior's kind of error
(:mod:`como3r.prior.simulated_errors`): a smooth multiplicative depth distortion of amplitude
``--amplitude`` (default 3 %) with a spatial wavelength of about a third of the image, and
per-pixel range noise of ``--noise`` (0.5 %). Poses are exact (the depth step runs at frozen
poses); keyframe 0 is pinned. Edges (k, k+1) and (k, k+2) in both directions carry
projective matches: each pixel of j is projected with its true point into i and rounded to
the nearest pixel, kept if i sees the same surface there.

For each variant (per-pixel, per-pixel + Laplacian, per-segment SLIC) it runs ``--rounds``
depth steps (segments from the current pointmaps, 10 Newton iterations, write-back) and
prints the depth error of the free keyframes (mean of ``|log(d / d_true)|`` after the first
and the last step, 90th percentile after the last), the RMS 3D distance between matched
points, the number of unknowns and the time per depth step. It does so twice: with the pinned
keyframe distorted like the others (the refinement can then only make the keyframes agree
with each other and with the anchor's distortion), and with an exact anchor (how much of the
distortion each parameterisation can recover from a correct reference).

Finally it runs the whole alternation of C-Sec. A.7 (:func:`como3r.backend.alternation.
alternate` with the global Gauss-Newton pose solve of ``como3r.optim``) from perturbed poses
for each variant and for poses alone, with short passes to keep the run to a few minutes,
and prints the mean keyframe position error (keyframe 0 is pinned at its true pose, so no
alignment is needed), the depth error and the time in each phase (C-Tab. 5 reports ATE).

    python benchmarks/depth_refinement_ablation.py [--keyframes 6] [--rounds 5] [--threads 1]
        [--joint-rounds 5] [--cleanup-iters 20] [--pose-pass-iters 10] [--skip-joint]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import platform
import time
from dataclasses import dataclass

import torch

from como3r.backend.alternation import AlternationSettings, alternate
from como3r.backend.depth_refinement import refine_keyframes
from como3r.config import DepthRefinementConfig, GlobalBAConfig, TrackingConfig
from como3r.frontend.graph import Edge, build_factors
from como3r.frontend.pairs import DirectedMatches
from como3r.geometry.lie import quat_rotate, sim3_act, sim3_compose, sim3_exp, sim3_inverse
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.values import PoseValues

H, W, FOCAL = 96, 128, 100.0
CONFIDENCE = 3.0
MATCH_Q = 2.0
VISIBILITY_TOL = 0.02  # relative range difference for "i sees the same surface"

# Axis-aligned planes of the room (camera 0 frame: x right, y down, z forward):
# (axis, value, bounds of the other two axes).
PLANES = [
    (1, 1.2, ((-4.0, 4.0), (0.0, 12.0))),  # floor y = 1.2
    (2, 9.0, ((-4.0, 4.0), (-3.0, 1.2))),  # back wall z = 9
    (0, -3.0, ((-3.0, 1.2), (0.0, 12.0))),  # left wall x = -3
]
BOX = ((-0.6, 0.9), (0.2, 1.2), (3.8, 4.8))


@dataclass
class SyntheticKeyframe:
    """The keyframe attributes the refinement uses."""

    X_hat: torch.Tensor
    X_init: torch.Tensor
    C: torch.Tensor
    K: torch.Tensor | None = None  # uncalibrated: ray-and-range factors in the pose solve

    def mean_confidence(self) -> torch.Tensor:
        return self.C


def camera_rays() -> torch.Tensor:
    """``(H, W, 3)`` unit rays of a pinhole camera."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    rays = torch.stack(
        [(u - W / 2 + 0.5) / FOCAL, (v - H / 2 + 0.5) / FOCAL, torch.ones_like(u)], -1
    )
    return rays / rays.norm(dim=-1, keepdim=True)


def ray_cast(origin: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Distance along each world ray ``directions (..., 3)`` to the first scene surface."""
    best = torch.full(directions.shape[:-1], math.inf, dtype=torch.float64)
    planes = list(PLANES)
    for axis in range(3):  # the six faces of the box
        bounds = [BOX[a] for a in range(3) if a != axis]
        planes += [(axis, BOX[axis][0], bounds), (axis, BOX[axis][1], bounds)]
    for axis, value, bounds in planes:
        others = [a for a in range(3) if a != axis]
        t = (value - origin[axis]) / directions[..., axis]
        hit = origin + t[..., None] * directions
        inside = (t > 1e-6) & torch.isfinite(t)
        for a, (low, high) in zip(others, bounds):
            inside &= (hit[..., a] >= low - 1e-9) & (hit[..., a] <= high + 1e-9)
        best = torch.where(inside & (t < best), t, best)
    return best


def keyframe_poses(n: int) -> torch.Tensor:
    """``(n, 8)`` poses moving forward and right with a slow yaw."""
    taus = torch.zeros(n, 7, dtype=torch.float64)
    taus[:, 0] = 0.15 * torch.arange(n)
    taus[:, 2] = 0.35 * torch.arange(n)
    taus[:, 4] = -0.04 * torch.arange(n)
    return sim3_exp(taus)


def smooth_field(generator: torch.Generator, terms: int = 4) -> torch.Tensor:
    """``(H, W)`` sum of random plane waves with wavelengths around a third of the image,
    normalised to a maximum magnitude of 1."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64) / W,
        torch.arange(W, dtype=torch.float64) / W,
        indexing="ij",
    )
    field = torch.zeros(H, W, dtype=torch.float64)
    for _ in range(terms):
        angle, phase = 2 * math.pi * torch.rand(2, generator=generator, dtype=torch.float64)
        wavelength = 0.25 + 0.2 * torch.rand(1, generator=generator, dtype=torch.float64)
        k = 2 * math.pi / wavelength
        field += torch.cos(k * (u * torch.cos(angle) + v * torch.sin(angle)) + phase)
    return field / field.abs().max()


def projective_matches(X_i: torch.Tensor, X_j: torch.Tensor, T_ij: torch.Tensor) -> DirectedMatches:
    """Pixel of i for every pixel of j from the true pointmaps, with a visibility test."""
    x = sim3_act(T_ij[None, None], X_j)
    u = torch.round(FOCAL * x[..., 0] / x[..., 2] + W / 2 - 0.5)
    v = torch.round(FOCAL * x[..., 1] / x[..., 2] + H / 2 - 0.5)
    inside = (x[..., 2] > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v = torch.nan_to_num(u).clamp(0, W - 1), torch.nan_to_num(v).clamp(0, H - 1)
    idx = (v * W + u).long().reshape(-1)
    seen = X_i.reshape(-1, 3)[idx].norm(dim=-1)
    visible = (seen - x.reshape(-1, 3).norm(dim=-1)).abs() < VISIBILITY_TOL * seen
    valid = inside.reshape(-1) & visible & torch.isfinite(seen)
    return DirectedMatches(idx=idx, valid=valid, q=torch.full((H * W,), MATCH_Q))


def build_problem(num_keyframes: int, amplitude: float, noise: float, seed: int):
    """Keyframes with distorted pointmaps, exact poses, edges and the true pointmaps."""
    generator = torch.Generator().manual_seed(seed)
    poses = keyframe_poses(num_keyframes)
    rays = camera_rays()
    truth, keyframes = [], []
    for pose in poses:
        directions = quat_rotate(pose[3:7].expand(H, W, 4), rays)
        distance = ray_cast(pose[:3], directions)
        # Rays that leave the room (the sky) have no point: NaN, as a prior's invalid pixel.
        truth.append(torch.where(torch.isfinite(distance), distance, math.nan)[..., None] * rays)
    for X in truth:
        log_error = amplitude * smooth_field(generator)
        log_error = log_error + noise * torch.randn(H, W, generator=generator, dtype=torch.float64)
        X_prior = (X * log_error.exp()[..., None]).float()
        keyframes.append(
            SyntheticKeyframe(X_prior.clone(), X_prior, torch.full((H, W), CONFIDENCE))
        )
    edges = []
    for i in range(num_keyframes):
        for j in (i + 1, i + 2):
            if j >= num_keyframes:
                continue
            for a, b in ((i, j), (j, i)):
                T_ab = sim3_compose(sim3_inverse(poses[a]), poses[b])
                edges.append(Edge(a, b, projective_matches(truth[a], truth[b], T_ab)))
    return keyframes, poses.float(), edges, [X.float() for X in truth]


def depth_error(keyframes, truth) -> tuple[float, float]:
    """Mean and 90th percentile of ``|log(d / d_true)|`` over the free keyframes."""
    errors = torch.cat(
        [
            (kf.X_hat.norm(dim=-1) / X.norm(dim=-1)).log().abs().reshape(-1)
            for kf, X in zip(keyframes[1:], truth[1:])
        ]
    )
    errors = errors[torch.isfinite(errors)]
    return float(errors.mean()), float(errors.quantile(0.9))


def match_rms(keyframes, poses, edges) -> float:
    """RMS 3D distance between matched points, in the frame of keyframe i."""
    squared, count = 0.0, 0
    for e in edges:
        T_ij = sim3_compose(sim3_inverse(poses[e.i]), poses[e.j])
        x_j = sim3_act(T_ij[None], keyframes[e.j].X_hat.reshape(-1, 3))
        x_i = keyframes[e.i].X_hat.reshape(-1, 3)[e.matches.idx]
        d = (x_j - x_i)[e.matches.valid]
        squared += float((d**2).sum())
        count += d.shape[0]
    return math.sqrt(squared / max(count, 1))


VARIANTS = (
    ("pixel", "per-pixel"),
    ("pixel_laplacian", "per-pixel + Laplacian"),
    ("segment", "per-segment (SLIC)"),
)


def run_scenario(args: argparse.Namespace, exact_anchor: bool) -> None:
    """Print one table: the prior's error, then each variant after 1 and after R steps."""

    def problem():
        keyframes, poses, edges, truth = build_problem(
            args.keyframes, args.amplitude, args.noise, args.seed
        )
        if exact_anchor:
            keyframes[0].X_hat, keyframes[0].X_init = truth[0].clone(), truth[0].clone()
        return keyframes, poses, edges, truth

    anchor = "exact" if exact_anchor else "distorted like the others"
    print(f"\nkeyframe 0 (pinned): {anchor}")
    header = (
        f"{'variant':<22}{'unknowns':>9}{'err@1':>8}{f'err@{args.rounds}':>8}"
        f"{'p90':>8}{'match rms':>11}{'s/step':>8}"
    )
    print(header)
    print("-" * len(header))
    keyframes, poses, edges, truth = problem()
    mean, p90 = depth_error(keyframes, truth)
    print(
        f"{'prior (before)':<22}{'-':>9}{mean:>8.4f}{mean:>8.4f}{p90:>8.4f}"
        f"{match_rms(keyframes, poses, edges):>11.4f}{'-':>8}"
    )
    for variant, name in VARIANTS:
        config = dataclasses.replace(DepthRefinementConfig(), variant=variant)
        keyframes, poses, edges, truth = problem()
        key_to_index = {k: k for k in range(len(keyframes))}
        seconds, after_one = 0.0, math.nan
        for step in range(args.rounds):
            start = time.perf_counter()
            report = refine_keyframes(keyframes, poses, edges, key_to_index, config, pinned=[0])
            seconds += time.perf_counter() - start
            if step == 0:
                after_one = depth_error(keyframes, truth)[0]
        mean, p90 = depth_error(keyframes, truth)
        print(
            f"{name:<22}{report.num_parameters:>9d}{after_one:>8.4f}{mean:>8.4f}{p90:>8.4f}"
            f"{match_rms(keyframes, poses, edges):>11.4f}{seconds / args.rounds:>8.3f}"
        )


def run_joint(args: argparse.Namespace) -> None:
    """The alternation of C-Sec. A.7 from perturbed poses: pose error and depth error."""
    print(
        f"\njoint alternation (C-Sec. A.7) from perturbed poses (3 cm, 0.6 deg, 2 % scale); "
        f"cleanup passes of {args.cleanup_iters} iterations, {args.joint_rounds} rounds with "
        f"{args.pose_pass_iters}-iteration pose passes"
    )
    header = (
        f"{'variant':<22}{'pos err':>9}{'depth err':>11}{'rounds':>8}{'pose s':>8}{'depth s':>9}"
    )
    print(header)
    print("-" * len(header))
    tracking = TrackingConfig()
    for variant, name in ((None, "poses only"), *VARIANTS):
        keyframes, true_poses, edges, truth = build_problem(
            args.keyframes, args.amplitude, args.noise, args.seed
        )
        generator = torch.Generator().manual_seed(args.seed + 1)
        tau = torch.cat(
            [
                0.03 * torch.randn(len(keyframes), 3, generator=generator),
                0.01 * torch.randn(len(keyframes), 3, generator=generator),
                0.02 * torch.randn(len(keyframes), 1, generator=generator),
            ],
            dim=1,
        )
        tau[0] = 0.0
        state = {"poses": sim3_compose(sim3_exp(tau), true_poses)}
        key_to_index = {k: k for k in range(len(keyframes))}

        def pose_pass(iters: int) -> float:
            factors = build_factors(edges, keyframes.__getitem__, int, tracking)
            values, _ = gauss_newton_irls(
                factors, PoseValues.from_poses(state["poses"], 1), GlobalBAConfig(), max_iters=iters
            )
            step = (values.poses[:, :3] - state["poses"][:, :3]).norm(dim=-1).max()
            state["poses"] = values.poses
            return float(step)

        config = dataclasses.replace(DepthRefinementConfig(), variant=variant or "segment")

        def depth_step() -> float:
            return refine_keyframes(
                keyframes, state["poses"], edges, key_to_index, config, pinned=[0]
            ).max_change

        settings = AlternationSettings(
            cleanup_iters=args.cleanup_iters,
            rounds=0 if variant is None else args.joint_rounds,
            pose_pass_iters=args.pose_pass_iters,
        )
        report = alternate(pose_pass, depth_step, settings)
        position_error = (state["poses"][:, :3] - true_poses[:, :3]).norm(dim=-1).mean()
        print(
            f"{name:<22}{float(position_error):>9.4f}{depth_error(keyframes, truth)[0]:>11.4f}"
            f"{len(report.rounds):>8d}{report.pose_seconds:>8.1f}{report.depth_seconds:>9.1f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--keyframes", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--amplitude", type=float, default=0.03)
    parser.add_argument("--noise", type=float, default=0.005)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--joint-rounds", type=int, default=5)
    parser.add_argument("--cleanup-iters", type=int, default=20)
    parser.add_argument("--pose-pass-iters", type=int, default=10)
    parser.add_argument("--skip-joint", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    print(
        f"machine: {platform.processor() or platform.machine()}, torch "
        f"{torch.__version__}, {args.threads} thread(s); {args.keyframes} keyframes "
        f"{W}x{H}, amplitude {args.amplitude:.1%}, noise {args.noise:.1%}, exact poses"
    )
    print(
        "err@k: mean |log(d / d_true)| over the free keyframes after k depth steps "
        "(10 Newton iterations each); p90 and match rms [m] after the last step"
    )
    for exact_anchor in (False, True):
        run_scenario(args, exact_anchor)
    if not args.skip_joint:
        run_joint(args)


if __name__ == "__main__":
    main()
