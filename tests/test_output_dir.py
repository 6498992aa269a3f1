"""Output folders (como3r.io.output): ``--overwrite`` replaces only what como3r wrote, and
only once the new output is complete."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import InputError
from como3r.io.output import MARKER, atomic_output_dir, is_como3r_output

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

SYNTH = ["synth", "--agents", "1", "--frames", "2", "--width", "32", "--height", "24"]


def _write(out: Path, text: str, overwrite: bool = False) -> None:
    with atomic_output_dir(out, overwrite=overwrite) as staging:
        (staging / "result.txt").write_text(text)


def test_output_carries_the_marker(tmp_path) -> None:
    out = tmp_path / "out"
    _write(out, "first")
    marker = json.loads((out / MARKER).read_text())
    assert set(marker) == {"como3r", "command", "created"}
    assert is_como3r_output(out) and not (tmp_path / "out.partial").exists()


@pytest.mark.parametrize(
    "argv0, program",
    [
        ("/venv/bin/como3r", "como3r"),
        ("/src/como3r/cli.py", "python -m como3r.cli"),
    ],
)
def test_the_marker_gives_the_command_as_typed(tmp_path, monkeypatch, argv0, program) -> None:
    monkeypatch.setattr("sys.argv", [argv0, "run", "--out", "my out"])
    _write(tmp_path / "out", "first")
    marker = json.loads((tmp_path / "out" / MARKER).read_text())
    assert marker["command"] == f"{program} run --out 'my out'"


def test_marked_folder_is_replaced(tmp_path) -> None:
    out = tmp_path / "out"
    _write(out, "first")
    (out / "stale.txt").write_text("from the first run")
    _write(out, "second", overwrite=True)
    assert (out / "result.txt").read_text() == "second"
    assert not (out / "stale.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no .old-<pid>, no .partial


def test_unmarked_folder_is_refused_and_kept(tmp_path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "my_notes.txt").write_text("precious")
    with pytest.raises(InputError, match="not written by como3r; refusing to overwrite"):
        _write(out, "new", overwrite=True)
    assert [p.name for p in out.iterdir()] == ["my_notes.txt"]
    assert not (tmp_path / "mine.partial").exists()


def test_failed_run_leaves_the_old_output_intact(tmp_path) -> None:
    out = tmp_path / "out"
    _write(out, "first")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_output_dir(out, overwrite=True) as staging:
            (staging / "result.txt").write_text("half")
            raise RuntimeError("boom")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_failed_swap_puts_the_old_output_back(tmp_path, monkeypatch) -> None:
    out = tmp_path / "out"
    _write(out, "first")
    real_rename = Path.rename

    def rename(self: Path, target):  # the staging -> out step fails (e.g. a full disk)
        if self.name == "out.partial":
            raise OSError(28, "No space left on device")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", rename)
    with pytest.raises(OSError):
        _write(out, "second", overwrite=True)
    assert (out / "result.txt").read_text() == "first"
    assert not list(tmp_path.glob("out.old-*"))


def test_empty_folder_is_used_without_overwrite(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    _write(out, "first")
    assert (out / "result.txt").read_text() == "first"


def test_staging_folder_left_by_a_killed_run_is_replaced(tmp_path) -> None:
    out = tmp_path / "out"
    leftover = tmp_path / "out.partial"
    leftover.mkdir()
    (leftover / MARKER).write_text("{}")
    (leftover / "half.txt").write_text("")
    _write(out, "first")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "result.txt"]


def test_unmarked_folder_named_like_staging_is_not_deleted(tmp_path) -> None:
    other = tmp_path / "out.partial"
    other.mkdir()
    (other / "data.txt").write_text("mine")
    with pytest.raises(InputError, match="out.partial: not written by como3r"):
        _write(tmp_path / "out", "first")
    assert (other / "data.txt").read_text() == "mine"


def test_cli_overwrite_refuses_an_unrelated_folder(tmp_path) -> None:
    out = tmp_path / "scene"
    out.mkdir()
    (out / "my_notes.txt").write_text("precious")
    result = CliRunner().invoke(app, [*SYNTH, "--out", str(out), "--overwrite"])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert errors == [
        f"error: {out}: not written by como3r; refusing to overwrite (it has no {MARKER} file)"
    ]
    assert (out / "my_notes.txt").read_text() == "precious"


def test_cli_overwrite_replaces_its_own_output(tmp_path) -> None:
    out = tmp_path / "scene"
    assert CliRunner().invoke(app, [*SYNTH, "--out", str(out)]).exit_code == 0
    refused = CliRunner().invoke(app, [*SYNTH, "--out", str(out)])
    assert refused.exit_code == 2 and "--overwrite" in refused.output
    result = CliRunner().invoke(app, [*SYNTH, "--out", str(out), "--overwrite", "--seed", "1"])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "scene.json").read_text())["seed"] == 1


def test_cli_run_refuses_before_any_work(tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "my_notes.txt").write_text("precious")
    result = CliRunner().invoke(
        app,
        [
            "run",
            "--agent",
            str(tmp_path / "no_such_agent"),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--overwrite",
        ],
    )
    assert result.exit_code == 2
    assert "refusing to overwrite" in result.output and "no_such_agent" not in result.output
    assert (out / "my_notes.txt").read_text() == "precious"
