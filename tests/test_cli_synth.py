"""``como3r synth``: the odometry option (decentralized mode inputs)."""

from __future__ import annotations

from typer.testing import CliRunner

from como3r.cli import app
from como3r.io.tum import read_tum


def test_unknown_odometry_model_is_one_error_and_no_folder(tmp_path) -> None:
    out = tmp_path / "scene"
    result = CliRunner().invoke(app, ["synth", "--out", str(out), "--odometry", "bogus"])
    assert result.exit_code == 2
    assert [line for line in result.output.splitlines() if line.startswith("error:")] == [
        "error: unknown --odometry 'bogus'; choose none or one of lio, vio"]
    assert not out.exists()


def test_odometry_is_written_per_agent_and_can_be_switched_off(tmp_path) -> None:
    common = ["--agents", "2", "--frames", "4", "--width", "32", "--height", "24"]
    with_odometry, without = tmp_path / "a", tmp_path / "b"
    assert CliRunner().invoke(app, ["synth", "--out", str(with_odometry), *common]).exit_code == 0
    assert CliRunner().invoke(app, ["synth", "--out", str(without), "--odometry", "none",
                                    *common]).exit_code == 0
    for agent in (0, 1):
        odometry = read_tum(with_odometry / f"agent_{agent}" / "odometry.txt")
        assert len(odometry) == 4
        assert not (without / f"agent_{agent}" / "odometry.txt").exists()
