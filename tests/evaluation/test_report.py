"""evaluate_run: input resolution, ate.json, the plot and every bad-input error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.evaluation.plot import plane_axes
from como3r.evaluation.report import evaluate_run
from como3r.io.tum import write_tum

FRAMES = 100


def smooth_poses(rng: np.random.Generator, frames: int = FRAMES) -> np.ndarray:
    """``(frames, 7)`` smooth random path: positions (sinusoids) and xyzw quaternions."""
    s = np.linspace(0.0, 1.0, frames)[:, None, None]
    freq, phase = rng.uniform(0.3, 1.5, (1, 3, 3)), rng.uniform(0, 2 * np.pi, (1, 3, 3))
    positions = (rng.uniform(1.0, 4.0, (1, 3, 3)) * np.sin(2 * np.pi * freq * s + phase)).sum(-1)
    quat = Rotation.from_rotvec((0.4 * np.sin(2 * np.pi * freq * s + phase)).sum(-1)).as_quat()
    return np.concatenate([positions, quat], axis=1)


def write_poses(path: Path, stamps: np.ndarray, poses: np.ndarray) -> Path:
    write_tum(path, stamps, torch.from_numpy(poses))
    return path


def make_run(tmp_path: Path, agents: int = 2, seed: int = 0) -> tuple[Path, list[Path]]:
    """A run folder with noisy, per-agent Sim(3)-transformed estimates and agent GT folders."""
    rng = np.random.default_rng(seed)
    run, stamps = tmp_path / "run", 10.0 + 0.1 * np.arange(FRAMES)
    gt_dirs = []
    for a in range(agents):
        gt = smooth_poses(rng)
        gt_dirs.append(tmp_path / f"agent{a}")
        write_poses(gt_dirs[-1] / "groundtruth.txt", stamps, gt)
        rotation, scale = Rotation.random(random_state=rng), rng.uniform(0.5, 2.0)
        est = np.concatenate(
            [
                scale * rotation.apply(gt[:, :3]) + rng.normal(0, 0.02, (FRAMES, 3)),
                (rotation * Rotation.from_quat(gt[:, 3:])).as_quat(),
            ],
            axis=1,
        )
        write_poses(run / "trajectories" / f"agent_{a}.txt", stamps, est)
    return run, gt_dirs


def test_evaluate_run_writes_json_plot_and_table(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path, agents=3)
    out = tmp_path / "eval"
    summary = evaluate_run(run, gt_dirs, out)

    report = json.loads((out / "ate.json").read_text())
    assert [a["agent"] for a in report["agents"]] == [0, 1, 2]
    for entry, result in zip(report["agents"], summary.agents):
        assert entry["ate"]["rmse"] == result.errors.ate.rmse
        assert 0.0 < entry["ate"]["rmse"] < 0.1  # noise 0.02 per axis, after alignment
        assert entry["frames"] == FRAMES
        # named inside the run folder, which is renamed from DIR.partial when complete
        assert entry["est"] == f"trajectories/agent_{entry['agent']}.txt"
        assert set(entry) >= {"rpe_trans", "rpe_rot_deg", "alignment"}
        assert entry["alignment"]["scale"] > 0.0
    assert report["merged"]["ate"]["rmse"] == summary.merged_ate
    assert summary.merged_ate > 10 * max(r.errors.ate.rmse for r in summary.agents)
    assert report["parameters"]["max_time_diff_s"] == 0.01

    rows = summary.table_rows()
    assert [r["agent"] for r in rows] == [0, 1, 2, "merged"]
    assert all(r.keys() == rows[0].keys() for r in rows)
    assert any(str(out / "ate.json") in n for n in summary.notes)

    with Image.open(out / "trajectories.png") as image:
        pixels = np.asarray(image.convert("RGB"))
    assert image.format == "PNG" and pixels.shape[0] > 100
    colours = {tuple(c) for c in pixels.reshape(-1, 3)[::7]}
    assert len(colours) > 10  # lines in several colours, not a blank canvas


def test_ground_truth_staged_with_the_run_is_named_relative_to_it(tmp_path: Path) -> None:
    # como3r demo writes scene and run into OUT.partial and renames it: an absolute path into
    # the staging folder would name a folder that no longer exists
    staging = tmp_path / "demo.partial"
    run, gt_dirs = make_run(staging)
    outside = tmp_path / "elsewhere" / "agent1"
    outside.mkdir(parents=True)
    (outside / "groundtruth.txt").write_text((gt_dirs[1] / "groundtruth.txt").read_text())
    evaluate_run(run, [gt_dirs[0], outside], run)
    entries = json.loads((run / "ate.json").read_text())["agents"]
    assert entries[0]["gt"] == "../agent0/groundtruth.txt"
    assert entries[1]["gt"] == str(outside / "groundtruth.txt")
    staging.rename(tmp_path / "demo")
    assert (tmp_path / "demo" / "run" / entries[0]["gt"]).is_file()


def test_ground_truth_files_and_folders_agree(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    by_folder = evaluate_run(run, gt_dirs, tmp_path / "a")
    by_file = evaluate_run(run, [d / "groundtruth.txt" for d in gt_dirs], tmp_path / "b")
    assert by_file.merged_ate == by_folder.merged_ate
    ate = [[r.errors.ate.rmse for r in s.agents] for s in (by_file, by_folder)]
    assert ate[0] == ate[1]


def test_single_trajectory_file(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path, agents=1)
    summary = evaluate_run(run / "trajectories" / "agent_0.txt", gt_dirs, tmp_path / "out")
    assert len(summary.agents) == 1
    assert summary.merged_ate == pytest.approx(summary.agents[0].errors.ate.rmse, abs=1e-12)
    assert (tmp_path / "out" / "ate.json").is_file()


def test_components_split_the_merged_ate(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path, agents=3)
    summary = evaluate_run(run, gt_dirs, tmp_path / "out", components=[[0, 2], [1]])
    assert summary.merged is None and summary.merged_ate is None
    assert [r["agent"] for r in summary.table_rows()][-1] == "merged 0+2"
    assert any("component" in note for note in summary.notes)
    report = json.loads((tmp_path / "out" / "ate.json").read_text())
    assert report["merged"] is None
    assert [m["agents"] for m in report["merged_components"]] == [[0, 2]]


def _missing_est(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    return run.parent / "nope", gts, run.parent / "nope"


def _no_trajectories_dir(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    for f in (run / "trajectories").iterdir():
        f.unlink()
    (run / "trajectories").rmdir()
    return run, gts, run / "trajectories"


def _gap_in_agents(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    (run / "trajectories" / "agent_1.txt").rename(run / "trajectories" / "agent_2.txt")
    return run, gts, run / "trajectories" / "agent_1.txt"


def _count_mismatch(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    return run, gts[:1], run / "trajectories"


def _gt_folder_without_file(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    (gts[1] / "groundtruth.txt").unlink()
    return run, gts, gts[1]


def _missing_gt_file(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    return run, [gts[0], gts[1] / "missing.txt"], gts[1] / "missing.txt"


def _file_with_two_gts(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    est = run / "trajectories" / "agent_0.txt"
    return est, gts, est


def _no_common_stamps(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    est = run / "trajectories" / "agent_1.txt"
    write_poses(est, 500.0 + np.arange(FRAMES), smooth_poses(np.random.default_rng(1)))
    return run, gts, est


def _collinear_estimate(run: Path, gts: list[Path]) -> tuple[Path, list[Path], Path]:
    est = run / "trajectories" / "agent_0.txt"
    poses = smooth_poses(np.random.default_rng(2))
    poses[:, :3] = np.linspace(0, 1, FRAMES)[:, None] * np.array([1.0, -2.0, 0.5])
    write_poses(est, 10.0 + 0.1 * np.arange(FRAMES), poses)
    return run, gts, est


@pytest.mark.parametrize(
    "break_input",
    [
        _missing_est,
        _no_trajectories_dir,
        _gap_in_agents,
        _count_mismatch,
        _gt_folder_without_file,
        _missing_gt_file,
        _file_with_two_gts,
        _no_common_stamps,
        _collinear_estimate,
    ],
)
def test_bad_input_names_the_file(tmp_path: Path, break_input) -> None:
    run, gt_dirs = make_run(tmp_path)
    est, gts, culprit = break_input(run, gt_dirs)
    with pytest.raises(InputError) as info:
        evaluate_run(est, gts, tmp_path / "out")
    message = str(info.value)
    assert str(culprit) in message and "\n" not in message
    assert not (tmp_path / "out" / "ate.json").exists()


def test_too_few_poses_names_both_files(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    _no_common_stamps(run, gt_dirs)
    with pytest.raises(InputError) as info:
        evaluate_run(run, gt_dirs, tmp_path / "out")
    assert str(gt_dirs[1] / "groundtruth.txt") in str(info.value)


def test_output_path_that_is_a_file(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    (tmp_path / "out").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        evaluate_run(run, gt_dirs, tmp_path / "out")


@pytest.mark.parametrize(("flat_axis", "expected"), [(1, (0, 2)), (2, (0, 1)), (0, (1, 2))])
def test_plot_plane_follows_ground_truth_spread(flat_axis: int, expected: tuple[int, int]) -> None:
    positions = smooth_poses(np.random.default_rng(3))[:, :3]
    positions[:, flat_axis] *= 0.01
    assert plane_axes([positions[:50], positions[50:]]) == expected
