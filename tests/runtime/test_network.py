"""``como3r coordinator`` and ``como3r agent`` as separate processes over Zenoh on loopback
TCP: the same result as one process, garbage dropped, a coordinator frozen past the lease
losing nothing, a killed agent seen leaving and rejoining when restarted."""

from __future__ import annotations

import json
import os
import re
import signal
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.transport import codec
from como3r.transport.messages import AgentStarted
from como3r.transport.zenoh_protocol import BYE, PIECE, STREAM, Keys, ZenohOptions, open_session

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]

zenoh = pytest.importorskip("zenoh")

#: what a user would pass for a tiny run: 64x48 images
SIZE = ["--set", "input.long_side=64"]
LIMIT_S = 240  # no process of a test outlives this


@pytest.fixture(scope="module")
def scene(tiny_scene) -> Path:
    """Two agents that meet (as in test_processes), 12 frames each."""
    return tiny_scene(frames=12, seed=0, overlap=0.5)


@pytest.fixture(scope="module")
def longer_scene(tiny_scene) -> Path:
    """The same kind of scene, 24 frames per agent (12 processed): tracking that outlasts a
    short freeze."""
    return tiny_scene(frames=24, seed=0, overlap=0.5)


def _watcher(team):
    """A Zenoh session of the test's own on the team's network."""
    return open_session(ZenohOptions(connect=(team.endpoint,), session=team.session))


def _wait_for_coordinator(session, keys: Keys) -> None:
    deadline = time.monotonic() + LIMIT_S
    while not any(
        r.ok is not None for r in session.liveliness().get(keys.coordinator(), timeout=1.0)
    ):
        assert time.monotonic() < deadline, "the coordinator never came up"
        time.sleep(0.2)


def _merged_ate(out: Path) -> float:
    return json.loads((out / "metrics.json").read_text())["ate"]["merged"]["ate"]["rmse"]


def test_coordinator_and_two_agents_over_tcp_match_the_single_process_run(
    scene, free_running, tmp_path
) -> None:
    """The networked run is the session's ``free_running`` one (conftest.py), of this
    module's scene."""
    agents = [scene / "agent_0", scene / "agent_1"]
    single = tmp_path / "single"
    result = CliRunner().invoke(
        app,
        [
            "run",
            "--agent",
            str(agents[0]),
            "--agent",
            str(agents[1]),
            "--out",
            str(single),
            "--prior",
            "simulated",
            *SIZE,
            "--single-process",
            "--quiet",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "the coordinator has every message" in free_running.logs["agent0"]
    metrics = json.loads((free_running.out / "metrics.json").read_text())
    runtime = metrics["runtime"]
    assert runtime["transport"] == "zenoh" and runtime["failed_agents"] == []
    assert metrics["components"] == [[0, 1]]  # the agents met
    for entry, row in zip(runtime["agents"], metrics["bandwidth"]):
        assert entry["status"] == "finished"
        assert entry["bytes_from_agent"]["KeyframeMessage"] > 0
        # the parts are measured as they travelled (float16 pointmaps): they add up to the
        # keyframe messages' bytes less their framing
        per_message = (
            entry["bytes_from_agent"]["KeyframeMessage"]
            / entry["messages_from_agent"]["KeyframeMessage"]
        )
        assert 0 < per_message - sum(row["keyframe_message_bytes_by_part"].values()) < 1000
    reference, networked = _merged_ate(single), _merged_ate(free_running.out)
    # free-running, the coordinator takes the keyframes in 2-5 batches (the single process
    # in 12) and runs 1-2 in-stream global BAs (5): what an edge is judged at and what the
    # agents track on differ, which the terminal alternation absorbs. Which candidates are
    # verified does not: keyframes go by (timestamp, agent) and a batch is verified in that
    # order, as one at a time (the single process takes a self-calibrated camera's first
    # keyframes as it releases them: their candidates differ, all rejected here; a batch verified newest first gave agent 1's keyframe 5 a
    # third cross-agent hit in place of its loop candidate when the merge fell in the same
    # batch: 10 edges, 13.66 mm, in 3 of 6 runs). Measured 15.297-15.411 mm in 6 runs at
    # load 7-15 against 15.408 mm single-process (0.7 % at most)
    assert abs(networked - reference) <= 0.03 * reference, (networked, reference)


def test_malformed_and_oversized_messages_are_logged_and_dropped(scene, team, tmp_path) -> None:
    team.coordinator(tmp_path / "out", 1, "--max-message-mb", "1")
    keys = Keys(team.session)
    session = _watcher(team)
    try:
        _wait_for_coordinator(session, keys)
        valid = codec.encode(AgentStarted(agent=0, pid=1, frames=6))
        wrong_version = valid.replace(b"\xa7version\x01", b"\xa7version\x07")
        assert wrong_version != valid
        seq0 = STREAM.pack(12345, 0, 0, 0.0)
        for key, payload, attachment in [
            (keys.up(0, "KeyframeMessage"), b"\x00garbage", seq0),
            (keys.up(0, "KeyframeMessage"), os.urandom(4096), None),  # no sequence number
            (keys.up(0, "KeyframeMessage"), b"\x92" * (1100 * 1024), seq0),  # over the cap
            (keys.up(0, "AgentStarted"), wrong_version, seq0),
            (keys.up(7, "AgentStarted"), valid, seq0),  # no agent 7 in this run
            (keys.up("x", "AgentStarted"), valid, seq0),
            (
                keys.up(0, "AgentStarted"),
                codec.encode(AgentStarted(agent=3, pid=1, frames=6)),
                seq0,
            ),  # agent 0's key, agent 3's message: must not claim agent 0's stream
        ]:
            # BLOCK as the transport does: the default (DROP) loses puts behind the 1.1 MB one
            # when the machine is busy
            session.put(
                key,
                payload,
                attachment=attachment,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
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
    for fragment in (
        "malformed msgpack",
        "no sequence number",
        "exceeds the cap",
        "version 7",
        "unknown agent '7'",
        "unknown agent 'x'",
        "an AgentStarted of agent 3",
    ):
        assert fragment in log, fragment
    runtime = json.loads((tmp_path / "out" / "metrics.json").read_text())["runtime"]
    assert runtime["agents"][0]["status"] == "finished"


class _Watch:
    """What the test's own Zenoh session sees of a team: each agent's messages by
    (incarnation, seq) with the time first seen, and liveliness changes with their times."""

    def __init__(self, team) -> None:
        self.keys, self.session = Keys(team.session), _watcher(team)
        self.first_seen: dict[tuple[str, int, int, int], float] = {}  # kind, agent, inc., seq
        self.frames: dict[int, list[int]] = {}  # agent -> FrameDone frame indices, in order
        self.tokens: list[tuple[float, str, bool]] = []  # (time, key, present)
        self.lock = threading.Lock()
        _wait_for_coordinator(self.session, self.keys)
        liveliness = self.session.liveliness()
        self.entities = [
            self.session.declare_subscriber(self.keys.up("*", "*"), self._on_message),
            liveliness.declare_subscriber(self.keys.alive("*", "*"), self._on_token),
            liveliness.declare_subscriber(self.keys.coordinator(), self._on_token),
        ]

    def _on_message(self, sample) -> None:
        key = str(sample.key_expr)
        kind, agent = key.rsplit("/", 1)[-1], int(self.keys.agent_of(key))
        if kind == BYE:  # the agent leaves: no message of its stream
            return
        attachment = sample.attachment.to_bytes()
        incarnation, seq = struct.unpack("<QQ", attachment[:16])
        if len(attachment) == PIECE.size:  # a piece of a large message: counted at its last
            _, _, index, pieces, *_ = PIECE.unpack(attachment)
            if index + 1 < pieces:
                return
        with self.lock:
            if (kind, agent, incarnation, seq) in self.first_seen:
                return  # sent again after a reconnect
            self.first_seen[kind, agent, incarnation, seq] = time.monotonic()
            if kind == "FrameDone":
                message = codec.decode(sample.payload.to_bytes())
                self.frames.setdefault(agent, []).append(message.frame_index)

    def _on_token(self, sample) -> None:
        with self.lock:
            self.tokens.append(
                (time.monotonic(), str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            )

    def count(self, kind: str, agent: int) -> int:
        with self.lock:
            return sum(1 for k, a, *_ in self.first_seen if k == kind and a == agent)

    def until(self, condition, what: str) -> float:
        deadline = time.monotonic() + LIMIT_S
        while not condition():
            assert time.monotonic() < deadline, what
            time.sleep(0.01)
        return time.monotonic()

    def token_change(self, after: float, fragment: str, present: bool) -> float | None:
        with self.lock:
            return next(
                (t for t, key, p in self.tokens if t >= after and fragment in key and p == present),
                None,
            )

    def close(self) -> None:
        for entity in self.entities:
            entity.undeclare()
        self.session.close()


def _runtime(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def test_a_frozen_coordinator_loses_nothing(longer_scene, team, tmp_path) -> None:
    """SIGSTOP the coordinator for longer than its Zenoh lease while the agents track: they
    see it go, track on, keep their messages, re-send them when it is back, and every
    keyframe each agent made reaches the outputs. The coordinator announces a 1 s lease
    (Zenoh's default is 10 s) so that the agents are still tracking when they notice."""
    out, lease_s = tmp_path / "out", 1.0
    zenoh_config = tmp_path / "lease.json5"
    zenoh_config.write_text(
        f"{{ transport: {{ link: {{ tx: {{ lease: {lease_s * 1000:.0f} }} }} }} }}"
    )
    team.coordinator(out, 2, "--zenoh-config", str(zenoh_config))
    watch = _Watch(team)
    try:
        for agent in (0, 1):
            team.agent(agent, longer_scene / f"agent_{agent}")
        watch.until(
            lambda: watch.count("FrameDone", 0) >= 1 and watch.count("FrameDone", 1) >= 1,
            "the agents never got going",
        )
        coordinator = team.processes["coordinator"]
        os.kill(coordinator.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        time.sleep(4 * lease_s)  # past the lease: every link to it expires
        os.kill(coordinator.pid, signal.SIGCONT)
        resumed = time.monotonic()
        gone = watch.token_change(stopped, "coordinator", False)
        # a coordinator the watcher never saw go never comes "back" either: fail now, not
        # after the whole LIMIT_S (seen once, under load, outside CI)
        assert gone is not None, "the watcher saw no liveliness drop while it was frozen"
        back = watch.until(
            lambda: watch.token_change(resumed, "coordinator", True),
            "the coordinator never came back",
        )
        for name in ("agent0", "agent1", "coordinator"):
            team.wait(name)
        done = time.monotonic()
    finally:
        watch.close()
    print(
        f"coordinator frozen {resumed - stopped:.1f} s: seen gone {gone - stopped:.2f} s "
        f"after SIGSTOP, back {back - resumed:.2f} s after SIGCONT, run finished "
        f"{done - resumed:.1f} s later"
    )
    assert 0.5 * lease_s < gone - stopped < 4 * lease_s  # on the lease
    metrics = _runtime(out)
    for agent in (0, 1):
        log = team.log(f"agent{agent}")
        assert "the coordinator is gone; tracking on" in log, log
        made_away = [int(n) for n in re.findall(r"(\d+) of them made while it was away", log)]
        assert made_away and made_away[0] > 0, log  # it tracked on while the coordinator was away
        entry = metrics["runtime"]["agents"][agent]
        assert entry["status"] == "finished", entry
        # the agents' own logs above show they saw it go; whether the coordinator, frozen,
        # saw their links drop before they rejoined is a race (in the full suite under load
        # it did not, twice), so its count is only bounded: never restarted, away at most once
        assert entry["times_away"] <= 1 and entry["restarts"] == 0
        assert entry["frames_done"] == entry["frames_expected"] == 12  # 24, subsampled
        # every keyframe the agent made (its own count) was stored, and the test saw as many
        assert entry["keyframes_received"] == metrics["agents"][agent]["keyframes"]
        assert entry["keyframes_received"] == watch.count("KeyframeMessage", agent)
        assert entry["keyframes_received"] >= 2
    # the coordinator logs an agent's return only where it saw the agent go: the race above
    # (its "is back after" asserted unconditionally failed the suite once, both counts 0)
    away = [metrics["runtime"]["agents"][agent]["times_away"] for agent in (0, 1)]
    assert ("is back after" in team.log("coordinator")) == any(away), away


def test_a_killed_agent_restarted_with_its_id_rejoins(longer_scene, team, tmp_path) -> None:
    """kill -9 of an agent mid-run is seen at once (its liveliness token); the agent is away,
    not failed; the same command started again takes over its id after the last frame the
    coordinator heard of, and the run finishes with that agent's frames."""
    out = tmp_path / "out"
    agents = [longer_scene / "agent_0", longer_scene / "agent_1"]
    team.coordinator(out, 2, "--gt", str(agents[0]), "--gt", str(agents[1]))
    watch = _Watch(team)
    try:
        team.agent(0, agents[0])
        victim = team.agent(1, agents[1])
        # its first keyframes leave it once its camera has settled on their pairs; killed
        # after the frame that sent them has reported (the coordinator resumes after it)
        watch.until(lambda: watch.count("KeyframeMessage", 1) >= 1, "agent 1 never got going")
        reported = watch.count("FrameDone", 1)
        watch.until(lambda: watch.count("FrameDone", 1) > reported, "agent 1 stopped")
        os.kill(victim.pid, signal.SIGKILL)
        killed = time.monotonic()
        left = watch.until(
            lambda: watch.token_change(killed, "agent/1/alive", False),
            "the killed agent's token never went",
        )
        victim.wait()
        restarted = time.monotonic()
        team.agent(1, agents[1])  # the same command again
        joined = watch.until(
            lambda: watch.token_change(restarted, "agent/1/alive", True),
            "the restarted agent never joined",
        )
        for name in ("agent0", "agent1", "coordinator"):
            team.wait(name)
    finally:
        watch.close()
    print(
        f"killed agent seen leaving after {(left - killed) * 1000:.0f} ms; restarted "
        f"process joined {joined - restarted:.1f} s after its start"
    )
    assert left - killed < 5.0
    metrics = _runtime(out)
    entry = metrics["runtime"]["agents"][1]
    assert entry["status"] == "finished" and entry["restarts"] == 1, entry
    first, second = entry["map_segments"]
    resumed_after = second["after_frame"]
    assert first["after_frame"] == -1 and resumed_after >= 2 and second["keyframes"] >= 1
    frames = watch.frames[1]  # FrameDone of both processes, as first seen
    before = [f for f in frames if f <= resumed_after]
    after = frames[len(before) :]
    assert after == [f for f in range(0, 24, 2) if f > resumed_after], frames  # it continued
    assert entry["frames_done"] == entry["frames_expected"] == len(before) + len(after) == 12
    log = team.log("coordinator")
    assert "a new process takes over its id" in log, log
    # the run finished with that agent's frames: all of the new process's, in the shared map
    assert first["in_outputs"] and second["in_outputs"], entry
    assert metrics["components"] == [[0, 1]]
    # its trajectory: the keyframes of the killed process, every frame the new one tracked
    lost = metrics["agents"][1]["lost_frames"]
    stamps = np.loadtxt(out / "trajectories" / "agent_1.txt", ndmin=2)[:, 0]
    assert len(stamps) == first["keyframes"] + len([f for f in after if f not in lost])
    assert len(after) >= 6 and len(lost) <= 1 and np.all(np.diff(stamps) > 0)
    print(
        f"agent 1: {len(before)} frames before the kill, {len(after)} after the restart; "
        f"merged ATE {metrics['ate']['merged']['ate']['rmse']:.4f} m"
    )


def test_an_agent_under_max_mbps_stays_under_it_and_reports_its_backlog(
    scene, team, tmp_path
) -> None:
    """One agent at 0.25 Mbit/s on loopback: every keyframe arrives, what it puts stays under
    the rate over the run (as the test's own subscriber sees the pieces), and the agent and
    metrics.json report its send backlog.

    The rate is what makes a backlog certain: the run's messages (about 40 kB each, 230 kB
    in all) take over 5 s at it, and the agent makes them in about 2 s (at 4 Mbit/s a loaded
    machine made them slower than the link took them, and nothing waited)."""
    from como3r.transport.zenoh_protocol import PIECE_BYTES

    max_mbps = 0.25
    out = tmp_path / "out"
    team.coordinator(out, 1)
    keys, session = Keys(team.session), _watcher(team)
    seen: list[tuple[float, int]] = []
    lock = threading.Lock()

    def on_piece(sample) -> None:
        if str(sample.key_expr).endswith(f"/{BYE}"):  # leaving, after the stream
            return
        with lock:
            seen.append((time.monotonic(), len(sample.payload)))

    subscriber = session.declare_subscriber(keys.up("*", "*"), on_piece)
    try:
        _wait_for_coordinator(session, keys)
        team.agent(0, scene / "agent_0", "--max-mbps", str(max_mbps))
        team.wait("agent0")
        team.wait("coordinator")
    finally:
        subscriber.undeclare()
        session.close()
    metrics = json.loads((out / "metrics.json").read_text())
    [entry], [row] = metrics["runtime"]["agents"], metrics["bandwidth"]
    assert entry["status"] == "finished"
    assert entry["keyframes_received"] == metrics["agents"][0]["keyframes"] >= 2
    put = sum(size for _, size in seen)
    assert put >= sum(entry["bytes_from_agent"].values())  # every piece was seen
    span = seen[-1][0] - seen[0][0]
    rate = max_mbps * 1e6 / 8
    print(f"{max_mbps} Mbit/s: {put} bytes put in {span:.1f} s, backlog {row['send_backlog']}")
    assert put <= 2 * PIECE_BYTES + 1.1 * rate * span, (put, span)
    backlog = row["send_backlog"]
    assert backlog["max_mbps"] == max_mbps and backlog["last_bytes"] == 0
    assert 0 < backlog["peak_bytes"] < put and backlog["peak_s"] == backlog["peak_bytes"] / rate
    log = team.log("agent0")
    assert re.search(r"the coordinator has every message; sent [\d.]+ MB, the longest", log), log
