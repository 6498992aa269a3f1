"""Who holds an agent id on the Zenoh transport, in one process over loopback TCP: the
first process to ask gets the task; a second one with the same id waits while the first is
connected, takes over once it is gone (the runtime deciding its task), and from then on only
its messages count; messages to an agent reach only the process they are meant for, and a
replaced process that comes back is told to stop."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import socket
import struct
import threading
import time
import uuid
from collections.abc import Iterator
from types import SimpleNamespace

import pytest

from como3r.config import Config, config_to_dict
from como3r.transport import codec
from como3r.transport.links import Joined, Left, Received, Rejected
from como3r.transport.messages import AgentStarted, AgentTask, Shutdown, Step
from como3r.transport.zenoh_agent import ZenohAgentLink
from como3r.transport.zenoh_hub import ZenohHub
from como3r.transport.zenoh_protocol import STREAM, Keys, ZenohOptions, open_session

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

zenoh = pytest.importorskip("zenoh")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Coordinator(threading.Thread):
    """The coordinator's thread: takes the hub's events and acknowledges, as the runtime."""

    def __init__(self, hub: ZenohHub) -> None:
        super().__init__(daemon=True)
        self.hub, self.events, self.running = hub, [], True

    def run(self) -> None:
        while self.running:
            self.events.extend(self.hub.events(0.05))
            self.hub.acknowledge({})

    def wait_for(self, condition, what: str, limit: float = 30.0) -> None:
        deadline = time.monotonic() + limit
        while not any(condition(e) for e in list(self.events)):
            assert time.monotonic() < deadline, f"{what}: {self.events}"
            time.sleep(0.02)


def _until_stored(link: ZenohAgentLink, limit: float = 10.0) -> None:
    """Wait until the coordinator has acknowledged every message ``link`` sent."""
    deadline = time.monotonic() + limit
    while len(link.spool):
        assert time.monotonic() < deadline, f"{len(link.spool)} message(s) not acknowledged"
        time.sleep(0.02)


def _fetch(link: ZenohAgentLink, out: list) -> threading.Thread:
    thread = threading.Thread(target=lambda: out.append(link.fetch_task()), daemon=True)
    thread.start()
    return thread


@pytest.mark.slow
def test_a_second_process_with_an_id_waits_then_takes_over(caplog) -> None:
    endpoint, keys = f"tcp/127.0.0.1:{_free_port()}", Keys(f"t{uuid.uuid4().hex[:8]}")
    coordinator_session = open_session(ZenohOptions(listen=(endpoint,)))
    hub = ZenohHub(coordinator_session, keys, 1, codec.DEFAULT_MAX_BYTES, 2.0)
    task = AgentTask(
        agent=0, input_path="", config=config_to_dict(Config()), prior={"name": "simulated"}
    )
    asked: list[int] = []

    def rejoin(agent: int) -> AgentTask:
        asked.append(agent)
        return dataclasses.replace(task, resume_after=5)

    hub.start([task], rejoin)
    loop = _Coordinator(hub)
    loop.start()
    sessions = [open_session(ZenohOptions(connect=(endpoint,))) for _ in range(3)]
    try:
        first = ZenohAgentLink(sessions[0], keys, 0)
        assert first.fetch_task().resume_after == -1 and asked == []
        first.send(AgentStarted(agent=0, pid=1, frames=4))
        loop.wait_for(lambda e: isinstance(e, Received), "the first process's message")
        _until_stored(first)

        second = ZenohAgentLink(sessions[1], keys, 0, wait_log_s=0.2)
        got: list[AgentTask] = []
        with caplog.at_level(logging.WARNING):
            fetching = _fetch(second, got)
            time.sleep(1.5)
            assert got == [] and asked == []  # the holder is connected: wait
            assert "another process with id 0" in caplog.text
        hub.send(0, Step(3))
        assert first.poll(5.0) and first.receive() == Step(3)
        assert not second.poll(0.5)  # not meant for it

        sessions[0].close()  # the holder's process is gone (no goodbye)
        fetching.join(30)
        assert [t.resume_after for t in got] == [5] and asked == [0]
        loop.wait_for(lambda e: isinstance(e, Left) and e.may_return, "the holder leaving")
        loop.wait_for(lambda e: isinstance(e, Joined), "the newcomer joining")

        stale = STREAM.pack(first.incarnation, 1, 0, 0.0)  # the old process, late
        sessions[2].put(
            keys.up(0, "AgentStarted"),
            codec.encode(AgentStarted(agent=0, pid=1, frames=4)),
            attachment=stale,
        )
        loop.wait_for(
            lambda e: isinstance(e, Rejected) and "does not hold" in e.error,
            "the old process's message rejected",
        )
        told: list = []  # the old process reconnecting is told to stop, and only it
        listener = sessions[2].declare_subscriber(
            keys.down(0, "*"),
            lambda sample: told.append(
                (sample.attachment.to_bytes(), codec.decode(sample.payload.to_bytes()))
            ),
        )
        token = sessions[2].liveliness().declare_token(keys.alive(0, first.incarnation))
        deadline = time.monotonic() + 10
        while not told:
            assert time.monotonic() < deadline, "the old process was not told"
            time.sleep(0.02)
        [(attachment, message)] = told
        assert attachment == struct.pack("<Q", first.incarnation)
        assert isinstance(message, Shutdown) and "taken over" in message.reason
        assert not second.poll(0.2)
        token.undeclare()
        listener.undeclare()
        second.send(AgentStarted(agent=0, pid=2, frames=2))  # a fresh sequence from 0
        loop.wait_for(
            lambda e: isinstance(e, Received) and e.message.pid == 2, "the newcomer's message"
        )
        second.close()  # returns once stored
    finally:
        loop.running = False
        loop.join(5)
        hub.stop([], interrupted=False)
        hub.close()
        for session in [*sessions[1:], coordinator_session]:
            session.close()


class _Entity:
    def undeclare(self) -> None:
        pass


class _NoCoordinator:
    """A session on which no coordinator answers; its second query ends the wait."""

    class Stop(Exception):
        pass

    def __init__(self) -> None:
        self.queries = 0

    def declare_subscriber(self, *args, **kwargs) -> _Entity:
        return _Entity()

    def declare_token(self, *args, **kwargs) -> _Entity:
        return _Entity()

    def liveliness(self) -> _NoCoordinator:
        return self

    def get(self, *args, **kwargs) -> list:
        self.queries += 1
        if self.queries > 1:
            raise self.Stop
        return []


def test_a_waiting_agent_names_the_endpoints_and_the_session(caplog) -> None:
    options = ZenohOptions(
        connect=("tcp/10.0.0.2:7447",), listen=("tcp/0.0.0.0:7448",), session="lab"
    )
    session = _NoCoordinator()
    link = ZenohAgentLink(session, Keys("lab"), 3, where=options.where())
    try:
        with caplog.at_level(logging.WARNING), pytest.raises(_NoCoordinator.Stop):
            link.fetch_task()
    finally:
        link.close()
    [line] = [r.getMessage() for r in caplog.records if "waiting" in r.getMessage()]
    assert line == (
        "agent 3: waiting: the coordinator (session 'lab', connecting to "
        "tcp/10.0.0.2:7447, listening on tcp/0.0.0.0:7448)"
    )


def test_where_names_scouting_and_the_configuration_file(tmp_path) -> None:
    where = ZenohOptions(scouting=True, config_file=tmp_path / "z.json5").where()
    assert where == (
        f"session 'como3r', scouting by UDP multicast, Zenoh configuration {tmp_path / 'z.json5'}"
    )


@pytest.mark.parametrize(
    "command, module, function, said",
    [
        (
            ["coordinator", "--agents", "3"],
            "como3r.runtime.network",
            "serve",
            "coordinator: waiting for 3 agent(s) (session 'lab', listening on tcp/0.0.0.0:7447)",
        ),
        (
            ["robot", "{tmp}", "--id", "0", "--robots", "2", "--connect", "tcp/10.0.0.2:7447"],
            "como3r.decentralized.robot_node",
            "run_robot",
            "robot 0: waiting for the team of 2 robot(s) (session 'lab', connecting to "
            "tcp/10.0.0.2:7447)",
        ),
    ],
)
def test_a_networked_command_says_where_it_waits(
    tmp_path, monkeypatch, command, module, function, said
) -> None:
    import importlib

    from typer.testing import CliRunner

    from como3r.cli import app
    from como3r.errors import InputError

    def stop(*args, **kwargs):
        raise InputError("stopped before the network")

    monkeypatch.setattr(importlib.import_module(module), function, stop)
    args = [a.replace("{tmp}", str(tmp_path)) for a in command]
    result = CliRunner().invoke(
        app,
        [*args, "--out", str(tmp_path / "out"), "--prior", "simulated", "--session", "lab"],
        env={"COLUMNS": "300"},
    )
    assert result.exit_code == 2, result.output
    assert said in result.output


@pytest.mark.slow
def test_an_agent_under_max_mbps_stays_under_it_and_hears_back_between_its_messages() -> None:
    """1 MB of messages from an agent at 4 Mbit/s (0.5 MB/s) on loopback: every message
    arrives, at no more than the rate over the whole transfer (plus its burst: one piece),
    the coordinator hears how much was queued behind each, and the acknowledgement of the
    first comes back while later ones still wait to be put (not behind them)."""
    from como3r.transport.messages import AgentFailed
    from como3r.transport.zenoh_protocol import PIECE_BYTES

    endpoint, keys = f"tcp/127.0.0.1:{_free_port()}", Keys(f"t{uuid.uuid4().hex[:8]}")
    coordinator_session = open_session(ZenohOptions(listen=(endpoint,)))
    hub = ZenohHub(coordinator_session, keys, 1, codec.DEFAULT_MAX_BYTES, 2.0)
    task = AgentTask(
        agent=0, input_path="", config=config_to_dict(Config()), prior={"name": "simulated"}
    )
    hub.start([task], lambda agent: task)
    loop = _Coordinator(hub)
    loop.start()
    session = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        link = ZenohAgentLink(session, keys, 0, max_mbps=4.0)
        link.fetch_task()
        queued_at_ack: list[int] = []
        acknowledge = link.spool.acknowledge

        def noting(seq: int) -> None:  # the link holds its lock here
            queued_at_ack.append(link._backlog())
            acknowledge(seq)

        link.spool.acknowledge = noting
        messages = [
            AgentFailed(agent=0, error="padding", details=f"{k}" * 200_000) for k in range(5)
        ]
        start = time.monotonic()
        for message in messages:
            link.send(message)
        link.close()  # returns once the coordinator has stored every message
        elapsed = time.monotonic() - start
        received = [e.message for e in loop.events if isinstance(e, Received)]
        assert [m.details[:1] for m in received] == [f"{k}" for k in range(5)]
        sent = link.bytes_put
        assert sent >= 1_000_000
        rate = 4e6 / 8
        assert sent <= rate * elapsed * 1.1 + PIECE_BYTES, (sent, elapsed)
        assert queued_at_ack[0] > 0, queued_at_ack  # acknowledged before the rest was put
        backlog = hub.traffic(0).backlog
        assert backlog is not None and backlog.max_mbps == pytest.approx(4.0)
        assert 600_000 < backlog.peak_bytes < sent and backlog.last_bytes == 0
    finally:
        loop.running = False
        loop.join(5)
        hub.stop([], interrupted=False)
        hub.close()
        session.close()
        coordinator_session.close()


class _DeafLink(ZenohAgentLink):
    """An agent whose acknowledgements are lost (its link cut as they go out) while
    ``deaf``."""

    deaf = True

    def _on_ack(self, sample) -> None:
        if not self.deaf:
            super()._on_ack(sample)


@contextlib.contextmanager
def _loopback_team(agents: int) -> Iterator[tuple[Keys, ZenohHub, _Coordinator, list]]:
    """A hub whose agents ``0 .. agents-1`` may join (asked again: the same task), its
    coordinator's thread running, and a Zenoh session per agent, on loopback TCP; all
    closed afterwards."""
    endpoint, keys = f"tcp/127.0.0.1:{_free_port()}", Keys(f"t{uuid.uuid4().hex[:8]}")
    coordinator_session = open_session(ZenohOptions(listen=(endpoint,)))
    hub = ZenohHub(coordinator_session, keys, agents, codec.DEFAULT_MAX_BYTES, 2.0)
    tasks = [
        AgentTask(agent=a, input_path="", config=config_to_dict(Config()), prior={"name": "x"})
        for a in range(agents)
    ]
    hub.start(tasks, lambda agent: tasks[agent])
    loop = _Coordinator(hub)
    loop.start()
    sessions = [open_session(ZenohOptions(connect=(endpoint,))) for _ in range(agents)]
    try:
        yield keys, hub, loop, sessions
    finally:
        loop.running = False
        loop.join(5)
        hub.close()
        for session in [*sessions, coordinator_session]:
            session.close()


def _stop_the_run(hub: ZenohHub, loop: _Coordinator) -> None:
    """The runtime's end: its thread stops taking events, then the hub stops."""
    loop.running = False
    loop.join(5)
    hub.stop([], interrupted=False)


@pytest.mark.slow
def test_the_coordinator_waits_for_an_agent_that_missed_its_last_acknowledgement() -> None:
    with _loopback_team(2) as (keys, hub, loop, sessions):
        cut, heard = _DeafLink(sessions[0], keys, 0), ZenohAgentLink(sessions[1], keys, 1)
        for link in (cut, heard):
            link.fetch_task()
            link.send(AgentStarted(agent=link.agent, pid=1, frames=2))
        loop.wait_for(
            lambda e: isinstance(e, Received) and e.agent == 0, "agent 0's message", limit=10
        )
        heard.close()  # acknowledged, and says so
        _stop_the_run(hub, loop)
        # agent 0 waits for an acknowledgement it never hears: the coordinator waits for it
        assert hub.linger(1.0) == [0] and len(cut.spool) == 1
        lingering: list[list[int]] = []
        waiting = threading.Thread(target=lambda: lingering.append(hub.linger(60.0)))
        waiting.start()
        # its link is back: it sees the coordinator go and come back, and re-sends
        cut.deaf = False
        cut._on_coordinator(SimpleNamespace(kind=zenoh.SampleKind.DELETE))
        cut._on_coordinator(SimpleNamespace(kind=zenoh.SampleKind.PUT))
        cut.close()  # returns once stored: the re-sent message was acknowledged
        waiting.join(30)
        assert lingering == [[]]  # agent 0 said Bye: no waiting out the 60 s


@pytest.mark.slow
def test_a_message_after_the_run_ended_is_neither_taken_nor_acknowledged(caplog) -> None:
    with _loopback_team(1) as (keys, hub, loop, [session]):
        link = ZenohAgentLink(session, keys, 0)
        link.fetch_task()
        link.send(AgentStarted(agent=0, pid=1, frames=2))
        loop.wait_for(lambda e: isinstance(e, Received), "the message", limit=10)
        _until_stored(link)
        _stop_the_run(hub, loop)
        link.send(AgentStarted(agent=0, pid=1, frames=2))  # too late: the run is over
        with caplog.at_level(logging.WARNING):
            assert hub.linger(1.5) == [0]  # no Bye: it still waits for an acknowledgement
        assert len(link.spool) == 1  # never acknowledged, so never taken for stored
        assert "message 1 came after the run ended" in caplog.text
