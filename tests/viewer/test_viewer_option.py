"""``--viewer``: its values, and the one error line without the extra (no rerun needed)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.cli_viewer import join_save_file
from como3r.errors import InputError
from como3r.viewer import INSTALL, ViewerSpec, check_viewer, parse_viewer

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")


@pytest.mark.parametrize(
    "args, joined",
    [
        (["--viewer", "save", "a.rrd", "--out", "o"], ["--viewer", "save=a.rrd", "--out", "o"]),
        (["--viewer=save", "a.rrd"], ["--viewer", "save=a.rrd"]),
        (["--viewer", "save", "--out", "o"], ["--viewer", "save", "--out", "o"]),
        (["--viewer", "spawn", "--out", "save"], ["--viewer", "spawn", "--out", "save"]),
        (["--out", "save", "x"], ["--out", "save", "x"]),
    ],
)
def test_save_takes_the_next_word_as_its_file(args, joined) -> None:
    assert join_save_file(args) == joined


def test_parse_viewer() -> None:
    assert parse_viewer("spawn") == ViewerSpec("spawn")
    assert parse_viewer("serve") == ViewerSpec("serve")
    assert parse_viewer("save=run.rrd") == ViewerSpec("save", Path("run.rrd"))
    for value, fragment in (
        ("show", "spawn, serve or save FILE.rrd"),
        ("save", "needs a file"),
        ("save=run.txt", "FILE.rrd"),
        ("serve=x.rrd", "takes no file"),
    ):
        with pytest.raises(InputError, match=fragment):
            parse_viewer(value)


def test_the_recording_goes_outside_the_output_folder(tmp_path) -> None:
    with pytest.raises(InputError, match="outside --out"):
        check_viewer(f"save={tmp_path / 'out' / 'run.rrd'}", tmp_path / "out")
    with pytest.raises(InputError, match="does not exist"):
        check_viewer(f"save={tmp_path / 'nowhere' / 'run.rrd'}", tmp_path / "out")


def test_spawn_needs_a_display_on_linux(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(InputError, match="--viewer serve or save FILE.rrd"):
        check_viewer("spawn", tmp_path / "out")


@pytest.mark.parametrize("command", ["run", "demo"])
def test_without_the_extra_one_error_line_before_any_work(
    command, tmp_path, monkeypatch, only_error_line
) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    agent = tmp_path / "agent"
    agent.mkdir()  # never opened: the viewer is checked first
    out = tmp_path / "out"
    args = (
        ["run", "--agent", str(agent), "--prior", "simulated"]
        if command == "run"
        else ["demo", "--frames", "4"]
    )
    result = CliRunner().invoke(
        app, [*args, "--out", str(out), "--viewer", "save", str(tmp_path / "run.rrd")]
    )
    line = only_error_line(result)
    assert "rerun-sdk, which is not installed" in line and INSTALL in line
    assert not out.exists() and not out.with_name("out.partial").exists()
    assert not (tmp_path / "run.rrd").exists()


def test_decentralized_runs_have_no_viewer(tmp_path, only_error_line) -> None:
    result = CliRunner().invoke(
        app,
        [
            "run",
            "--agent",
            str(tmp_path),
            "--out",
            str(tmp_path / "out"),
            "--mode",
            "decentralized",
            "--viewer",
            "spawn",
        ],
    )
    assert "--mode centralized" in only_error_line(result)
