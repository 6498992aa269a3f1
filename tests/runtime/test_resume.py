"""``como3r run --resume`` (store/resume.py; issue 14 item 2 for como3r run).

A run killed with SIGKILL once its session store holds some keyframes, or interrupted by
Ctrl-C (once or twice) or SIGTERM (runtime/interrupts.py), then run again with ``--resume``,
ends with the outputs of an uninterrupted run; a store that cannot be resumed is one error
line.
"""

from __future__ import annotations

import errno
import json
import multiprocessing
import os
import shlex
import shutil
import signal
import sqlite3
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import StoreError
from como3r.store.reader import read_session
from como3r.store.schema import FORMAT_VERSION, STORE_NAME

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]

# keyframes go to the coordinator one at a time (no batches): the kills and signals below
# count the keyframes stored and the coordinator's add_keyframe calls
RUN = [
    "--prior",
    "simulated",
    "--set",
    "input.long_side=64",
    "--set",
    "global_ba.max_batch_keyframes=1",
    "-q",
]


@pytest.fixture(scope="module")
def scene(tiny_scene) -> Path:
    return tiny_scene(frames=8, seed=1, overlap=0.2)


def _args(scene: Path, out: Path, *extra: str) -> list[str]:
    return [
        "run",
        "--agent",
        str(scene / "agent_0"),
        "--agent",
        str(scene / "agent_1"),
        "--out",
        str(out),
        *RUN,
        *extra,
    ]


def _extra(runtime: str) -> list[str]:
    return ["--single-process"] if runtime == "single-process" else []


@pytest.fixture(scope="module")
def reference_run(scene, tmp_path_factory) -> Callable[[str], Path]:
    """``reference_run(runtime)``: the output folder of an uninterrupted run of ``runtime``,
    made once for the module (never changed: a test that resumes from it copies it). Not a
    parametrized module fixture: the tests parametrize ``uninterrupted`` indirectly, each
    with its own values, and pytest would make such a fixture again for each of them."""
    made: dict[str, Path] = {}

    def get(runtime: str) -> Path:
        if runtime not in made:
            out = tmp_path_factory.mktemp("reference") / "run"
            result = CliRunner().invoke(app, _args(scene, out, *_extra(runtime)))
            assert result.exit_code == 0, result.output
            made[runtime] = out
        return made[runtime]

    return get


@pytest.fixture(params=["processes", "single-process"])
def uninterrupted(request, reference_run) -> tuple[str, dict]:
    """A runtime and the metrics of its uninterrupted run (free-running agent processes
    differ from the single-process schedule: updates reach the agents later)."""
    out = reference_run(request.param)
    return request.param, json.loads((out / "metrics.json").read_text())


def _kill_when_stored(args: list[str], store: Path, keyframes: int) -> int:
    """Run ``como3r`` with ``args`` in a process and SIGKILL it once ``store`` holds at least
    ``keyframes`` keyframes; returns how many it holds. The process is a fork of this one
    (a new interpreter would spend seconds importing torch before the run started)."""
    process = multiprocessing.get_context("fork").Process(  # not a daemon: it starts agents
        target=app, args=(args,), kwargs={"prog_name": "como3r"}
    )
    process.start()
    deadline = time.monotonic() + 300
    try:
        while process.is_alive() and time.monotonic() < deadline:
            if store.exists():
                try:  # paged: a full read, every 0.2 s, takes 3.5 times the CPU
                    held = len(read_session(store, paged=True).graph)
                except StoreError:  # not created yet
                    held = 0
                if held >= keyframes:
                    os.kill(process.pid, signal.SIGKILL)
                    break
            time.sleep(0.2)
    finally:
        process.kill()
        process.join()
    assert process.exitcode == -signal.SIGKILL, "the run ended before it was killed"
    return len(read_session(store).graph)


def _merged_ate(metrics: dict) -> float:
    [merged] = metrics["ate"]["merged_components"]
    return merged["ate"]["rmse"]


def test_a_killed_run_resumes_to_the_uninterrupted_result(scene, tmp_path, uninterrupted) -> None:
    runtime, reference = uninterrupted
    out, extra = tmp_path / "run", _extra(runtime)
    store = tmp_path / "run.partial" / STORE_NAME
    total = reference["coordinator"]["keyframes"]
    held = _kill_when_stored(_args(scene, out, *extra), store, total // 2)
    assert total // 2 <= held < total and not out.exists()
    result = CliRunner().invoke(app, _args(scene, out, *extra, "--resume"))
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coordinator"]["keyframes"] == total  # the stored ones were not re-added
    assert metrics["components"] == reference["components"] == [[0, 1]]
    assert [a["frames"] for a in metrics["agents"]] == [a["frames"] for a in reference["agents"]]
    assert _merged_ate(metrics) == pytest.approx(_merged_ate(reference), rel=0.1)
    session = read_session(out / STORE_NAME)
    assert session.finished and len(session.graph) == total
    print(
        f"{runtime}: killed with {held} of {total} keyframes stored; merged ATE "
        f"{_merged_ate(metrics):.4f} m resumed, {_merged_ate(reference):.4f} m "
        f"uninterrupted"
    )


def _partial_store(finished: Path, tmp_path: Path) -> Path:
    """A copy of a finished run's folder as ``run.partial`` (as a run killed while writing
    its outputs leaves it): a store to resume from."""
    partial = tmp_path / "run.partial"
    shutil.copytree(finished, partial)
    return partial / STORE_NAME


def test_what_cannot_be_resumed_is_one_error_line(
    scene, reference_run, tmp_path, only_error_line
) -> None:
    out = tmp_path / "run"
    line = only_error_line(CliRunner().invoke(app, _args(scene, out, "--resume")))
    assert "nothing to resume" in line
    store = _partial_store(reference_run("single-process"), tmp_path)
    # this --set is the point of the check: a configuration other than the stored one
    line = only_error_line(
        CliRunner().invoke(
            app, _args(scene, out, "--resume", "--set", "depth.alternation_rounds=1")
        )
    )
    assert "depth.alternation_rounds" in line
    line = only_error_line(CliRunner().invoke(app, _args(scene, out, "--resume")))
    assert "finished" in line  # killed while writing its outputs: nothing left to resume
    with sqlite3.connect(store) as db:
        db.execute(f"PRAGMA user_version={FORMAT_VERSION + 1}")
    line = only_error_line(CliRunner().invoke(app, _args(scene, out, "--resume")))
    assert f"format version {FORMAT_VERSION + 1}" in line and "upgrade como3r" in line
    store.write_bytes(store.read_bytes()[:4096])
    line = only_error_line(CliRunner().invoke(app, _args(scene, out, "--resume")))
    assert str(store) in line
    assert store.parent.is_dir() and not out.exists()  # a failed resume keeps the store


# ------------------------------------------------------------------ interrupts are checkpoints


def _signal_at(monkeypatch, call: int, signals: tuple[signal.Signals, ...]) -> None:
    """Send this process ``signals`` as the coordinator is handed its ``call``-th keyframe
    (1-based), before it handles it: a first Ctrl-C or SIGTERM lets it finish that keyframe,
    a second aborts at once, inside it (the store has the keyframes before it)."""
    from como3r.coordination.coordinator import Coordinator

    add_keyframes, calls = Coordinator.add_keyframes, []

    def add_and_signal(self, packets, solve=True):
        calls.append(packets)  # one keyframe each: these runs set max_batch_keyframes=1
        if len(calls) == call:
            for signum in signals:
                os.kill(os.getpid(), signum)
                time.sleep(0.05)  # let the handler run before the next signal
        return add_keyframes(self, packets, solve)

    monkeypatch.setattr(Coordinator, "add_keyframes", add_and_signal)


# SIGTERM with agent processes, the real signal reaching the main process only, is
# tests/test_cli_errors.py::test_an_interrupted_multiprocess_run_keeps_its_store[sigterm]
@pytest.mark.parametrize(
    ("uninterrupted", "signals"),
    [
        ("processes", (signal.SIGINT,)),
        ("processes", (signal.SIGINT, signal.SIGINT)),
        ("single-process", (signal.SIGINT,)),
        ("single-process", (signal.SIGINT, signal.SIGINT)),
        ("single-process", (signal.SIGTERM,)),
    ],
    ids=["processes-ctrl-c", "processes-twice", "single-ctrl-c", "single-twice", "single-sigterm"],
    indirect=["uninterrupted"],
)
def test_an_interrupted_run_keeps_its_store_and_resumes_to_the_uninterrupted_result(
    scene, tmp_path, uninterrupted, signals, monkeypatch
) -> None:
    """Ctrl-C (once or twice) or SIGTERM in the middle of a run leaves ``OUT.partial`` with
    its session store and one line giving the exact command that continues it; that
    command ends with the uninterrupted run's outputs."""
    runtime, reference = uninterrupted
    out, total = tmp_path / "run", reference["coordinator"]["keyframes"]
    args = _args(scene, out, *_extra(runtime))
    monkeypatch.setattr(sys, "argv", ["como3r", *args])  # the command line as typed
    with monkeypatch.context() as patched:
        _signal_at(patched, total // 2, signals)
        result = CliRunner().invoke(app, args)
    assert result.exit_code == 128 + signals[-1], result.output
    partial = tmp_path / "run.partial"
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines[-1] == (
        f"interrupted: the session store in {partial} is kept; continue "
        f"with: {shlex.join(['como3r', *args, '--resume'])}"
    )
    assert "Traceback" not in result.output and not out.exists()
    held = len(read_session(partial / STORE_NAME).graph)
    # a first signal lets the run finish the frame (or message) at hand, which may hand
    # over several keyframes; a second aborts inside the keyframe at hand
    if len(signals) == 2:
        assert held == total // 2 - 1
    else:
        assert total // 2 <= held < total
    line = CliRunner().invoke(app, args).output  # a plain re-run does not delete it
    assert "continue it with --resume" in line and (partial / STORE_NAME).is_file()
    result = CliRunner().invoke(app, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coordinator"]["keyframes"] == total
    assert metrics["components"] == reference["components"]
    assert [a["frames"] for a in metrics["agents"]] == [a["frames"] for a in reference["agents"]]
    assert _merged_ate(metrics) == pytest.approx(_merged_ate(reference), rel=1e-3)
    print(
        f"{runtime}, {'+'.join(s.name for s in signals)} after {held} of {total} "
        f"keyframes: merged ATE {_merged_ate(metrics):.6f} m resumed, "
        f"{_merged_ate(reference):.6f} m uninterrupted"
    )


def test_a_first_ctrl_c_after_the_input_lets_the_outputs_be_written(
    scene, tmp_path, monkeypatch
) -> None:
    """Once every frame is read, what is left is the terminal work: a first Ctrl-C lets it
    finish and the outputs are written."""
    from como3r.coordination.coordinator import Coordinator

    finish = Coordinator.finish

    def signal_and_finish(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        return finish(self, *args, **kwargs)

    monkeypatch.setattr(Coordinator, "finish", signal_and_finish)
    out = tmp_path / "run"
    result = CliRunner().invoke(app, _args(scene, out, "--single-process"))
    assert result.exit_code == 0, result.output
    assert (out / "metrics.json").is_file() and not (tmp_path / "run.partial").exists()


def test_overwrite_replaces_an_interrupted_runs_store(scene, tmp_path, monkeypatch) -> None:
    out = tmp_path / "run"
    args = _args(scene, out, "--single-process")
    with monkeypatch.context() as patched:
        _signal_at(patched, 3, (signal.SIGINT,))
        assert CliRunner().invoke(app, args).exit_code == 130
    assert (tmp_path / "run.partial" / STORE_NAME).is_file()
    result = CliRunner().invoke(app, [*args, "--overwrite"])
    assert result.exit_code == 0, result.output
    assert (out / "metrics.json").is_file() and not (tmp_path / "run.partial").exists()


def test_a_full_disk_keeps_the_store_and_resumes_to_the_uninterrupted_result(
    scene, tmp_path, uninterrupted, monkeypatch
) -> None:
    """SQLite's own "database or disk is full" (the store may not grow past its size at the
    run's half: ``max_page_count``) ends a run as an interrupt does, with one error line
    naming the command that continues it once space is freed."""
    from como3r.store.writer import SessionStore

    runtime, reference = uninterrupted
    out, total = tmp_path / "run", reference["coordinator"]["keyframes"]
    args = _args(scene, out, *_extra(runtime))
    monkeypatch.setattr(sys, "argv", ["como3r", *args])
    record, calls = SessionStore.record, []

    def record_until_full(self, *rest, **kwargs):
        calls.append(None)
        if len(calls) == total // 2:
            pages = self.connection.execute("PRAGMA page_count").fetchone()[0]
            self.connection.execute(f"PRAGMA max_page_count={pages}")
        return record(self, *rest, **kwargs)

    with monkeypatch.context() as patched:
        patched.setattr(SessionStore, "record", record_until_full)
        result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    partial = tmp_path / "run.partial"
    [line] = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert "database or disk is full" in line
    assert line.endswith(
        f"; the session store in {partial} is kept: free some space and "
        f"continue with: {shlex.join(['como3r', *args, '--resume'])}"
    )
    assert 0 < len(read_session(partial / STORE_NAME).graph) < total
    result = CliRunner().invoke(app, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coordinator"]["keyframes"] == total
    assert _merged_ate(metrics) == pytest.approx(_merged_ate(reference), rel=1e-3)


@pytest.mark.parametrize(
    "error",
    [KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")],
    ids=["ctrl-c twice", "full disk"],
)
def test_a_run_stopped_while_writing_its_outputs_leaves_nothing(
    scene, tmp_path, error, monkeypatch
) -> None:
    """Its store took the terminal refinement, which ``run --resume`` does not continue:
    nothing is kept, nothing said to be resumable (as before interrupts were checkpoints)."""

    def stop(*_args, **_kwargs):
        raise error

    monkeypatch.setattr("como3r.runtime.outputs.write_run_files", stop)
    out = tmp_path / "run"
    result = CliRunner().invoke(app, _args(scene, out, "--single-process"))
    lines = [line for line in result.output.splitlines() if line.strip()]
    if isinstance(error, KeyboardInterrupt):
        assert result.exit_code == 130
        assert lines[-1] == f"interrupted: nothing was written to {out}"
    else:
        assert result.exit_code == 2
        assert lines[-1] == "error: No space left on device"
    assert not out.exists() and not (tmp_path / "run.partial").exists()
