"""A robot's declared odometry kind (decentralized/odometry_kind.py): the file, its
validation, ``como3r synth``'s declaration and the declared start's way to the solver."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.config import Config
from como3r.config_decentralized import DecentralizedConfig
from como3r.decentralized import odometry_kind
from como3r.decentralized.consistency import merged_graph
from como3r.decentralized.messages import PoseEstimate, PoseGraphShare
from como3r.decentralized.odometry_kind import (
    ODOMETRY_KIND_FILE,
    OdometryKind,
    odometry_start,
    read_odometry_kind,
    write_odometry_kind,
)
from como3r.decentralized.pose_graph_problem import OdometryStart
from como3r.decentralized.runner import open_robot, run_decentralized
from como3r.errors import InputError, MessageError
from como3r.runtime.pipeline import PriorSpec
from como3r.transport.codec import decode, encode


def _declare(folder, text: str):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / ODOMETRY_KIND_FILE).write_text(text)
    return folder


def test_a_declaration_is_read_back_as_written(tmp_path):
    assert read_odometry_kind(tmp_path) is None  # undeclared
    for declared in (
        OdometryKind("vio"),
        OdometryKind("metric"),
        OdometryKind("vio", start_scale_error=0.2, start_depths=0.5),
        OdometryKind("vio", start_scale_error=0.0),
    ):
        write_odometry_kind(tmp_path, declared)
        assert read_odometry_kind(tmp_path) == declared


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{", "not readable JSON"),
        ('["vio"]', "must be a JSON object"),
        ("{}", '"kind" must be one of vio, metric'),
        ('{"kind": "lio"}', "LiDAR-inertial, stereo or wheel odometry is metric"),
        ('{"kind": "vio", "start_scale": 0.3}', r"unknown key\(s\) \['start_scale'\]"),
        ('{"kind": "vio", "start_scale_error": -0.1}', "'start_scale_error' must be a finite"),
        ('{"kind": "vio", "start_scale_error": "0.3"}', "'start_scale_error' must be a finite"),
        ('{"kind": "vio", "start_scale_error": NaN}', "'start_scale_error' must be a finite"),
        ('{"kind": "vio", "start_depths": 0}', "'start_depths' must be a finite number > 0"),
        ('{"kind": "vio", "start_depths": true}', "'start_depths' must be a finite"),
        ('{"kind": "metric", "start_scale_error": 0.3}', "applies to kind vio only"),
    ],
)
def test_a_bad_declaration_is_an_input_error_naming_the_file(tmp_path, text, message):
    folder = _declare(tmp_path / "agent", text)
    with pytest.raises(InputError, match=message) as error:
        read_odometry_kind(folder)
    assert str(folder / ODOMETRY_KIND_FILE) in str(error.value)


def test_synth_declares_the_odometry_it_simulates(tmp_path):
    common = ["--agents", "2", "--frames", "3", "--width", "32", "--height", "24"]
    for model, kind in (("vio", "vio"), ("lio", "metric")):
        out = tmp_path / model
        result = CliRunner().invoke(app, ["synth", "--out", str(out), "--odometry", model, *common])
        assert result.exit_code == 0, result.output
        for agent in (0, 1):
            document = json.loads((out / f"agent_{agent}" / ODOMETRY_KIND_FILE).read_text())
            assert document == {"kind": kind}
    result = CliRunner().invoke(
        app, ["synth", "--out", str(tmp_path / "none"), "--odometry", "none", *common]
    )
    assert result.exit_code == 0
    assert not (tmp_path / "none" / "agent_0" / ODOMETRY_KIND_FILE).exists()


def test_a_robot_opens_with_its_declared_start_and_fails_early_on_a_bad_one(
    scene, main_config: Config, tmp_path, caplog
):
    """The conftest scene is declared ``metric`` (``lio``); a copy declared ``vio`` gets the
    configured start, one without a declaration None (said once at info), a bad one an
    InputError before any work."""
    settings = DecentralizedConfig(keyframe_distance_ratio=0.1)
    assert open_robot(scene[0], main_config, settings).start == OdometryStart(0.0, 0.0)
    copy = tmp_path / "agent"
    shutil.copytree(scene[0], copy)
    write_odometry_kind(copy, OdometryKind("vio"))
    assert open_robot(copy, main_config, settings).start == OdometryStart(0.3, pytest.approx(3.0))
    (copy / ODOMETRY_KIND_FILE).unlink()
    with caplog.at_level(logging.INFO, logger="como3r.decentralized.odometry_kind"):
        assert open_robot(copy, main_config, settings).start is None
    assert sum("undeclared" in r.getMessage() for r in caplog.records) == 1
    _declare(copy, '{"kind": "visual"}')
    with pytest.raises(InputError, match="odometry.json"):
        open_robot(copy, main_config, settings)


def test_a_robot_s_declaration_is_read_once_per_mission(
    scene, main_config: Config, settings_factory, tmp_path, monkeypatch
):
    """The driver reads each robot's ``odometry.json`` before the mission and its robot
    thread takes that reading (open_robot's RobotData) instead of reading it again."""
    reads: list = []
    read = odometry_kind.read_odometry_kind

    def counting(folder):
        reads.append(folder)
        return read(folder)

    monkeypatch.setattr(odometry_kind, "read_odometry_kind", counting)
    settings = settings_factory(keyframe_distance_ratio=0.45)
    run_decentralized(scene[:2], tmp_path / "out", main_config, PriorSpec("simulated"), settings)
    assert sorted(reads) == sorted(scene[:2])  # once per robot, not twice


def _share(sender: int, **changes) -> PoseGraphShare:
    fields = dict(
        sender=sender,
        recipient=0,
        round=1,
        time_s=1.0,
        odometry=np.tile([0.0, 0, 0, 0, 0, 0, 1, 1], (3, 1)),
        estimate=np.zeros((0, 8)),
        frame=sender,
        loops=[],
    )
    return PoseGraphShare(**{**fields, **changes})


def test_declared_starts_travel_to_the_solver_with_the_odometry():
    """A share carries its robot's start and those of the robots it relays, across the
    codec; the solver's merged graph has each robot's (robot 3 relayed, robot 1 undeclared),
    and a start of a robot the share does not relay is refused on decode."""
    vio, metric = OdometryStart(0.3, 4.3), OdometryStart()
    relayed = {3: np.tile([0.0, 0, 0, 0, 0, 0, 1, 1], (2, 1))}
    shares = {
        0: _share(0, start=vio),
        1: _share(1),
        2: _share(2, start=metric, relayed=relayed, relayed_starts={3: vio}),
    }
    shares = {r: decode(encode(s)) for r, s in shares.items()}
    assert shares[0].start == vio and shares[1].start is None
    assert merged_graph(shares).starts == {0: vio, 2: metric, 3: vio}
    estimate = PoseEstimate(
        sender=0,
        recipient=1,
        round=1,
        time_s=1.0,
        poses=np.zeros((0, 8)),
        frame=-1,
        relayed=relayed,
        relayed_starts={3: vio},
    )
    assert decode(encode(estimate)).relayed_starts == {3: vio}
    with pytest.raises(MessageError, match="relayed_starts"):
        decode(encode(_share(1, relayed_starts={3: vio})))
    with pytest.raises(MessageError, match="scale_sigma"):
        decode(encode(_share(1, start=OdometryStart(-0.1, 1.0))))
    assert odometry_start(OdometryKind("vio"), DecentralizedConfig()).scale_sigma == 0.3
