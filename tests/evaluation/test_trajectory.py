"""ATE / RPE through evo: invariances, the merged ATE, and agreement with evo's own CLI."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.evaluation.trajectory import (
    agent_errors,
    associate,
    merged_errors,
    merged_errors_by_component,
)
from como3r.io.tum import Trajectory, read_tum, write_tum

FRAMES = 100


def smooth_path(rng: np.random.Generator, frames: int = FRAMES, t0: float = 100.0) -> Trajectory:
    """A smooth random 3-D camera path (sums of sinusoids) with smoothly varying orientation."""
    s = np.linspace(0.0, 1.0, frames)[:, None, None]
    freq, phase = rng.uniform(0.3, 1.5, (1, 3, 3)), rng.uniform(0, 2 * np.pi, (1, 3, 3))
    positions = (rng.uniform(1.0, 4.0, (1, 3, 3)) * np.sin(2 * np.pi * freq * s + phase)).sum(-1)
    rotvecs = (0.4 * np.sin(2 * np.pi * freq[..., ::-1] * s + phase)).sum(-1)
    quat = Rotation.from_rotvec(rotvecs).as_quat()
    T_WC = np.concatenate([positions, quat, np.ones((frames, 1))], axis=1)
    return Trajectory(t0 + 0.05 * np.arange(frames), torch.from_numpy(T_WC))


def random_sim3(rng: np.random.Generator) -> tuple[Rotation, np.ndarray, float]:
    return Rotation.random(random_state=rng), rng.uniform(-10, 10, 3), float(rng.uniform(0.5, 2.0))


def transformed(
    traj: Trajectory,
    rotation: Rotation,
    translation: np.ndarray,
    scale: float,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> Trajectory:
    """``traj`` mapped by x -> s R x + t (orientations rotated by R), optionally noisy."""
    poses = traj.T_WC.numpy()
    positions = scale * rotation.apply(poses[:, :3]) + translation
    if noise:
        positions = positions + rng.normal(0.0, noise, positions.shape)
    quat = (rotation * Rotation.from_quat(poses[:, 3:7])).as_quat()
    T_WC = np.concatenate([positions, quat, np.ones((len(traj), 1))], axis=1)
    return Trajectory(traj.timestamps.copy(), torch.from_numpy(T_WC))


def test_ground_truth_against_itself_is_zero(dtype: torch.dtype) -> None:
    rng = np.random.default_rng(0)
    # Identical timestamps for all agents: merging by time would pair agents wrongly.
    gts = [smooth_path(rng) for _ in range(3)]
    gts = [Trajectory(g.timestamps, g.T_WC.to(dtype)) for g in gts]
    pairs = [associate(g, g, f"est{a}", f"gt{a}") for a, g in enumerate(gts)]
    for pair in pairs:
        errors = agent_errors(pair)
        assert errors.frames == FRAMES
        assert errors.ate.rmse < 1e-9 and errors.ate.max < 1e-9
        assert errors.rpe_trans.rmse < 1e-9
        assert errors.rpe_rot_deg.rmse < 1e-4  # arccos near 1 is ill-conditioned
        assert errors.alignment.scale == pytest.approx(1.0, abs=1e-9)
    merged = merged_errors(pairs, range(3))
    assert merged.frames == 3 * FRAMES
    assert merged.ate.rmse < 1e-9


def test_per_agent_sim3_is_absorbed_but_merged_sees_gauge_errors() -> None:
    rng = np.random.default_rng(1)
    gts = [smooth_path(rng) for _ in range(3)]
    sims = [random_sim3(rng) for _ in gts]
    ests = [transformed(g, *sim) for g, sim in zip(gts, sims)]
    pairs = [associate(e, g, f"est{a}", f"gt{a}") for a, (e, g) in enumerate(zip(ests, gts))]
    for pair, (rotation, _, scale) in zip(pairs, sims):
        errors = agent_errors(pair)
        assert errors.ate.rmse < 1e-6
        assert errors.rpe_trans.rmse < 1e-6
        assert errors.alignment.scale == pytest.approx(1.0 / scale, rel=1e-9)
        recovered = Rotation.from_matrix(errors.alignment.rotation) * rotation
        assert recovered.magnitude() < 1e-9
    stacked = np.concatenate([g.positions for g in gts])
    extent = float(np.ptp(stacked, axis=0).max())
    assert merged_errors(pairs, range(3)).ate.rmse > 0.1 * extent


def test_rpe_rotation_of_a_single_perturbed_frame() -> None:
    rng = np.random.default_rng(2)
    gt = smooth_path(rng)
    theta_deg, k = 3.0, 40
    poses = gt.T_WC.clone().numpy()
    bump = Rotation.from_euler("z", theta_deg, degrees=True)
    perturbed = Rotation.from_quat(poses[k, 3:7]) * bump
    poses[k, 3:7] = perturbed.as_quat()
    est = Trajectory(gt.timestamps, torch.from_numpy(poses))
    errors = agent_errors(associate(est, gt, "est", "gt"))
    # Two consecutive pairs (k-1, k) and (k, k+1) each see the angle theta; all others zero.
    expected = theta_deg * math.sqrt(2 / (FRAMES - 1))
    assert errors.rpe_rot_deg.rmse == pytest.approx(expected, rel=1e-6)
    assert errors.rpe_rot_deg.max == pytest.approx(theta_deg, rel=1e-6)
    assert errors.ate.rmse < 1e-9


def write_noisy_pair(tmp_path: Path, seed: int) -> tuple[Path, Path]:
    """GT and a noisy, Sim(3)-transformed estimate with jittered stamps and dropped frames."""
    rng = np.random.default_rng(seed)
    gt = smooth_path(rng)
    est = transformed(gt, *random_sim3(rng), noise=0.05, rng=rng)
    keep = np.sort(rng.choice(FRAMES, FRAMES - 10, replace=False))
    stamps = est.timestamps[keep] + rng.uniform(-0.004, 0.004, len(keep))
    gt_path, est_path = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum(gt_path, gt.timestamps, gt.T_WC)
    write_tum(est_path, stamps, est.T_WC[keep])
    return gt_path, est_path


def run_evo(tool: str, args: list[str], tmp_path: Path) -> dict[str, float]:
    """Statistics the evo command-line tool ``tool`` saves for ``args``."""
    exe = shutil.which(tool)
    assert exe is not None, f"{tool} not found: evo is a declared dependency of como3r"
    results = tmp_path / f"{tool}.zip"
    subprocess.run(
        [exe, *args, "--save_results", str(results), "--no_warnings"],
        check=True,
        capture_output=True,
        timeout=60,
    )
    with zipfile.ZipFile(results) as archive:
        return json.loads(archive.read("stats.json"))


def test_ate_equals_evo_ape_cli(tmp_path: Path) -> None:
    gt_path, est_path = write_noisy_pair(tmp_path, seed=3)
    errors = agent_errors(associate(read_tum(est_path), read_tum(gt_path), "est", "gt"))
    assert errors.frames == FRAMES - 10
    assert errors.ate.rmse > 0.01
    stats = run_evo("evo_ape", ["tum", str(gt_path), str(est_path), "-as"], tmp_path)
    for name in ("rmse", "mean", "median", "max"):
        assert getattr(errors.ate, name) == pytest.approx(stats[name], abs=1e-9)


@pytest.mark.parametrize(
    ("relation", "field"), [("trans_part", "rpe_trans"), ("angle_deg", "rpe_rot_deg")]
)
def test_rpe_equals_evo_rpe_cli(tmp_path: Path, relation: str, field: str) -> None:
    gt_path, est_path = write_noisy_pair(tmp_path, seed=4)
    errors = agent_errors(associate(read_tum(est_path), read_tum(gt_path), "est", "gt"))
    args = [
        "tum",
        str(gt_path),
        str(est_path),
        "-as",
        "--delta",
        "1",
        "--delta_unit",
        "f",
        "-r",
        relation,
    ]
    stats = run_evo("evo_rpe", args, tmp_path)
    assert getattr(errors, field).rmse == pytest.approx(stats["rmse"], abs=1e-9)
    assert getattr(errors, field).rmse > 0.0


@pytest.mark.parametrize("overlap", [0, 2])
def test_too_few_associated_poses_names_both(overlap: int) -> None:
    rng = np.random.default_rng(5)
    gt = smooth_path(rng)
    # Shift all but `overlap` estimated stamps far outside the association window.
    stamps = gt.timestamps + np.where(np.arange(FRAMES) < overlap, 0.0, 1000.0)
    est = Trajectory(stamps, gt.T_WC)
    with pytest.raises(InputError, match=f"only {overlap} pose") as info:
        associate(est, gt, "run/agent_0.txt", "seq/groundtruth.txt")
    assert "run/agent_0.txt" in str(info.value) and "seq/groundtruth.txt" in str(info.value)


@pytest.mark.parametrize(
    ("shape", "which"),
    [("constant", "estimated"), ("collinear", "estimated"), ("collinear", "ground-truth")],
)
def test_degenerate_alignment_is_an_input_error(shape: str, which: str) -> None:
    rng = np.random.default_rng(6)
    gt = smooth_path(rng)
    poses = gt.T_WC.clone()
    line = torch.linspace(0.0, 1.0, FRAMES, dtype=torch.float64)[:, None]
    poses[:, :3] = 0.0 if shape == "constant" else line * torch.tensor([1.0, 2.0, 3.0])
    degenerate = Trajectory(gt.timestamps, poses)
    est, ref = (degenerate, gt) if which == "estimated" else (gt, degenerate)
    pair = associate(est, ref, "run/agent_0.txt", "gt.txt")
    with pytest.raises(InputError, match=f"run/agent_0.txt vs gt.txt.*{which}"):
        agent_errors(pair)


def test_merged_per_gauge_component() -> None:
    rng = np.random.default_rng(7)
    gts = [smooth_path(rng) for _ in range(3)]
    sim = random_sim3(rng)
    # Agents 1 and 2 share one gauge, agent 0 has its own.
    ests = [transformed(gts[0], *random_sim3(rng))] + [transformed(g, *sim) for g in gts[1:]]
    pairs = [associate(e, g, f"est{a}", f"gt{a}") for a, (e, g) in enumerate(zip(ests, gts))]
    assert merged_errors_by_component(pairs)[0].ate.rmse > 0.1
    groups = merged_errors_by_component(pairs, [[0], [2, 1]])
    assert [m.agents for m in groups] == [(1, 2)]
    assert groups[0].ate.rmse < 1e-6 and groups[0].frames == 2 * FRAMES
    assert merged_errors_by_component(pairs, [[0], [1], [2]]) == []


@pytest.mark.parametrize("components", [[[0, 3]], [[0, 1], [1, 2]]])
def test_invalid_components(components: list[list[int]]) -> None:
    rng = np.random.default_rng(8)
    gts = [smooth_path(rng) for _ in range(3)]
    pairs = [associate(g, g, f"est{a}", f"gt{a}") for a, g in enumerate(gts)]
    with pytest.raises(InputError, match="components"):
        merged_errors_by_component(pairs, components)


def test_association_leaves_frames_in_a_ground_truth_gap_out() -> None:
    """30 Hz frames against 100 Hz ground truth with a 150 ms hole and a late start: each
    frame takes the nearest sample within evo's 10 ms, so exactly the frames with no sample
    that close drop out, as ``evo_ape --t_max_diff 0.01`` drops them."""
    rng = np.random.default_rng(7)
    gt_full = smooth_path(rng, frames=400)
    stamps = 100.0 + 0.01 * np.arange(400)
    keep = ~((stamps >= 101.0) & (stamps < 101.15)) & (stamps >= 100.14)
    gt = Trajectory(stamps[keep], gt_full.T_WC[torch.from_numpy(keep)])
    frames = 100.003 + np.arange(110) / 30.0
    est = Trajectory(frames, torch.zeros(110, 8, dtype=torch.float64))
    est.T_WC[:, 6] = 1.0
    pair = associate(est, gt, "est.txt", "gt.txt")
    nearest = np.abs(frames[:, None] - gt.timestamps[None]).min(axis=1)
    expected = frames[nearest <= 0.01]
    np.testing.assert_allclose(pair.est.timestamps, expected)
    assert len(pair) <= 110 - 4 - 3  # the late start and the hole both cost frames
    assert np.abs(pair.gt.timestamps - pair.est.timestamps).max() <= 0.01
