"""A new user's own images (issue 17): a folder of JPEGs without depth, run with
``--prior mast3r`` and a local checkpoint, and the mistakes such a user makes first."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import pytest
from PIL import Image
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.prior.mast3r.testing import tiny_network, write_checkpoint
from como3r.runtime import processes


def _images(agent: Path, count: int = 4, flat: bool = False) -> Path:
    """An agent folder of ``count`` ordinary JPEGs in ``rgb/`` (or, ``flat``, in the folder
    itself) and nothing else: the images of a small synthetic scene (what a camera would
    give), without its depth, calibration or ground truth."""
    scene = agent.with_name(f"{agent.name}_scene")
    scene.mkdir(parents=True)
    synthesize(
        scene,
        agents=1,
        seed=1,
        overlap=0.2,
        frames=count,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    folder = agent if flat else agent / "rgb"
    folder.mkdir(parents=True)
    for i, png in enumerate(sorted((scene / "agent_0" / "rgb").iterdir())):
        Image.open(png).convert("RGB").save(folder / f"IMG_{i:04d}.jpg", quality=90)
    return agent


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})


def test_images_with_the_simulated_prior_name_mast3r_before_any_work(
    tmp_path, only_error_line
) -> None:
    """Used to start the agents, log an ERROR line per agent and then fail."""
    agent = _images(tmp_path / "mine")
    out = tmp_path / "out"
    line = only_error_line(
        _invoke("run", "--agent", str(agent), "--out", str(out), "--prior", "simulated")
    )
    assert "no depth/ folder" in line and "--prior mast3r" in line
    assert not out.exists()


def test_a_flat_folder_of_images_says_where_they_belong(tmp_path, only_error_line) -> None:
    agent = _images(tmp_path / "mine", flat=True)
    ckpt = tmp_path / "x.pth"
    ckpt.write_bytes(b"the folder is read before the checkpoint")
    line = only_error_line(
        _invoke(
            "run", "--agent", str(agent), "--out", str(tmp_path / "out"), "--weights", str(ckpt)
        )
    )
    assert f"its images belong in {agent / 'rgb'}/" in line


@pytest.mark.slow
def test_own_jpegs_with_a_local_checkpoint_run_and_warn_once(tmp_path, caplog) -> None:
    """The README's path for one's own images: no depth, no calibration, MASt3R from a
    local checkpoint, one agent process. Without retrieval files loop closure is off, said
    once here (the agent process builds its prior quiet: test_build_prior_quiet_does_not_warn;
    it used to say it again on stderr)."""
    agent = _images(tmp_path / "mine", count=6)
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING):
        result = _invoke(
            "run",
            "--agent",
            str(agent),
            "--out",
            str(out),
            "--weights",
            str(ckpt),
            "--set",
            "input.long_side=64",
        )
    assert result.exit_code == 0, result.output
    for name in ("map.ply", "metrics.json", "report.html", "trajectories/agent_0.txt"):
        assert (out / name).is_file(), name
    retrieval_off = [r for r in caplog.records if "no --retrieval-weights" in r.getMessage()]
    assert len(retrieval_off) == 1, [r.getMessage() for r in caplog.records]


def _slot(agent: int) -> SimpleNamespace:
    return SimpleNamespace(
        agent=agent,
        status="running",
        error=None,
        clock=0.0,
        process=SimpleNamespace(is_alive=lambda: False),
    )


def test_the_last_agent_failing_is_not_logged_besides_the_error_line(caplog) -> None:
    """'agent N failed ... (the other agents continue)' only while another agent is left;
    the last failure is said by the run's one error line ('every agent failed: ...')."""
    runtime = processes._Runtime.__new__(processes._Runtime)
    runtime.slots, runtime.progress = [_slot(0), _slot(1)], None
    runtime.hub, runtime.verifiers = SimpleNamespace(drop=lambda agent: None), None
    with caplog.at_level(logging.WARNING, logger=processes.__name__):
        runtime._fail(runtime.slots[0], "first")
        runtime._fail(runtime.slots[1], "second")
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == ["agent 0 failed: first (the other agents continue)"]
    assert [s.status for s in runtime.slots] == ["failed", "failed"]


@pytest.mark.parametrize("quiet", [False, True])
def test_build_prior_quiet_does_not_warn(quiet, tmp_path, caplog) -> None:
    from como3r.config import Config
    from como3r.runtime.pipeline import PriorSpec, build_prior

    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    with caplog.at_level(logging.WARNING):
        _, codebook = build_prior(PriorSpec("mast3r", weights=ckpt), Config(), quiet=quiet)
    assert codebook is None
    assert any("no --retrieval-weights" in r.getMessage() for r in caplog.records) != quiet
