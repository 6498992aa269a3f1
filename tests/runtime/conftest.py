"""Fixtures shared by the runtime's tests: small synthetic scenes, made once per test
session, and a team of ``como3r coordinator`` / ``como3r agent`` processes on loopback TCP, and a
scripted hub."""

from __future__ import annotations

import socket
import subprocess
import sys
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from como3r.data.synth import synthesize

#: what a user would pass for a tiny run of the 64x48 scenes below
SIZE = ["--set", "input.long_side=64"]
LIMIT_S = 240  # no process of a team outlives this


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Callable[..., Path]:
    """``tiny_scene(frames, seed, overlap, agents=2)``: the folder of a synthetic scene of
    the default preset at 64x48 with ``agents`` agents (``agent_<a>``), made on first use."""
    made: dict[tuple, Path] = {}

    def make(frames: int, seed: int, overlap: float, agents: int = 2) -> Path:
        key = (frames, seed, overlap, agents)
        if key not in made:
            root = tmp_path_factory.mktemp(f"scene_f{frames}_s{seed}_a{agents}")
            synthesize(
                root,
                agents=agents,
                seed=seed,
                overlap=overlap,
                frames=frames,
                preset="default",
                width=64,
                height=48,
                progress=None,
            )
            made[key] = root
        return made[key]

    return make


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ZenohTeam:
    """A coordinator and agents as ``python -m como3r.cli`` processes, logs in files (a
    process started again under a name appends to its log)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp, self.port, self.session = tmp, free_port(), f"t{uuid.uuid4().hex[:12]}"
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.processes: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *args: str) -> subprocess.Popen:
        with open(self.tmp / f"{name}.log", "a") as log:
            process = subprocess.Popen(
                [sys.executable, "-m", "como3r.cli", *args, "--session", self.session],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        self.processes[name] = process
        return process

    def coordinator(self, out: Path, agents: int, *extra: str) -> subprocess.Popen:
        return self.start(
            "coordinator",
            "coordinator",
            "--listen",
            self.endpoint,
            "--out",
            str(out),
            "--agents",
            str(agents),
            "--prior",
            "simulated",
            *SIZE,
            *extra,
        )

    def agent(self, agent: int, path: Path, *extra: str) -> subprocess.Popen:
        return self.start(
            f"agent{agent}",
            "agent",
            "--connect",
            self.endpoint,
            "--id",
            str(agent),
            str(path),
            "--prior",
            "simulated",
            *extra,
        )

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
def new_team(tmp_path) -> Callable[[str], ZenohTeam]:
    """``new_team(name)``: a :class:`ZenohTeam` of its own (port, session, logs in
    ``tmp_path / name``); every team's processes are killed at the end of the test."""
    teams: list[ZenohTeam] = []

    def make(name: str) -> ZenohTeam:
        folder = tmp_path / name
        folder.mkdir(exist_ok=True)
        teams.append(ZenohTeam(folder))
        return teams[-1]

    yield make
    for made in teams:
        made.close()


@dataclass(frozen=True)
class TeamRun:
    """A finished run of a :class:`ZenohTeam`: its output folder and each process's log."""

    out: Path
    logs: dict[str, str]


@pytest.fixture(scope="session")
def free_running(tiny_scene, made_once) -> TeamRun:
    """``como3r coordinator`` (``--gt`` of both agents) and two ``como3r agent`` processes
    on loopback TCP, free-running and uninterrupted, on ``tiny_scene(12, 0, 0.5)``: the
    networked run that test_network.py's TCP test compares with one process and
    test_runtime_state.py's killed coordinator with its resumed run, made once per session
    (:func:`made_once`; a team run is about 16 s of CPU)."""
    scene = tiny_scene(frames=12, seed=0, overlap=0.5)
    agents = [scene / "agent_0", scene / "agent_1"]
    names = ("coordinator", "agent0", "agent1")

    def make(folder: Path) -> None:
        team = ZenohTeam(folder)
        try:
            team.coordinator(folder / "out", 2, "--gt", str(agents[0]), "--gt", str(agents[1]))
            for a, path in enumerate(agents):
                team.agent(a, path)
            for name in names:
                team.wait(name)
        finally:
            team.close()

    folder = made_once("free_running", make)
    return TeamRun(folder / "out", {name: (folder / f"{name}.log").read_text() for name in names})


@pytest.fixture
def team(new_team) -> ZenohTeam:
    """A :class:`ZenohTeam` logging in the test's ``tmp_path``."""
    return new_team("")


class ScriptedHub:
    """A hub whose events a test hands over (``script``); it records what the runtime sends
    and which agents it drops (a coordinator's transport without processes)."""

    name = "scripted"

    def __init__(self) -> None:
        self.script: list = []
        self.sent: list = []
        self.dropped: list[int] = []

    def start(self, tasks, rejoin) -> None:
        self.tasks = list(tasks)

    def events(self, timeout: float) -> list:
        events, self.script = self.script, []
        return events

    def durable(self, held) -> dict:
        return {}

    def acknowledge(self, held) -> None:
        pass

    def send(self, agent: int, message) -> None:
        self.sent.append((agent, message))

    def drop(self, agent: int) -> None:
        self.dropped.append(agent)


@pytest.fixture
def scripted_hub() -> ScriptedHub:
    return ScriptedHub()
