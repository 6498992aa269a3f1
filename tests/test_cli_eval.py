"""`como3r eval` end to end through the typer app: exit codes, table, files, error line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from como3r.cli import app
from como3r.io.tum import write_tum

FRAMES = 80


def make_run(tmp_path: Path, agents: int = 2, one_frame: bool = False) -> tuple[Path, list[Path]]:
    """A run folder whose estimates are noisy, per-agent rotated/scaled copies of the GT
    (``one_frame``: all rotated and scaled alike, as agents whose maps merged)."""
    rng = np.random.default_rng(0)
    run, stamps, gt_dirs = tmp_path / "run", 0.1 * np.arange(FRAMES), []
    s = np.linspace(0.0, 1.0, FRAMES)[:, None, None]
    shared = Rotation.random(random_state=rng)
    for a in range(agents):
        freq, phase = rng.uniform(0.3, 1.5, (1, 3, 3)), rng.uniform(0, 2 * np.pi, (1, 3, 3))
        positions = (3.0 * np.sin(2 * np.pi * freq * s + phase)).sum(-1)
        quat = Rotation.from_rotvec((0.4 * np.sin(2 * np.pi * freq * s + phase)).sum(-1))
        gt_dirs.append(tmp_path / f"agent{a}")
        write_tum(
            gt_dirs[-1] / "groundtruth.txt",
            stamps,
            torch.from_numpy(np.concatenate([positions, quat.as_quat()], axis=1)),
        )
        rotation = shared if one_frame else Rotation.random(random_state=rng)
        noisy = 1.5 * rotation.apply(positions) + rng.normal(0, 0.02, positions.shape)
        est = np.concatenate([noisy, (rotation * quat).as_quat()], axis=1)
        write_tum(run / "trajectories" / f"agent_{a}.txt", stamps, torch.from_numpy(est))
    return run, gt_dirs


def invoke(run: Path, gts: list[Path], *extra: str):
    args = ["eval", "--est", str(run)] + [a for g in gts for a in ("--gt", str(g))] + list(extra)
    return CliRunner().invoke(app, args, env={"COLUMNS": "200"})


def test_eval_good_run(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    out = tmp_path / "eval"
    result = invoke(run, gt_dirs, "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "merged" in result.stdout and "ATE RMSE" in result.stdout
    assert (out / "ate.json").stat().st_size > 0
    assert (out / "trajectories.png").stat().st_size > 0
    assert str(out / "ate.json") in result.stdout


def test_eval_defaults_to_writing_into_the_run(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    assert invoke(run, gt_dirs).exit_code == 0
    assert (run / "ate.json").is_file() and (run / "trajectories.png").is_file()


def test_eval_bad_input_prints_one_error_line(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    (gt_dirs[1] / "groundtruth.txt").unlink()
    result = invoke(run, gt_dirs)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:")
    assert str(gt_dirs[1]) in lines[0]
    assert "Traceback" not in result.output


def test_eval_count_mismatch_exits_2(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    result = invoke(run, gt_dirs[:1])
    assert result.exit_code == 2
    assert result.stderr.startswith("error:") and "trajectories" in result.stderr


def test_eval_writes_the_report_of_the_run_with_its_evaluation(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    out = tmp_path / "eval"
    result = invoke(run, gt_dirs, "--out", str(out))
    assert result.exit_code == 0, result.output
    page = (out / "report.html").read_text()
    assert f"wrote {out / 'report.html'}" in " ".join(result.stdout.split())
    assert not (run / "report.html").exists()  # --out keeps the run folder as it was
    # the estimates drawn against the ground truth after this evaluation's alignment
    assert "ground truth dashed grey" in page and "<img alt='ATE over time'" in page
    assert f"evaluated by como3r eval against {gt_dirs[0] / 'groundtruth.txt'}" in page
    merged = json.loads((out / "ate.json").read_text())["merged"]["ate"]["rmse"]
    assert f"<b>merged ATE RMSE [m]</b> {merged:.4g}" in page


def test_eval_report_option_names_the_page(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path)
    page = tmp_path / "pages" / "evaluated.html"
    result = invoke(run, gt_dirs, "--report", str(page))
    assert result.exit_code == 0, result.output
    assert "<img alt='trajectories'" in page.read_text()
    assert (run / "ate.json").is_file() and not (run / "report.html").exists()


def test_eval_report_needs_a_run_folder(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path, agents=1)
    result = invoke(
        run / "trajectories" / "agent_0.txt", gt_dirs, "--report", str(tmp_path / "r.html")
    )
    assert result.exit_code == 2
    assert result.stderr.startswith("error: --report:") and "run folder" in result.stderr
    plain = invoke(run / "trajectories" / "agent_0.txt", gt_dirs, "--out", str(tmp_path / "e"))
    assert plain.exit_code == 0, plain.output  # a trajectory file is evaluated, no report
    assert not (tmp_path / "e" / "report.html").exists()


def test_eval_warns_once_when_the_ground_truths_are_in_another_order(tmp_path: Path) -> None:
    run, gt_dirs = make_run(tmp_path, agents=3, one_frame=True)
    in_order = invoke(run, gt_dirs, "--out", str(tmp_path / "in_order"))
    assert in_order.exit_code == 0, in_order.output
    assert "warning" not in in_order.output
    # agent 0's ground truth given third, agent 1's first, agent 2's second
    result = invoke(run, [gt_dirs[1], gt_dirs[2], gt_dirs[0]], "--out", str(tmp_path / "out"))
    assert result.exit_code == 0, result.output
    assert result.output.count("warning") == 1
    assert "taking --gt #3, #1, #2 for agents 0, 1, 2" in result.output
    assert "Is --gt in agent order" in result.output


def test_eval_does_not_compare_orders_of_agents_in_separate_frames(tmp_path: Path) -> None:
    """Agents never merged (several gauge components): no merged ATE to compare orders by."""
    run, gt_dirs = make_run(tmp_path, agents=2, one_frame=True)
    swapped = invoke(run, gt_dirs[::-1], "--out", str(tmp_path / "swapped"))
    assert "taking --gt #2, #1 for agents 0, 1" in swapped.output
    (run / "graph.json").write_text(json.dumps({"keyframes": [], "components": [[0], [1]]}))
    result = invoke(run, gt_dirs[::-1], "--out", str(tmp_path / "out"))
    assert result.exit_code == 0, result.output
    assert "warning" not in result.output
