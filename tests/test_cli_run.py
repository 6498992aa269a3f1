"""``como3r run``: bad input gives one error line and no output folder; MASt3R plumbing."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.prior.mast3r.testing import TINY_MODEL_STRING, tiny_network, write_checkpoint


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=1,
        overlap=0.2,
        frames=6,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    return root


def _run(*args: str):
    return CliRunner().invoke(app, ["run", *args])


def _assert_one_error(result, *fragments: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len([line for line in lines if line.startswith("error:")]) == 1, result.output
    for fragment in fragments:
        assert fragment in result.output, result.output


@pytest.mark.parametrize(
    "args, fragments",
    [
        (["--agent", "{missing}", "--prior", "simulated"], ["missing_agent"]),
        (["--agent", "{agent}", "--prior", "bogus"], ["bogus", "simulated"]),
        (["--agent", "{agent}", "--prior", "mast3r"], ["--weights"]),
        (["--agent", "{agent}", "--set", "tracking.sigma_rya=1"], ["tracking.sigma_rya"]),
        (["--agent", "{agent}", "--config", "{missing}.yaml"], ["missing_agent.yaml"]),
        (["--agent", "{agent}", "--prior", "mast3r", "--weights", "{garbage}"], ["garbage.pth"]),
        (
            ["--agent", "{agent}", "--device", "cuda", "--prior", "mast3r", "--weights", "{ckpt}"],
            ["cuda"],
        ),
    ],
)
def test_bad_input_gives_one_error_line_and_no_output(scene, tmp_path, args, fragments) -> None:
    if torch.cuda.is_available() and "cuda" in args:
        # CUDA is there, so what is wrong is the checkpoint (it holds no weights)
        fragments = ["tiny.pth", "does not fit the MASt3R network"]
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    ckpt = tmp_path / "tiny.pth"
    torch.save({"model": {}, "args": argparse.Namespace(model=TINY_MODEL_STRING)}, ckpt)
    values = {
        "missing": str(tmp_path / "missing_agent"),
        "agent": str(scene / "agent_0"),
        "garbage": str(garbage),
        "ckpt": str(ckpt),
    }
    out = tmp_path / "out"
    result = _run(*[a.format(**values) for a in args], "--out", str(out))
    _assert_one_error(result, *fragments)
    assert not out.exists() and not out.with_name("out.partial").exists()


def test_existing_output_folder_is_not_overwritten(scene, tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    result = _run("--agent", str(scene / "agent_0"), "--out", str(out), "--prior", "simulated")
    _assert_one_error(result, "--overwrite")
    assert (out / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_mast3r_plumbing_with_a_tiny_random_checkpoint(scene, tmp_path, device) -> None:
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    out = tmp_path / "run"
    result = _run(
        "--agent",
        str(scene / "agent_0"),
        "--out",
        str(out),
        "--prior",
        "mast3r",
        "--weights",
        str(ckpt),
        "--device",
        str(device),
        "--set",
        "input.long_side=64",
    )
    assert result.exit_code == 0, result.output
    for name in (
        "config.yaml",
        "map.ply",
        "graph.json",
        "metrics.json",
        "report.html",
        "trajectories/agent_0.txt",
        "keyframes/agent_0.txt",
    ):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    agent = metrics["agents"][0]
    # random weights track nothing sensible: every frame is accounted for, none invented
    assert agent["frames"] == 3
    assert agent["tracked"] + agent["lost"] == agent["frames"]
    assert "MASt3R" in json.dumps(metrics["prior"])
    assert torch.device(metrics["prior"]["device"]).type == device.type


def test_a_run_on_the_simulated_prior_says_so_everywhere(scene, tmp_path) -> None:
    out = tmp_path / "run"
    result = _run(
        "--agent",
        str(scene / "agent_0"),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--single-process",
        "--set",
        "input.long_side=64",
    )
    assert result.exit_code == 0, result.output
    assert "prior: simulated" in result.output
    assert "prior: simulated" in (out / "report.html").read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["prior"]["name"] == "SimulatedPrior"
    assert "frames_dropped" not in metrics["agents"][0]  # a recorded input drops nothing
