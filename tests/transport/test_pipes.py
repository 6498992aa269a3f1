"""The coordinator's end of the agent pipes: each pipe read and decoded on a thread of its
own (transport/pipe_readers.py), what :meth:`PipeHub.events` hands over unchanged: each
agent's messages in order, an ended agent's last messages before its ``Left``, rejections,
unreadable framing, the size cap; bounded read-ahead; no thread outlives ``stop``."""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Iterator
from typing import Any

import pytest
import torch

from como3r.frontend.packets import KeyframePacket
from como3r.runtime import ingest
from como3r.transport import codec
from como3r.transport.links import Event, Left, Received, Rejected
from como3r.transport.messages import FROM_AGENT, FrameDone, KeyframeMessage, Shutdown, Step
from como3r.transport.pipe_readers import PipeReader
from como3r.transport.pipes import Channel, PipeHub

from ..keyframe_packets import mast3r_packet

H, W = 12, 16


class _Process:
    """What the hub asks of an agent's process; its sentinel a pipe that ends as it dies
    (``mortal``: when terminated; else never, as one stuck past the signal)."""

    def __init__(self, mortal: bool = True) -> None:
        self._sentinel, self._alive = multiprocessing.Pipe(duplex=False)
        self.sentinel = self._sentinel.fileno()
        self.exitcode: int | None = None
        self.mortal = mortal

    def die(self, code: int) -> None:
        self.exitcode = code
        self._alive.close()

    def is_alive(self) -> bool:
        return self.exitcode is None

    def terminate(self) -> None:
        if self.is_alive() and self.mortal:
            self.die(-15)

    def join(self, timeout: float | None = None) -> None:
        """Nothing to wait for: it dies when told."""


class _Agent:
    """An agent's end: a coded channel to the hub, its raw pipe, its process."""

    def __init__(self, hub: PipeHub, agent: int, mortal: bool = True) -> None:
        from_agent_r, from_agent_w = multiprocessing.Pipe(duplex=False)
        to_agent_r, to_agent_w = multiprocessing.Pipe(duplex=False)
        self.raw = from_agent_w  # for bytes that are no message (the channel's outbox)
        self.channel = Channel(to_agent_r, from_agent_w, 2**24, accepts=(Shutdown,), coded=True)
        self.process = _Process(mortal)
        _AGENTS.append(self)
        coordinator = Channel(from_agent_r, to_agent_w, hub.max_bytes, FROM_AGENT)
        hub.processes[agent], hub.channels[agent] = self.process, coordinator
        hub.readers[agent] = PipeReader(
            agent, coordinator, self.process.sentinel, hub._wake, hub._bell, hub.read_ahead
        )

    def exit(self, code: int = 0) -> None:
        """Flush and close its pipes, then die (its last messages are in the pipe)."""
        self.channel.close()
        self.process.die(code)


#: the agents' ends a test made (closed after it)
_AGENTS: list[_Agent] = []


def _hub(read_ahead: int = 10_000_000, max_bytes: int = 2**24) -> PipeHub:
    return PipeHub(_no_target, max_bytes, grace_s=5.0, read_ahead=read_ahead)


def _no_target(*args: object) -> None:
    """No process is started here: the tests make their agents' ends."""


@pytest.fixture(autouse=True)
def _close_agents() -> Iterator[None]:
    yield
    while _AGENTS:
        _AGENTS.pop().channel.close(timeout=5.0)


@pytest.fixture
def hub() -> Iterator[PipeHub]:
    made = _hub()
    yield made
    made.stop([], interrupted=True)


def _done(agent: int, frame: int, outcome: str = "tracked") -> FrameDone:
    return FrameDone(
        agent=agent,
        frame_index=frame,
        timestamp=0.1 * frame,
        outcome=outcome,
        seconds=0.0,
        keyframes_waiting=0,
    )


def _until_left(hub: PipeHub, agents: int) -> list[Event]:
    """Every event until ``agents`` agents have left."""
    events: list[Event] = []
    while sum(isinstance(e, Left) for e in events) < agents:
        events += hub.events(5.0)
    return events


def _readers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("como3r-pipe-reader")]


def test_each_agents_messages_in_order_and_its_last_ones_before_it_left(hub) -> None:
    agents = [_Agent(hub, agent) for agent in range(3)]
    for k in range(40):
        for agent, end in enumerate(agents):
            end.channel.send(_done(agent, k, outcome="x" * 5000))  # beyond a pipe's buffer
    for agent, end in enumerate(agents):
        end.exit(code=agent)
    events = _until_left(hub, 3)
    for agent in range(3):
        mine = [e for e in events if e.agent == agent]
        assert [e.message.frame_index for e in mine[:-1]] == list(range(40))
        assert all(isinstance(e, Received) for e in mine[:-1])
        assert mine[-1] == Left(agent, f"process died (exit code {agent})")
    assert hub.events(0.0) == []  # every agent gone: nothing to wait for
    traffic = hub.traffic(1)
    assert traffic.messages_received["FrameDone"] == 40
    assert traffic.bytes_received == agents[1].channel.traffic.bytes_sent


def test_a_keyframe_is_decoded_off_the_coordinators_thread(hub, monkeypatch) -> None:
    """The reader decodes it (its CPU seconds come with it); the coordinator's ingest
    takes it as its agent coded it: the decode's record of the coded maps crosses threads."""
    decoded_on: list[str] = []
    channel_decode = Channel.decode

    def decode(self: Channel, data: bytes) -> tuple[Any, float]:
        decoded_on.append(threading.current_thread().name)
        return channel_decode(self, data)

    monkeypatch.setattr(Channel, "decode", decode)
    agent = _Agent(hub, 0)
    packet = _packet()
    agent.channel.send(KeyframeMessage(packet=packet, applied_seq=0, T_WC_previous=None))
    (event,) = hub.events(5.0)
    assert isinstance(event, Received) and event.seconds > 0.0
    assert decoded_on == ["como3r-pipe-reader-0"]
    assert ingest.coded(event.message.packet)
    assert ingest.received(event.message.packet) is event.message.packet
    assert torch.equal(event.message.packet.T_WC, packet.T_WC)


def test_a_bad_message_is_rejected_and_the_agent_goes_on(hub) -> None:
    agent = _Agent(hub, 0)
    agent.channel.send(Step(frame_index=3))  # not a message the coordinator accepts
    agent.channel.send(_done(0, 1))
    events: list[Event] = []
    while len(events) < 2:
        events += hub.events(5.0)
    assert isinstance(events[0], Rejected) and "Step" in events[0].error
    assert isinstance(events[1], Received) and events[1].message == _done(0, 1)


@pytest.mark.parametrize("what", ["over the cap", "cut framing"])
def test_unreadable_framing_ends_the_agent_as_a_protocol_error(what) -> None:
    hub = _hub(max_bytes=1000)
    try:
        agent = _Agent(hub, 0)
        agent.raw.send_bytes(codec.encode(_done(0, 0)))
        if what == "over the cap":
            agent.raw.send_bytes(b"x" * 2000)
        else:  # a length prefix promising more than ever comes
            agent.raw._send((100).to_bytes(4, "big", signed=True) + b"short")
        agent.raw.close()
        events = _until_left(hub, 1)
        assert isinstance(events[0], Received) and events[0].message == _done(0, 0)
        assert isinstance(events[-1], Left) and events[-1].reason.startswith(
            "protocol error: unreadable message ("
        )
        assert events[-1].reason.endswith("; cap 1000 bytes")
        assert not agent.process.is_alive()  # dropped
        assert hub.events(0.0) == []  # gone once: its sentinel says nothing more
    finally:
        hub.stop([], interrupted=True)


def test_a_reader_holds_at_most_its_read_ahead() -> None:
    """With room for one message, each collection hands over one; the rest wait in the
    pipe (the agent's sends wait behind them), none is lost or reordered, and those still
    in the pipe when the process ended come before its Left."""
    hub = _hub(read_ahead=1)
    try:
        agent = _Agent(hub, 0)
        for k in range(50):
            agent.channel.send(_done(0, k))
        agent.exit()  # with all but the one read still in the pipe
        batches = []
        while not batches or not isinstance(batches[-1][-1], Left):
            batches.append(hub.events(5.0))
        events = [e for batch in batches for e in batch]
        assert [e.message.frame_index for e in events[:-1]] == list(range(50))
        assert events[-1] == Left(0, "process died (exit code 0)")
        assert all(sum(isinstance(e, Received) for e in batch) <= 1 for batch in batches)
    finally:
        hub.stop([], interrupted=True)


def test_stop_ends_every_reader_even_one_waiting_for_room_or_messages() -> None:
    before = set(threading.enumerate())
    hub = _hub(read_ahead=1)
    waiting, idle = _Agent(hub, 0, mortal=False), _Agent(hub, 1, mortal=False)
    for k in range(4):
        waiting.channel.send(_done(0, k))
    assert hub.events(5.0)  # the reader has read; now it waits for room (or for messages)
    hub.stop([0, 1], interrupted=False)  # no process ends: the hub's stop wakes them
    assert _readers() == []
    assert set(threading.enumerate()) - before == {waiting.channel._sender, idle.channel._sender}
    for end in (waiting, idle):
        assert end.channel.receive() == Shutdown("the coordinator is stopping")
        end.channel.close()
    assert set(threading.enumerate()) <= before
    for end in (waiting, idle):
        end.process.die(0)


def test_a_second_stop_is_harmless(hub) -> None:
    agent = _Agent(hub, 0)
    agent.exit()
    hub.stop([], interrupted=True)
    hub.stop([], interrupted=True)
    assert _readers() == []


def _packet() -> KeyframePacket:
    return mast3r_packet(H, W, encoding=None)


def test_a_waiting_keyframe_is_held_as_its_bytes_and_decoded_alike(hub) -> None:
    """Issue 41: the reader hands a keyframe's bytes on with it (no other message's); a
    keyframe waiting for its turn is held as them, not decoded, and decoded again when its
    turn comes into the same keyframe."""
    from como3r.runtime.agent_events import Waiting

    agent = _Agent(hub, 0)
    packet = _packet()
    agent.channel.send(KeyframeMessage(packet=packet, applied_seq=0, T_WC_previous=None))
    (event,) = hub.events(5.0)
    agent.channel.send(_done(0, 1))
    (done,) = hub.events(5.0)
    assert isinstance(done, Received) and done.data is None
    assert isinstance(event, Received) and event.data is not None
    waiting = Waiting.of(None, event.message, None, event.data, codec.DEFAULT_MAX_BYTES)
    assert waiting.held is None and waiting.frame_index == packet.frame_index
    message, seconds = waiting.message()
    assert seconds > 0.0 and message is not event.message
    for name in ("T_WC", "X_hat", "C_hat"):
        assert torch.equal(getattr(message.packet, name), getattr(event.message.packet, name))
    assert (message.packet.colors == event.message.packet.colors).all()
