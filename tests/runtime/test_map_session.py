"""``como3r run --map`` and ``--freeze-map`` (runtime/map_session.py; issue 14 item 3): agent 0
maps a place today, agent 1 comes tomorrow against agent 0's map, and the output of the
second day holds both agents in one frame; a frozen map keeps its keyframes exactly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from como3r.cli import app
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]

RUN = ["--prior", "simulated", "--set", "input.long_side=64", "-q"]


@pytest.fixture(scope="module")
def scene(tiny_scene) -> Path:
    return tiny_scene(frames=8, seed=1, overlap=0.2)  # two agents that meet


@pytest.fixture(scope="module")
def day1(scene, tmp_path_factory) -> Path:
    """Agent 0 alone, today."""
    out = tmp_path_factory.mktemp("day1") / "run"
    result = CliRunner().invoke(
        app, ["run", "--agent", str(scene / "agent_0"), "--out", str(out), *RUN, "--single-process"]
    )
    assert result.exit_code == 0, result.output
    return out


def _day2(scene: Path, day1: Path, out: Path, *extra: str) -> dict:
    """Agent 1 tomorrow, on day 1's map, in the default runtime (agent processes)."""
    result = CliRunner().invoke(
        app,
        [
            "run",
            "--map",
            str(day1),
            "--agent",
            str(scene / "agent_1"),
            "--out",
            str(out),
            *RUN,
            *extra,
        ],
    )
    assert result.exit_code == 0, result.output
    return json.loads((out / "metrics.json").read_text())


def _ate(scene: Path, run: Path) -> dict:
    """``como3r eval`` of both agents' trajectories: per agent and merged (one Sim(3))."""
    result = CliRunner().invoke(
        app,
        ["eval", "--est", str(run), "--gt", str(scene / "agent_0"), "--gt", str(scene / "agent_1")],
    )
    assert result.exit_code == 0, result.output
    return json.loads((run / "ate.json").read_text())


def _keyframes(run: Path, agent: int) -> list:
    session = read_session(run / STORE_NAME)
    graph = session.graph
    return [graph.keyframes[g] for g in graph.agent_keyframes(agent)]


def test_a_second_day_joins_the_first_days_map_in_one_frame(scene, day1, tmp_path) -> None:
    out = tmp_path / "day2"
    metrics = _day2(scene, day1, out)
    assert metrics["components"] == [[0, 1]]  # agent 1 found agent 0's places
    assert [a["status"] for a in metrics["runtime"]["agents"]] == ["map", "finished"]
    before, after = _keyframes(day1, 0), _keyframes(out, 0)
    assert [kf.frame_index for kf in after] == [kf.frame_index for kf in before]
    moved = max(float((a.T_WC - b.T_WC)[:3].norm()) for a, b in zip(after, before))
    assert moved > 0  # the global BA refined the saved map too
    day1_frames = np.loadtxt(day1 / "trajectories" / "agent_0.txt", ndmin=2)[:, 0]
    day2_frames = np.loadtxt(out / "trajectories" / "agent_0.txt", ndmin=2)[:, 0]
    assert np.array_equal(day1_frames, day2_frames)  # every frame agent 0 tracked
    ate = _ate(scene, out)
    per_agent = [a["ate"]["rmse"] for a in ate["agents"]]
    merged = ate["merged"]["ate"]["rmse"]
    assert merged <= 2 * max(per_agent), (merged, per_agent)  # one frame, not two
    print(
        f"two days: merged ATE {merged:.4f} m (agents {per_agent}); the saved keyframes "
        f"moved up to {moved:.2e} m"
    )


def test_a_frozen_map_keeps_its_keyframes(scene, day1, tmp_path) -> None:
    out = tmp_path / "day2"
    metrics = _day2(scene, day1, out, "--freeze-map", "--single-process")
    assert metrics["components"] == [[0, 1]]
    for before, after in zip(_keyframes(day1, 0), _keyframes(out, 0), strict=True):
        assert torch.equal(before.T_WC, after.T_WC)
        assert torch.equal(before.X_hat, after.X_hat)
    ate = _ate(scene, out)
    assert ate["merged"]["ate"]["rmse"] <= 2 * max(a["ate"]["rmse"] for a in ate["agents"])


def test_what_cannot_start_on_a_map_is_one_error_line(
    scene, day1, tmp_path, only_error_line
) -> None:
    agent = ["--agent", str(scene / "agent_1")]
    line = only_error_line(
        CliRunner().invoke(app, ["run", *agent, "--out", str(tmp_path / "a"), *RUN, "--freeze-map"])
    )
    assert "--freeze-map" in line and "--map" in line
    line = only_error_line(
        CliRunner().invoke(
            app, ["run", *agent, "--map", str(scene), "--out", str(tmp_path / "b"), *RUN]
        )
    )
    assert "no session.db there" in line
    # this --set is the point of the check: a map made with another configuration
    line = only_error_line(
        CliRunner().invoke(
            app,
            [
                "run",
                *agent,
                "--map",
                str(day1),
                "--out",
                str(tmp_path / "c"),
                *RUN,
                "--set",
                "depth.alternation_rounds=1",
            ],
        )
    )
    assert "another configuration (depth.alternation_rounds" in line
    assert not any((tmp_path / name).exists() for name in "abc")
