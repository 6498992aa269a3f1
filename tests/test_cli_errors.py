"""Every failure a user can cause is one ``error:`` line and exit status 2; Ctrl-C is one
``interrupted:`` line and exit status 130, with nothing written (a run interrupted
once its session store holds work keeps it, and says how to continue it)."""

from __future__ import annotations

import contextlib
import io
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from rich.console import Console
from typer.testing import CliRunner

from como3r import cli_common
from como3r.cli import app
from como3r.config import Config, apply_overrides, load_config, validate
from como3r.data.synth import synthesize
from como3r.errors import ConfigError, StoreError
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=1,
        overlap=0.2,
        frames=4,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    return root


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args), env={"COLUMNS": "80"})


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["run", "--out", "x"], "no input: give --agent PATH or --camera SOURCE"),
        (["run"], "no input: give --agent PATH or --camera SOURCE"),  # the input first, then --out
        (["run", "--agent", "a"], "missing option --out"),
        (["eval", "--est", "x"], "Missing option '--gt'"),
        (["run", "--agent", "a", "--out", "x", "--bogus"], "No such option: --bogus"),
        (["synth", "--out", "x", "--agents", "abc"], "Invalid value for '--agents'"),
        (["synth", "--out", "x", "--agents", "0"], "Invalid value for '--agents'"),
        (["bogus"], "No such command 'bogus'"),
        (["--bogus", "run"], "No such option: --bogus"),
        (["weights", "fetch", "--nope"], "No such option: --nope"),
    ],
)
def test_option_parsing_errors_are_one_line(args, fragment, only_error_line) -> None:
    line = only_error_line(_invoke(*args))
    assert fragment in line and "--help" in line


def test_no_arguments_still_prints_the_help() -> None:
    result = _invoke()
    assert "Usage" in result.output and "error:" not in result.output


def test_yaml_syntax_error_is_one_line_naming_file_and_line(
    scene, tmp_path, only_error_line
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking:\n  sigma_ray: [1, 2\n  huber_k: 1\n")
    out = tmp_path / "out"
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--config",
            str(bad),
        )
    )
    assert f"{bad}:3:" in line and "not valid YAML" in line
    assert not out.exists()


def test_unparsable_override_is_one_line(scene, tmp_path, only_error_line) -> None:
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--set",
            "tracking.sigma_ray=[1",
        )
    )
    assert "cannot parse override value '[1'" in line


@pytest.mark.parametrize(
    "override, message",
    [
        ("tracking.sigma_ray=-1", "tracking.sigma_ray must be > 0, got -1.0"),
        ("tracking.sigma_depth=0", "tracking.sigma_depth must be > 0"),
        ("tracking.rel_cost_tol=0", "tracking.rel_cost_tol must be > 0"),
        ("matching.convergence_tol=-1e-6", "matching.convergence_tol must be > 0"),
        ("depth.sigma_point=0", "depth.sigma_point must be > 0"),
        ("tracking.min_inlier_fraction=1.5", "tracking.min_inlier_fraction must be in [0, 1]"),
        ("tracking.keyframe_match_fraction=-0.1", "tracking.keyframe_match_fraction must be in"),
        ("verification.min_covisible_ratio=2", "verification.min_covisible_ratio must be in"),
        ("tracking.inlier_angle_deg=0", "tracking.inlier_angle_deg must be > 0"),
        ("input.prefetch_frames=-1", "input.prefetch_frames must be >= 0"),
        ("input.long_side=500", "input.long_side must be a positive multiple of 16"),
        ("input.long_side=0", "input.long_side must be a positive multiple of 16"),
        ("input.subsample=0", "input.subsample must be >= 1"),
        ("tracking.max_iters=0", "tracking.max_iters must be >= 1"),
        ("global_ba.max_iters_cleanup=0", "global_ba.max_iters_cleanup must be >= 1"),
        ("depth.inner_iters=0", "depth.inner_iters must be >= 1"),
        ("local_solve.dense_keyframes=0", "local_solve.dense_keyframes must be >= 1"),
        ("local_solve.relinearize_tol=0", "local_solve.relinearize_tol must be > 0"),
        ("decentralized.confidence_k=0", "decentralized.confidence_k must be > 0"),
        (
            "decentralized.registration.dense_max_shift_ratio=0",
            "decentralized.registration.dense_max_shift_ratio must be > 0",
        ),
        ("simulated_prior.gross_failure_rate=2", "simulated_prior.gross_failure_rate must be in"),
        ("tracking.fusion=pixels", "tracking.fusion: 'pixels' is not one of"),
    ],
)
def test_out_of_range_values_are_refused_when_overridden(override, message) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        apply_overrides(Config(), [override])


@pytest.mark.parametrize(
    "override",
    [
        "input.prefetch_frames=0",
        "depth.alternation_rounds=0",
        "matching.descriptor_radius=0",
        "tracking.min_inlier_fraction=0",
        "tracking.min_inlier_fraction=1",
        "input.long_side=96",
    ],
)
def test_zero_where_it_means_off_and_range_ends_are_accepted(override) -> None:
    apply_overrides(Config(), [override])


def test_defaults_are_valid() -> None:
    assert validate(Config()) == Config()


def test_out_of_range_value_in_a_file_names_file_and_key(tmp_path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("tracking:\n  sigma_ray: -0.001\n")
    with pytest.raises(ConfigError, match=f"{path}: tracking.sigma_ray must be > 0"):
        load_config(path)


def test_out_of_range_override_at_the_cli_is_one_line_and_no_output(
    scene, tmp_path, only_error_line
) -> None:
    out = tmp_path / "out"
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--set",
            "tracking.sigma_ray=-1",
        )
    )
    assert "tracking.sigma_ray must be > 0" in line
    assert not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_cuda_is_an_error(scene, tmp_path, only_error_line) -> None:
    out = tmp_path / "out"
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--device",
            "cuda",
        )
    )
    assert "--device cuda" in line and "--device cpu" in line
    assert not out.exists()


def test_unknown_device_is_an_error(scene, tmp_path, only_error_line) -> None:
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--device",
            "tpu",
        )
    )
    assert "unknown --device 'tpu'" in line


def test_output_folder_that_cannot_be_created_is_one_line(tmp_path, only_error_line) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    line = only_error_line(_invoke("synth", "--out", str(blocker / "scene"), "--frames", "2"))
    assert str(blocker) in line


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--prior", "simulated", "--precision", "fp8"], "unknown --precision 'fp8'"),
        (["--prior", "bogus"], "unknown --prior 'bogus'"),
        (["--prior", "simulated", "--mode", "bogus"], "unknown --mode 'bogus'"),
        (["--weights", "{tmp}/nothere.pth"], "--weights {tmp}/nothere.pth: no such file"),
    ],
)
def test_run_options_are_checked_before_any_work(
    args, fragment, scene, tmp_path, only_error_line
) -> None:
    """A malformed --precision is an error even with the simulated prior (which ignores a
    valid one); these are found before the output folder or a progress bar appears."""
    out = tmp_path / "out"
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--out",
            str(out),
            *[a.format(tmp=tmp_path) for a in args],
        )
    )
    assert fragment.format(tmp=tmp_path) in line
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize(
    "args",
    [
        ["run", "--agent", "{tmp}/missing_agent", "--prior", "simulated", "--out", "{tmp}/out"],
        ["synth", "--out", "{tmp}/out", "--height", "5000"],  # found inside the rendering
    ],
)
def test_stderr_is_only_the_error_line_when_not_a_terminal(args, tmp_path) -> None:
    """The real command with its stderr in a pipe: no progress bar is printed (it used to
    print its last state, '0/?', above the error)."""
    child = subprocess.run(
        [sys.executable, "-m", "como3r.cli", *[a.format(tmp=tmp_path) for a in args]],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert child.returncode == 2, child.stderr
    assert len(child.stderr.splitlines()) == 1 and child.stderr.startswith("error: "), child.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("fail", [False, True])
def test_progress_bar_on_a_terminal_is_erased_by_an_error(fail, monkeypatch) -> None:
    terminal = io.StringIO()
    monkeypatch.setattr(
        cli_common, "err_console", Console(file=terminal, force_terminal=True, width=60)
    )
    with contextlib.suppress(RuntimeError):
        with cli_common.progress_bar() as bar:
            bar.advance(bar.add_task("work", total=3))
            if fail:
                raise RuntimeError
    assert "1/3" in terminal.getvalue()
    # the last thing written erases the bar's line when the work failed, else it stays
    assert terminal.getvalue().endswith("\x1b[1A\x1b[2K") == fail


def _interrupt(*_args, **_kwargs) -> None:
    raise KeyboardInterrupt


@pytest.mark.parametrize("command", ["synth", "demo", "run"])
def test_ctrl_c_is_one_line_and_leaves_nothing(command, scene, tmp_path, monkeypatch) -> None:
    out = tmp_path / "out"
    if command == "run":
        monkeypatch.setattr("como3r.runtime.pipeline.load_frame", _interrupt)
        args = [
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--prior",
            "simulated",
            "--single-process",
            "--set",
            "input.prefetch_frames=0",
        ]
    else:
        monkeypatch.setattr("como3r.data.synth.synthesize", _interrupt)
        args = [command, "--frames", "4"]
    result = _invoke(*args, "--out", str(out))
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 130, result.output
    assert lines[-1] == f"interrupted: nothing was written to {out}"
    assert not [line for line in lines if line.startswith(("error", "Traceback"))]
    assert not out.exists() and not out.with_name("out.partial").exists()


@pytest.mark.slow
def test_sigint_during_synth(tmp_path) -> None:
    """The real signal, in a child process: waits until the work has started."""
    out = tmp_path / "scene"
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from como3r.cli import main; main()",
            "synth",
            "--out",
            str(out),
            "--frames",
            "2000",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    staging = out.with_name("scene.partial")
    while not (staging / "agent_0").exists() and child.poll() is None:
        time.sleep(0.05)
    child.send_signal(signal.SIGINT)
    _, stderr = child.communicate(timeout=300)
    assert child.returncode == 130, stderr
    assert stderr.splitlines()[-1] == f"interrupted: nothing was written to {out}"
    assert not out.exists() and not staging.exists()


def _children(pid: int) -> list[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(c) for c in path.read_text().split()] if path.exists() else []


@pytest.fixture(scope="module")
def longer_scene(tmp_path_factory) -> Path:
    """Two agents with frames enough to be interrupted halfway (the scene above, 4 frames,
    may be finished before a keyframe is stored)."""
    root = tmp_path_factory.mktemp("longer_scene")
    synthesize(
        root,
        agents=2,
        seed=1,
        overlap=0.2,
        frames=24,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    return root


@pytest.mark.slow
@pytest.mark.skipif(
    not Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists(),
    reason="needs Linux /proc children lists",
)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_an_interrupted_multiprocess_run_keeps_its_store(longer_scene, tmp_path, signum) -> None:
    """The real signals, in a child process. Ctrl-C in a terminal signals the whole process
    group, agent processes included: they leave it to the coordinator (they used to print
    KeyboardInterrupt tracebacks from wherever they were, often torch's imports). SIGTERM
    (``kill PID``, a service manager stopping it) reaches the main process only. Either way
    the coordinator stops at its next checkpoint, stops the agents, keeps ``OUT.partial``
    with its session store and ends on one line giving the exact command that continues
    it, which finishes the run."""
    out, partial = tmp_path / "out", tmp_path / "out.partial"
    args = [
        "run",
        "--agent",
        str(longer_scene / "agent_0"),
        "--agent",
        str(longer_scene / "agent_1"),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--set",
        "input.long_side=64",
        "-q",
    ]

    def default_sigint() -> None:  # a test runner started in the background ignores it
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    child = subprocess.Popen(
        [sys.executable, "-m", "como3r.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
        start_new_session=True,
    )
    deadline = time.monotonic() + 300
    while not _stored(partial / STORE_NAME) and child.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert len(_children(child.pid)) >= 2  # the agent processes are still working
    if signum == signal.SIGINT:
        os.killpg(child.pid, signum)
    else:
        child.send_signal(signum)
    _, stderr = child.communicate(timeout=300)
    assert child.returncode == 128 + signum, stderr
    command = shlex.join(["python", "-m", "como3r.cli", *args, "--resume"])
    assert stderr.splitlines()[-1] == (
        f"interrupted: the session store in {partial} is kept; continue with: {command}"
    ), stderr
    assert "Traceback" not in stderr and not out.exists()
    result = _invoke(*args, "--resume")
    assert result.exit_code == 0, result.output
    assert (out / "metrics.json").is_file() and not partial.exists()


def _stored(store: Path) -> bool:
    """Whether ``store`` exists and holds a keyframe (read paged: polled every 0.1 s, a
    full read takes 3.5 times the CPU)."""
    try:
        return store.is_file() and len(read_session(store, paged=True).graph) > 0
    except StoreError:  # being created
        return False


def test_ctrl_c_in_eval_leaves_no_partial_file(scene, tmp_path, monkeypatch) -> None:
    """Interrupted while writing the plot: ate.json is not left half-updated or alone."""
    est = tmp_path / "est"
    (est / "trajectories").mkdir(parents=True)
    gt = scene / "agent_0" / "groundtruth.txt"
    (est / "trajectories" / "agent_0.txt").write_text(gt.read_text())
    monkeypatch.setattr("como3r.evaluation.report._write_plot", _interrupt)
    result = _invoke("eval", "--est", str(est), "--gt", str(gt))
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 130, result.output
    assert lines[-1] == f"interrupted: nothing was written to {est}"
    assert sorted(p.name for p in est.iterdir()) == ["trajectories"]


def test_ctrl_c_in_weights_fetch_says_the_download_resumes(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("COMO3R_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr("como3r.prior.weights.fetch_file", _interrupt)
    result = _invoke("weights", "fetch", "--trust-unverified")
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 130, result.output
    assert lines[-1].startswith("interrupted: what was downloaded is kept as <file>.part in ")
    assert "como3r weights fetch" in lines[-1]


def test_python_m_como3r_cli_runs() -> None:
    """The module entry point imports without a cycle (cli and cli_weights)."""
    child = subprocess.run(
        [sys.executable, "-m", "como3r.cli", "--help"], capture_output=True, text=True, timeout=120
    )
    assert child.returncode == 0, child.stderr
    assert "weights" in child.stdout
