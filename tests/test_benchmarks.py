"""Every benchmark script imports, parses its options and is listed in the manual (docs/benchmarks.md).

Benchmarks never gate CI on their numbers; this only keeps them runnable as the package
changes under them (a renamed function or option otherwise surfaces when somebody needs the
table).
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the scripts; ``_name.py`` modules are what several of them import
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))


def test_there_are_benchmarks() -> None:
    assert len(SCRIPTS) >= 10


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_shows_its_help(script: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "argv", [str(script), "--help"])
    monkeypatch.setattr(sys, "path", [str(script.parent), *sys.path])
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(script), run_name="__main__")
    assert stop.value.code == 0
    assert "usage:" in capsys.readouterr().out


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_is_in_the_readme(script: Path) -> None:
    assert f"benchmarks/{script.name}" in (ROOT / "docs" / "benchmarks.md").read_text()


@pytest.mark.slow
def test_prior_statistics_measures_a_tiny_scene(monkeypatch, capsys) -> None:
    script = ROOT / "benchmarks" / "prior_statistics.py"
    monkeypatch.setattr(
        sys,
        "argv",
        [
            str(script),
            "--model",
            "easy",
            "--presets",
            "default",
            "--width",
            "96",
            "--height",
            "72",
            "--frames",
            "8",
            "--pairs",
            "2",
            "--gap",
            "1",
        ],
    )
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "NN<=2px" in out and "no-ray px" in out
    row = next(line.split() for line in out.splitlines() if line.split()[:2] == ["default", "easy"])
    # the easy model's descriptors are a near-oracle: most matches land within 2 px
    assert row[2].endswith("%") and float(row[2].rstrip("%")) > 50.0
