"""``como3r synth``: the odometry option (decentralized mode inputs)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from como3r.cli import app
from como3r.io.tum import read_tum


def test_unknown_odometry_model_is_one_error_and_no_folder(tmp_path) -> None:
    out = tmp_path / "scene"
    result = CliRunner().invoke(app, ["synth", "--out", str(out), "--odometry", "bogus"])
    assert result.exit_code == 2
    assert [line for line in result.output.splitlines() if line.startswith("error:")] == [
        "error: unknown --odometry 'bogus'; choose none or one of lio, vio"
    ]
    assert not out.exists()


def test_odometry_is_written_per_agent_and_can_be_switched_off(tmp_path) -> None:
    common = ["--agents", "2", "--frames", "4", "--width", "32", "--height", "24"]
    with_odometry, without = tmp_path / "a", tmp_path / "b"
    assert CliRunner().invoke(app, ["synth", "--out", str(with_odometry), *common]).exit_code == 0
    assert (
        CliRunner()
        .invoke(app, ["synth", "--out", str(without), "--odometry", "none", *common])
        .exit_code
        == 0
    )
    for agent in (0, 1):
        odometry = read_tum(with_odometry / f"agent_{agent}" / "odometry.txt")
        assert len(odometry) == 4
        assert not (without / f"agent_{agent}" / "odometry.txt").exists()


def test_scale_is_validated_and_recorded(tmp_path) -> None:
    common = ["--agents", "1", "--frames", "2", "--width", "32", "--height", "24"]
    bad = tmp_path / "bad"
    result = CliRunner().invoke(app, ["synth", "--out", str(bad), "--scale", "0", *common])
    assert result.exit_code == 2
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "--scale" in errors[0] and not bad.exists()
    street = tmp_path / "street"
    result = CliRunner().invoke(
        app, ["synth", "--out", str(street), "--scale", "5", "--preset", "rotation", *common]
    )
    assert result.exit_code == 0, result.output
    meta = json.loads((street / "scene.json").read_text())
    assert (meta["scale"], meta["preset"]) == (5.0, "rotation")
