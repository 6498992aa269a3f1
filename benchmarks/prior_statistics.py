"""How hard the simulated prior is, measured against the ground truth (a script, not a test).

Prints the statistics of the review of the realistic model ("A prior as hard as MASt3R",
item 1) for each ``--model`` on two synthetic scenes (``--presets``: a textured one and the
``low-texture`` family), two agents of ``--frames`` frames at ``--width x --height``:

* ``NN<=2px``: fraction of the global nearest-neighbour matches of ``D_ii`` in ``D_ji``
  (over every pixel of view j) that land within 2 px of the true correspondence, over the
  pixels of i that j truly sees, for the pairs ``(k, k + gap)`` of agent 0.
* ``R@1`` / ``rank``: retrieval. Each frame of agent 0 that sees a frame of agent 1 (true
  covisibility above 0.3) queries the retrieval features of agent 1's frames; the score of a
  database frame is the mean over the query's patches of their best cosine with its patches
  (what ASMK approximates, without a codebook). Recall at 1 and median rank of the most
  covisible frame.
* ``rho``: Spearman rank correlation between ``log(C_ii - 1)`` and ``|log range error|`` of
  ``X_ii`` (valid pixels, the pair's median log scale removed), and the same against the
  error's smooth part (box mean over an eighth of the long side) and its pixel part (the
  rest). A confidence that knows the injected error gives strongly negative values.
* ``ray px``: median pixel distance between the correspondence ``X_ji`` implies in image i
  (the pixel whose ``X_ii`` ray is nearest to the ray of ``X_ji``, MASt3R-SLAM's projective
  matching solved exactly) and the true one, with the model's intrinsics and ray errors and
  with them set to 0 (``no-ray``). Equal values mean the intrinsics errors never reach the
  correspondences. ``|pose0``: the same without the pair's pose error (no rotation and
  translation noise, no gross failures), which otherwise dominates: what is left is the
  rays' and the ranges' share.
* ``C ovl`` / ``C none``: median ``C_ji`` of pairs across the agents that overlap (true
  covisibility above 0.3) and of pairs that do not (below 0.01); ``AUC``: how well the
  pair's median ``C_ji`` separates the two (0.5: it does not know, 1: it knows the truth);
  ``covis``: within overlapping pairs, median ``C_ji`` of the pixels i truly sees over that
  of the others. Overlapping pairs are up to ``--pairs`` of those above 0.3, pairs without
  overlap up to ``--pairs`` below 0.01, each spread over all such pairs.
* ``depth %``: median ``|X_ii range / true range - 1|`` after the pair's median scale;
  ``focal %``: median ``|f / f_true - 1|`` of the focal ``X_ii`` implies (least squares of
  ``u = f x / z + c``); ``pose deg``: median rotation error of the similarity fitted between
  view j's true points and ``X_ji``.

``--ood S ...`` adds rows of the ``v2`` model at ``simulated_prior.ood_severity = S``
(blur, low light, sky, thin structures; :mod:`como3r.prior.simulated_ood`).

Usage::

    python benchmarks/prior_statistics.py [--model realistic easy] [--presets default
        low-texture] [--width 320] [--height 240] [--frames 16] [--ood 0.5 1] [--threads 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
import time
import typing
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from como3r.config import SimulatedPriorConfig
from como3r.data.agent import open_agent
from como3r.data.preprocess import frame_ground_truth, make_view
from como3r.data.synth import synthesize
from como3r.geometry.camera import project, unproject_depth
from como3r.geometry.lie import (
    matrix_to_quat,
    quat_to_matrix,
    sim3_act,
    sim3_compose,
    sim3_inverse,
    so3_log,
)
from como3r.geometry.umeyama import umeyama_sim3
from como3r.prior.base import View
from como3r.prior.ground_truth import GroundTruth, InMemoryTruth
from como3r.prior.simulated import SimulatedPrior
from como3r.prior.simulated_encoding import SimulatedEncoding

MODELS = typing.get_args(typing.get_type_hints(SimulatedPriorConfig)["model"])
OVERLAP, NO_OVERLAP = 0.3, 0.01
QUERY_PIXELS = 1500


@dataclass
class Scene:
    """Views and ground truth of a synthetic scene: ``views[agent][frame]``."""

    views: list[list[View]]
    truth: InMemoryTruth

    def gt(self, view: View) -> GroundTruth:
        return self.truth.truth(view.agent, view.index)


def load_scene(root: Path, preset: str, frames: int, width: int, height: int) -> Scene:
    """Synthesize two agents of ``preset`` into ``root`` and load them at full size."""
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.5,
        frames=frames,
        preset=preset,
        width=width,
        height=height,
    )
    truth, views = InMemoryTruth(), []
    for a in range(2):
        agent = open_agent(root / f"agent_{a}")
        row = []
        for i in range(len(agent)):
            frame = agent.load_frame(i)
            row.append(make_view(frame, a, max(width, height), calib=agent.calib))
            truth.add(a, i, frame_ground_truth(frame, max(width, height), agent.calib))
        views.append(row)
    return Scene(views, truth)


def relative_pose(gt_i: GroundTruth, gt_j: GroundTruth) -> torch.Tensor:
    """Sim(3) ``(8,)`` taking camera j's points into camera i."""
    return sim3_compose(sim3_inverse(gt_i.T_WC), gt_j.T_WC).float()


def correspondences(gt_i: GroundTruth, gt_j: GroundTruth) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each pixel of i truly lands in j: ``(H, W, 2)`` pixels and ``(H, W)`` bool
    visibility (in the image, in front, not occluded: z-buffer test on j's depth)."""
    points, valid = unproject_depth(gt_i.depth, gt_i.K), gt_i.depth > 0
    in_j = sim3_act(relative_pose(gt_j, gt_i), points)
    uv = project(in_j, gt_j.K)
    H, W = gt_j.depth.shape
    col, row = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H) & valid & (in_j[..., 2] > 0)
    seen = gt_j.depth[row.clamp(0, H - 1), col.clamp(0, W - 1)]
    return uv, inside & ((seen - in_j[..., 2]).abs() < 0.02 * in_j[..., 2])


def covisibility(gt_i: GroundTruth, gt_j: GroundTruth) -> float:
    """Fraction of i's valid pixels that j sees."""
    valid = gt_i.depth > 0
    return float(correspondences(gt_i, gt_j)[1].sum()) / max(int(valid.sum()), 1)


def sample(mask: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """Up to ``count`` flat indices of ``mask``'s True pixels, seeded."""
    where = mask.reshape(-1).nonzero()[:, 0]
    gen = torch.Generator().manual_seed(seed)
    return where[torch.randperm(where.numel(), generator=gen)[:count]]


def nn_within_2px(pred, gt_i: GroundTruth, gt_j: GroundTruth, seed: int) -> float | None:
    """Fraction of global nearest-descriptor matches of i's covisible pixels within 2 px."""
    uv, visible = correspondences(gt_i, gt_j)
    queries = sample(visible, QUERY_PIXELS, seed)
    if queries.numel() < 50:
        return None
    d = pred.D_ii.shape[-1]
    nearest = (pred.D_ii.reshape(-1, d)[queries] @ pred.D_ji.reshape(-1, d).T).argmax(-1)
    W = pred.D_ji.shape[1]
    found = torch.stack([nearest % W, nearest // W], dim=-1).float()
    return float(((found - uv.reshape(-1, 2)[queries]).norm(dim=-1) <= 2.0).float().mean())


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation (ties broken by order; continuous data)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def log_range_error(gt: GroundTruth, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(H, W)`` log range error of ``X`` with the median removed, and validity."""
    valid = gt.depth > 0
    ranges = unproject_depth(gt.depth, gt.K).norm(dim=-1)
    error = torch.zeros_like(ranges)
    error[valid] = torch.log(X.norm(dim=-1)[valid] / ranges[valid])
    error[valid] -= error[valid].median()
    return error, valid


def smooth_part(error: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Box mean of the valid error over an eighth of the long side (normalised convolution)."""
    size = max(3, (max(error.shape) // 8) | 1)
    kernel = torch.ones(1, 1, size, size)
    num = F.conv2d((error * valid)[None, None], kernel, padding=size // 2)[0, 0]
    den = F.conv2d(valid.float()[None, None], kernel, padding=size // 2)[0, 0]
    return num / den.clamp_min(1e-6)


def confidence_rhos(pred, gt: GroundTruth) -> tuple[float, float, float]:
    """Spearman of ``log(C_ii - 1)`` with |error|, |smooth error|, |pixel error|."""
    error, valid = log_range_error(gt, pred.X_ii)
    smooth = smooth_part(error, valid)
    logit = torch.log((pred.C_ii - 1).clamp_min(1e-12))[valid].numpy()
    return tuple(
        spearman(logit, part[valid].abs().numpy()) for part in (error, smooth, error - smooth)
    )


def ray_matching_px(pred, gt_i: GroundTruth, gt_j: GroundTruth, seed: int) -> float | None:
    """Median px between the pixel of i whose ``X_ii`` ray is nearest to ``X_ji``'s ray and
    the true projection, over pixels of j that i sees."""
    uv, visible = correspondences(gt_j, gt_i)
    queries = sample(visible, QUERY_PIXELS, seed)
    if queries.numel() < 50:
        return None
    rays_i = F.normalize(pred.X_ii.reshape(-1, 3), dim=-1)
    rays_ji = F.normalize(pred.X_ji.reshape(-1, 3)[queries], dim=-1)
    nearest = (rays_ji @ rays_i.T).argmax(-1)
    W = pred.X_ii.shape[1]
    found = torch.stack([nearest % W, nearest // W], dim=-1).float()
    return float((found - uv.reshape(-1, 2)[queries]).norm(dim=-1).median())


def depth_focal_pose(
    pred, view: View, gt_i: GroundTruth, gt_j: GroundTruth
) -> tuple[float, float, float]:
    """Median relative depth error, relative focal error, pose rotation error (deg)."""
    error, valid = log_range_error(gt_i, pred.X_ii)
    depth = float((torch.exp(error[valid]) - 1).abs().median())
    ratio = (pred.X_ii[..., 0] / pred.X_ii[..., 2])[valid]
    u = torch.arange(view.shape[1], dtype=torch.float32).expand(view.shape)[valid]
    A = torch.stack([ratio, torch.ones_like(ratio)], dim=-1).double()
    focal = float(torch.linalg.lstsq(A, u[:, None].double()).solution[0, 0])
    focal_error = abs(focal / float(gt_i.K[0, 0]) - 1)
    points, valid_j = unproject_depth(gt_j.depth, gt_j.K), gt_j.depth > 0
    fitted = umeyama_sim3(points[valid_j].double(), pred.X_ji[valid_j].double()).float()
    R = quat_to_matrix(fitted[3:7]) @ quat_to_matrix(relative_pose(gt_i, gt_j)[3:7]).T
    angle = math.degrees(float(so3_log(matrix_to_quat(R.double())).norm()))
    return depth, focal_error, angle


def retrieval_ranks(
    prior: SimulatedPrior, encodings: list[list[SimulatedEncoding]], covis: np.ndarray
) -> list[int]:
    """Rank (1 = first) of the most covisible agent-1 frame for each agent-0 query."""
    features = [[prior.retrieval_features(e)[0] for e in row] for row in encodings]
    ranks = []
    for q, query in enumerate(features[0]):
        if covis[q].max() < OVERLAP:
            continue
        scores = np.asarray([float((query @ base.T).max(-1).values.mean()) for base in features[1]])
        ranks.append(1 + int((scores > scores[int(covis[q].argmax())]).sum()))
    return ranks


def auc(positive: list[float], negative: list[float]) -> float:
    """Probability that a positive scores above a negative (ties count half)."""
    if not positive or not negative:
        return float("nan")
    p, n = np.asarray(positive)[:, None], np.asarray(negative)[None, :]
    return float(np.mean((p > n) + 0.5 * (p == n)))


def measure(
    scene: Scene, config: SimulatedPriorConfig, gap: int, max_pairs: int
) -> dict[str, float]:
    """Every statistic of one model on one scene (module docstring)."""
    prior = SimulatedPrior(config, scene.truth)
    no_ray_config = dataclasses.replace(
        config, focal_error=0.0, principal_point_error=0.0, ray_field_deg=0.0
    )
    exact_pose = dict(
        rotation_noise_deg=0.0, translation_noise=0.0, translation_floor=0.0, gross_failure_rate=0.0
    )
    variants = {  # the ray-matching error of these models besides the model itself
        "ray_none": SimulatedPrior(no_ray_config, scene.truth),
        "ray_pose0": SimulatedPrior(dataclasses.replace(config, **exact_pose), scene.truth),
        "ray_none_pose0": SimulatedPrior(
            dataclasses.replace(no_ray_config, **exact_pose), scene.truth
        ),
    }
    encodings = [[prior.encode(v) for v in row] for row in scene.views]
    frames = len(scene.views[0])
    out: dict[str, list[float]] = {
        key: []
        for key in (
            "nn",
            "rho",
            "rho_smooth",
            "rho_pixel",
            "ray",
            *variants,
            "depth",
            "focal",
            "pose",
        )
    }
    for k in range(0, frames - gap, max(1, (frames - gap) // max_pairs))[:max_pairs]:
        view_i, view_j = scene.views[0][k], scene.views[0][k + gap]
        gt_i, gt_j = scene.gt(view_i), scene.gt(view_j)
        pred = prior.decode(encodings[0][k], encodings[0][k + gap])
        for key, value in (
            ("nn", nn_within_2px(pred, gt_i, gt_j, k)),
            ("ray", ray_matching_px(pred, gt_i, gt_j, k)),
        ):
            if value is not None:
                out[key].append(value)
        for key, value in zip(("rho", "rho_smooth", "rho_pixel"), confidence_rhos(pred, gt_i)):
            out[key].append(value)
        for key, value in zip(
            ("depth", "focal", "pose"), depth_focal_pose(pred, view_i, gt_i, gt_j)
        ):
            out[key].append(value)
        for key, variant in variants.items():
            value = ray_matching_px(
                variant.decode(variant.encode(view_i), variant.encode(view_j)), gt_i, gt_j, k
            )
            if value is not None:
                out[key].append(value)
    covis = np.asarray(
        [[covisibility(scene.gt(a), scene.gt(b)) for b in scene.views[1]] for a in scene.views[0]]
    )
    ranks = retrieval_ranks(prior, encodings, covis)
    overlapping, apart = (
        pairs[:: max(1, len(pairs) // max_pairs)][:max_pairs]
        for pairs in (
            list(zip(*np.nonzero(covis > OVERLAP))),
            list(zip(*np.nonzero(covis < NO_OVERLAP))),
        )
    )
    medians: dict[bool, list[float]] = {True: [], False: []}
    covis_ratio = []
    for is_overlap, pairs in ((True, overlapping), (False, apart)):
        for a, b in pairs:
            pred = prior.decode(encodings[0][a], encodings[1][b])
            valid_j = scene.gt(scene.views[1][b]).depth > 0
            medians[is_overlap].append(float(pred.C_ji[valid_j].median()))
            if is_overlap:
                seen = correspondences(scene.gt(scene.views[1][b]), scene.gt(scene.views[0][a]))[1]
                unseen = valid_j & ~seen
                if int(seen.sum()) > 50 and int(unseen.sum()) > 50:
                    covis_ratio.append(float(pred.C_ji[seen].median() / pred.C_ji[unseen].median()))
    result = {
        key: float(np.mean(values)) if key.startswith("rho") else float(np.median(values))
        for key, values in out.items()
        if values
    }
    result.update(
        {
            "r1": float(np.mean(np.asarray(ranks) == 1)) if ranks else float("nan"),
            "rank": float(np.median(ranks)) if ranks else float("nan"),
            "queries": float(len(ranks)),
            "c_overlap": float(np.median(medians[True])) if medians[True] else float("nan"),
            "c_none": float(np.median(medians[False])) if medians[False] else float("nan"),
            "auc": auc(medians[True], medians[False]),
            "covis": float(np.median(covis_ratio)) if covis_ratio else float("nan"),
            "pairs": float(len(out["depth"])),
            "overlap_pairs": float(len(medians[True])),
            "apart_pairs": float(len(medians[False])),
        }
    )
    return result


COLUMNS = (  # (key, header, format)
    ("nn", "NN<=2px", "{:.1%}"),
    ("r1", "R@1", "{:.0%}"),
    ("rank", "rank", "{:.1f}"),
    ("rho", "rho", "{:+.2f}"),
    ("rho_smooth", "rho smooth", "{:+.2f}"),
    ("rho_pixel", "rho pixel", "{:+.2f}"),
    ("ray", "ray px", "{:.2f}"),
    ("ray_none", "no-ray px", "{:.2f}"),
    ("ray_pose0", "ray|pose0", "{:.2f}"),
    ("ray_none_pose0", "no-ray|pose0", "{:.2f}"),
    ("c_overlap", "C ovl", "{:.2f}"),
    ("c_none", "C none", "{:.2f}"),
    ("auc", "AUC", "{:.2f}"),
    ("covis", "covis", "{:.2f}"),
    ("depth", "depth %", "{:.1%}"),
    ("focal", "focal %", "{:.1%}"),
    ("pose", "pose deg", "{:.2f}"),
)


def print_table(rows: list[tuple[str, str, dict[str, float]]]) -> None:
    """One row per (preset, model), fixed-width columns."""
    headers = ["preset", "model"] + [h for _, h, _ in COLUMNS]
    cells = [
        [preset, model]
        + [
            fmt.format(stats[key]) if key in stats and not math.isnan(stats[key]) else "-"
            for key, _, fmt in COLUMNS
        ]
        for preset, model, stats in rows
    ]
    widths = [max(len(h), *(len(r[c]) for r in cells)) for c, h in enumerate(headers)]
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    for row in cells:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model",
        nargs="+",
        choices=MODELS,
        default=["realistic"],
        help="simulated_prior.model values to measure",
    )
    parser.add_argument("--presets", nargs="+", default=["default", "low-texture"])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--frames", type=int, default=16, help="frames per agent (2 agents)")
    parser.add_argument("--gap", type=int, default=2, help="frame gap of the agent-0 pairs")
    parser.add_argument("--pairs", type=int, default=6, help="pairs per kind")
    parser.add_argument(
        "--ood",
        nargs="*",
        type=float,
        default=[],
        help="also measure v2 at these simulated_prior.ood_severity values (rows 'v2 oodS')",
    )
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="prior_statistics_") as tmp:
        for preset in args.presets:
            root = Path(tmp) / preset
            root.mkdir()
            scene = load_scene(root, preset, args.frames, args.width, args.height)
            configs = [(model, SimulatedPriorConfig(model=model)) for model in args.model] + [
                (f"v2 ood{s:g}", SimulatedPriorConfig(model="v2", ood_severity=s)) for s in args.ood
            ]
            for model, config in configs:
                stats = measure(scene, config, args.gap, args.pairs)
                rows.append((preset, model, stats))
                print(
                    f"{preset} / {model}: {stats['pairs']:.0f} pairs (gap {args.gap}), "
                    f"{stats['queries']:.0f} retrieval queries, "
                    f"{stats['overlap_pairs']:.0f} overlapping and "
                    f"{stats['apart_pairs']:.0f} non-overlapping pairs",
                    flush=True,
                )
    print(
        f"\n{args.width}x{args.height}, 2 agents x {args.frames} frames, seed 0, "
        f"{time.perf_counter() - start:.0f} s"
    )
    print_table(rows)


if __name__ == "__main__":
    main()
