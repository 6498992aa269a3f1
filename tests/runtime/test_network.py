"""``como3r coordinator`` and ``como3r agent`` as separate processes over Zenoh on loopback
TCP: the same result as one process, garbage dropped, a killed agent seen leaving."""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.runtime import codec
from como3r.runtime.messages import AgentStarted
from como3r.runtime.transport_zenoh import Keys, ZenohOptions, open_session

zenoh = pytest.importorskip("zenoh")

#: what a user would pass for a tiny run: 64x48 images, 12 frames per agent
SIZE = ["--set", "input.long_side=64"]
LIMIT_S = 240  # no process of a test outlives this


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """Two agents that meet (as in test_processes)."""
    root = tmp_path_factory.mktemp("scene")
    synthesize(root, agents=2, seed=0, overlap=0.5, frames=12, preset="default", width=64,
               height=48, progress=None)
    return root


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Team:
    """A coordinator and agents as ``python -m como3r.cli`` processes, logs in files."""

    def __init__(self, tmp: Path) -> None:
        self.tmp, self.port, self.session = tmp, _free_port(), f"t{uuid.uuid4().hex[:12]}"
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.processes: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *args: str) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "w")
        process = subprocess.Popen([sys.executable, "-m", "como3r.cli", *args,
                                    "--session", self.session],
                                   stdout=log, stderr=subprocess.STDOUT)
        log.close()
        self.processes[name] = process
        return process

    def coordinator(self, out: Path, agents: int, *extra: str) -> subprocess.Popen:
        return self.start("coordinator", "coordinator", "--listen", self.endpoint, "--out",
                          str(out), "--agents", str(agents), "--prior", "simulated", *SIZE,
                          *extra)

    def agent(self, agent: int, path: Path) -> subprocess.Popen:
        return self.start(f"agent{agent}", "agent", "--connect", self.endpoint, "--id",
                          str(agent), str(path), "--prior", "simulated")

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text()

    def wait(self, name: str) -> int:
        code = self.processes[name].wait(LIMIT_S)
        assert code == 0, self.log(name)
        return code

    def close(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.kill()
                process.wait()


@pytest.fixture
def team(tmp_path):
    team = _Team(tmp_path)
    yield team
    team.close()


def _watcher(team: _Team):
    """A Zenoh session of the test's own on the team's network."""
    return open_session(ZenohOptions(connect=(team.endpoint,), session=team.session))


def _wait_for_coordinator(session, keys: Keys) -> None:
    deadline = time.monotonic() + LIMIT_S
    while not any(r.ok is not None for r in session.liveliness().get(keys.coordinator(),
                                                                        timeout=1.0)):
        assert time.monotonic() < deadline, "the coordinator never came up"
        time.sleep(0.2)


def _merged_ate(out: Path) -> float:
    return json.loads((out / "metrics.json").read_text())["ate"]["merged"]["ate"]["rmse"]


def test_coordinator_and_two_agents_over_tcp_match_the_single_process_run(scene, team,
                                                                          tmp_path) -> None:
    agents = [scene / "agent_0", scene / "agent_1"]
    team.coordinator(tmp_path / "net", 2, "--gt", str(agents[0]), "--gt", str(agents[1]))
    for a, path in enumerate(agents):
        team.agent(a, path)
    single = tmp_path / "single"
    result = CliRunner().invoke(app, ["run", "--agent", str(agents[0]), "--agent",
                                      str(agents[1]), "--out", str(single), "--prior",
                                      "simulated", *SIZE, "--single-process", "--quiet"])
    assert result.exit_code == 0, result.output
    for name in ("coordinator", "agent0", "agent1"):
        team.wait(name)
    assert "the coordinator has every message" in team.log("agent0")
    metrics = json.loads((tmp_path / "net" / "metrics.json").read_text())
    runtime = metrics["runtime"]
    assert runtime["transport"] == "zenoh" and runtime["failed_agents"] == []
    assert metrics["components"] == [[0, 1]]  # the agents met
    for entry in runtime["agents"]:
        assert entry["status"] == "finished"
        assert entry["bytes_from_agent"]["KeyframeMessage"] > 0
    reference, networked = _merged_ate(single), _merged_ate(tmp_path / "net")
    assert abs(networked - reference) <= 0.1 * reference, (networked, reference)


def test_malformed_and_oversized_messages_are_logged_and_dropped(scene, team,
                                                                 tmp_path) -> None:
    team.coordinator(tmp_path / "out", 1, "--max-message-mb", "1")
    keys = Keys(team.session)
    session = _watcher(team)
    try:
        _wait_for_coordinator(session, keys)
        valid = codec.encode(AgentStarted(agent=0, pid=1, frames=6))
        wrong_version = valid.replace(b"\xa7version\x01", b"\xa7version\x07")
        assert wrong_version != valid
        seq0 = struct.pack("<QQ", 12345, 0)
        for key, payload, attachment in [
            (keys.up(0, "KeyframeMessage"), b"\x00garbage", seq0),
            (keys.up(0, "KeyframeMessage"), os.urandom(4096), None),  # no sequence number
            (keys.up(0, "KeyframeMessage"), b"\x92" * (1100 * 1024), seq0),  # over the cap
            (keys.up(0, "AgentStarted"), wrong_version, seq0),
            (keys.up(7, "AgentStarted"), valid, seq0),  # no agent 7 in this run
            (keys.up("x", "AgentStarted"), valid, seq0),
            (keys.up(0, "AgentStarted"), codec.encode(AgentStarted(agent=3, pid=1, frames=6)),
             seq0),  # agent 0's key, agent 3's message: must not claim agent 0's stream
        ]:
            session.put(key, payload, attachment=attachment)
        deadline = time.monotonic() + 60  # the coordinator, still running, logs each
        while team.log("coordinator").count("dropped a message") < 7:
            assert team.processes["coordinator"].poll() is None, team.log("coordinator")
            assert time.monotonic() < deadline, team.log("coordinator")
            time.sleep(0.1)
    finally:
        session.close()
    team.agent(0, scene / "agent_0")  # and then serves a real agent to the end
    team.wait("agent0")
    team.wait("coordinator")
    log = team.log("coordinator")
    assert log.count("dropped a message") == 7, log
    for fragment in ("malformed msgpack", "no sequence number", "exceeds the cap",
                     "version 7", "unknown agent '7'", "unknown agent 'x'",
                     "an AgentStarted of agent 3"):
        assert fragment in log, fragment
    runtime = json.loads((tmp_path / "out" / "metrics.json").read_text())["runtime"]
    assert runtime["agents"][0]["status"] == "finished"


def test_a_killed_agent_is_seen_leaving_and_the_others_finish(scene, team, tmp_path) -> None:
    team.coordinator(tmp_path / "out", 2)
    keys = Keys(team.session)
    session = _watcher(team)
    started, left = threading.Event(), []
    try:
        _wait_for_coordinator(session, keys)
        watch = [
            session.declare_subscriber(keys.up(1, "FrameDone"), lambda s: started.set()),
            session.liveliness().declare_subscriber(
                keys.agent(1), lambda s: left.append(time.monotonic())
                if s.kind == zenoh.SampleKind.DELETE else None),
        ]
        team.agent(0, scene / "agent_0")
        victim = team.agent(1, scene / "agent_1")
        assert started.wait(LIMIT_S), team.log("agent1")
        os.kill(victim.pid, signal.SIGKILL)
        killed = time.monotonic()
        while not left and time.monotonic() - killed < 30:
            time.sleep(0.01)
        assert left, "the killed agent's liveliness token never went"
        detected = left[0] - killed
        print(f"killed agent seen leaving after {detected * 1000:.0f} ms")
        assert detected < 5.0
        for entity in watch:
            entity.undeclare()
    finally:
        session.close()
    team.wait("agent0")
    team.wait("coordinator")
    runtime = json.loads((tmp_path / "out" / "metrics.json").read_text())["runtime"]
    assert [a["status"] for a in runtime["agents"]] == ["finished", "failed"]
    assert "left" in runtime["agents"][1]["error"]
    assert "agent 1 failed: left" in team.log("coordinator")
