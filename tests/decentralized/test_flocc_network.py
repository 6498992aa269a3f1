"""``como3r robot``: the decentralized mode with one process per robot over Zenoh (loopback
TCP), the link filter applied by each receiver. The same mission as the one-process router
gives the same result."""

from __future__ import annotations

import dataclasses
import json
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest
import yaml

from como3r.config import config_to_dict
from como3r.decentralized.protocol import run_protocol
from como3r.decentralized.runner import open_robot
from como3r.decentralized.schedule import read_schedule
from como3r.io.tum import read_tum
from como3r.runtime.pipeline import PriorSpec
from como3r.transport.team import add_member, init_team

pytestmark = pytest.mark.slow

pytest.importorskip("zenoh")

LIMIT_S = 240  # no robot process outlives this
#: robots 0 and 1 meet, then 1 and 2; robots 0 and 2 never do
SCHEDULE = "0,0.0,1.9\n1,0.0,1.9,1.95,3.0\n2,1.95,3.0\n"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_robots(scene, config, tmp, team: Path | None = None) -> list[dict]:
    """Three robot processes on ``scene`` with :data:`SCHEDULE` (``team``: each with its
    member folder ``team/r<K>``); their metrics."""
    (tmp / "config.yaml").write_text(yaml.safe_dump(config_to_dict(config)))
    (tmp / "schedule.csv").write_text(SCHEDULE)
    endpoint, session = f"tcp/127.0.0.1:{_free_port()}", f"t{uuid.uuid4().hex[:12]}"
    processes = []
    for robot in range(3):
        network = ["--listen", endpoint] if robot == 0 else ["--connect", endpoint]
        if team is not None:
            network += ["--team", str(team / f"r{robot}")]
        log = open(tmp / f"robot{robot}.log", "w")
        processes.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "como3r.cli",
                    "robot",
                    str(scene[robot]),
                    "--id",
                    str(robot),
                    "--robots",
                    "3",
                    *network,
                    "--out",
                    str(tmp / f"out{robot}"),
                    "--prior",
                    "simulated",
                    "--config",
                    str(tmp / "config.yaml"),
                    "--schedule",
                    str(tmp / "schedule.csv"),
                    "--session",
                    session,
                    "--quiet",
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
        log.close()
    try:
        codes = [p.wait(LIMIT_S) for p in processes]
    finally:
        for p in processes:
            if p.poll() is None:
                p.kill()
    for robot, code in enumerate(codes):
        assert code == 0, (tmp / f"robot{robot}.log").read_text()
    return [json.loads((tmp / f"out{r}" / "metrics.json").read_text()) for r in range(3)]


def _config(main_config, settings_factory):
    return dataclasses.replace(
        main_config, decentralized=settings_factory(keyframe_distance_ratio=0.45)
    )


@pytest.fixture(scope="module")
def mission(scene, main_config, settings_factory, tmp_path_factory):
    """Three robot processes on the shared scene with :data:`SCHEDULE`; their output folders
    and metrics, and the one-process run of the same mission."""
    tmp = tmp_path_factory.mktemp("robots")
    config = _config(main_config, settings_factory)
    metrics = _run_robots(scene, config, tmp)
    end_s = max(
        float(open_robot(p, config, config.decentralized).odometry.timestamps[-1]) for p in scene
    )
    reference = run_protocol(
        [str(p) for p in scene],
        config,
        config.decentralized,
        PriorSpec("simulated"),
        end_s,
        read_schedule(tmp / "schedule.csv"),
    )
    return tmp, metrics, reference


def test_robots_that_never_meet_exchange_nothing_and_join_one_frame_through_a_third(mission):
    _, metrics, _ = mission
    end = {"round": 1, "time_s": 1.966667, "group": [1, 2]}  # the mission's end
    assert [m["rounds"] for m in metrics] == [
        [{"round": 0, "time_s": 1.9, "group": [0, 1]}],
        [{"round": 0, "time_s": 1.9, "group": [0, 1]}, end],
        [end],
    ]
    peers = [m["bytes"]["by_peer"] for m in metrics]
    assert set(peers[0]) == {"1"} and set(peers[2]) == {"1"} and set(peers[1]) == {"0", "2"}
    assert [m["frame"] for m in metrics] == [0, 0, 0]  # robot 2 through robot 1
    assert all(
        m["bytes"]["dropped_by_link_filter"] == {} and m["bytes"]["invalid"] == 0 for m in metrics
    )


def test_robot_processes_give_the_one_process_result(mission, scene):
    tmp, metrics, reference = mission
    for robot, m in enumerate(metrics):
        report = reference.reports[robot]
        assert m["robots"][0]["error"] == "" and m["frame"] == report.frame
        graph = json.loads((tmp / f"out{robot}" / "graph.json").read_text())
        accepted = [(e["from"], e["to"]) for e in graph["edges"] if e["accepted"]]
        assert accepted == [
            ([l.robot_a, l.keyframe_a], [l.robot_b, l.keyframe_b]) for l in report.loops
        ]
        # the bytes each robot counted are the ones the router delivered, but for the
        # registered keyframes' images: lossless WebP across machines, byte planes and
        # Zstandard between threads
        for way in ("sent", "received"):
            counted = dict(m["bytes"][way])
            delivered = dict(getattr(reference.traffic, way).get(robot, {}))
            assert counted.pop("EncodingReply", 0) <= delivered.pop("EncodingReply", 0)
            assert counted == delivered
        keyframes = read_tum(tmp / f"out{robot}" / "keyframes" / f"agent_{robot}.txt")
        np.testing.assert_allclose(
            keyframes.T_WC[: len(report.estimate)].numpy(), report.estimate, atol=1e-4
        )
        [bandwidth] = m["bandwidth"]
        assert bandwidth["bytes_sent"] == m["bytes"]["sent_total"]
        assert bandwidth["keyframes"] == len(keyframes) and bandwidth["image_bytes"] == 3 * 64 * 96
        trajectory = read_tum(tmp / f"out{robot}" / "trajectories" / f"agent_{robot}.txt")
        assert len(trajectory) == len(read_tum(scene[robot] / "odometry.txt"))
    assert sum(len(r.loops) for r in reference.reports.values()) > 0


def test_a_team_of_robots_gives_the_open_networks_result(
    mission, scene, main_config, settings_factory, tmp_path_factory
):
    """The same mission with --team (mutual TLS, access control, robots 1 and 2 meeting
    through gossip on TLS ports): the same loops, frames and bytes."""
    tmp = tmp_path_factory.mktemp("team_robots")
    init_team(tmp / "team")
    for robot in range(3):
        add_member(tmp / "team", f"r{robot}", "robot", robot)
    metrics = _run_robots(scene, _config(main_config, settings_factory), tmp, tmp / "team")
    open_tmp, open_metrics, _ = mission
    for robot, (m, reference) in enumerate(zip(metrics, open_metrics)):
        assert m["frame"] == reference["frame"] and m["rounds"] == reference["rounds"]
        assert m["bytes"]["sent"] == reference["bytes"]["sent"]
        assert m["bytes"]["received"] == reference["bytes"]["received"]
        assert m["bytes"]["invalid"] == 0
        graphs = [
            json.loads((folder / f"out{robot}" / "graph.json").read_text())
            for folder in (tmp, open_tmp)
        ]
        team_loops, open_loops = ([e for e in g["edges"] if e["accepted"]] for g in graphs)
        assert team_loops == open_loops
        assert "open network" not in (tmp / f"robot{robot}.log").read_text()
