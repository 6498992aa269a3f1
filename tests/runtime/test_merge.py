"""``como3r merge A B --out C`` (runtime/merge.py; issue 14 item 3): two sessions that see the
same places end in one map, in A's frame; two that never do are one error line and no
output."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

RUN = ["--prior", "simulated", "--set", "input.long_side=64", "-q", "--single-process"]


def _alone(scene: Path, agent: int, out: Path) -> Path:
    """A session of one agent of ``scene``."""
    result = CliRunner().invoke(
        app, ["run", "--agent", str(scene / f"agent_{agent}"), "--out", str(out), *RUN]
    )
    assert result.exit_code == 0, result.output
    return out


def _merge(first: Path, second: Path, out: Path):
    return CliRunner().invoke(
        app, ["merge", str(first), str(second), "--out", str(out), "--prior", "simulated", "-q"]
    )


@pytest.mark.slow
def test_two_sessions_that_meet_merge_into_one_map_in_the_first_ones_frame(
    tiny_scene, tmp_path
) -> None:
    scene = tiny_scene(frames=8, seed=1, overlap=0.2)
    first, second = _alone(scene, 0, tmp_path / "a"), _alone(scene, 1, tmp_path / "b")
    out = tmp_path / "merged"
    result = _merge(first, second, out)
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["components"] == [[0, 1]]
    merged, a, b = (read_session(run / STORE_NAME) for run in (out, first, second))
    assert len(merged.graph) == len(a.graph) + len(b.graph)
    assert merged.finished and set(merged.reports) == {0, 1}
    anchor_before, anchor_after = a.graph.keyframes[0], merged.graph.keyframes[0]
    assert torch.equal(anchor_before.T_WC, anchor_after.T_WC)  # A's frame is kept
    assert sorted((out / "trajectories").iterdir()) == [
        out / "trajectories" / "agent_0.txt",
        out / "trajectories" / "agent_1.txt",
    ]
    result = CliRunner().invoke(
        app,
        ["eval", "--est", str(out), "--gt", str(scene / "agent_0"), "--gt", str(scene / "agent_1")],
    )
    assert result.exit_code == 0, result.output
    ate = json.loads((out / "ate.json").read_text())
    per_agent = [entry["ate"]["rmse"] for entry in ate["agents"]]
    assert ate["merged"]["ate"]["rmse"] <= 2 * max(per_agent), ate["merged"]  # one frame
    print(f"merged ATE {ate['merged']['ate']['rmse']:.4f} m (agents {per_agent})")


@pytest.mark.slow
def test_two_sessions_that_never_meet_are_one_error_line(tmp_path, only_error_line) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    synthesize(
        scene,
        agents=2,
        seed=1,
        overlap=0.2,
        frames=16,
        preset="no-meeting",
        width=64,
        height=48,
        progress=None,
    )
    first, second = _alone(scene, 0, tmp_path / "a"), _alone(scene, 1, tmp_path / "b")
    assert all(len(read_session(run / STORE_NAME).graph) >= 2 for run in (first, second))
    out = tmp_path / "merged"
    line = only_error_line(_merge(first, second, out))
    assert "share no place" in line and str(first) in line and str(second) in line
    assert not out.exists() and not out.with_name("merged.partial").exists()


def test_a_folder_without_a_finished_session_is_one_error_line(
    tiny_scene, tmp_path, only_error_line
) -> None:
    scene = tiny_scene(frames=8, seed=1, overlap=0.2)
    line = only_error_line(_merge(scene, scene, tmp_path / "merged"))
    assert "merge" in line and "no session.db there" in line
