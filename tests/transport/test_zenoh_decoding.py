"""The Zenoh hub's decodes on a thread per agent id (transport/zenoh_decoding.py), driven
through the callbacks a Zenoh session would call: nothing is decoded on the thread that
takes the events; what does not decode, or comes under another agent's key, is rejected with
the error it had on that thread; a keyframe reaches the ingest as its agent coded it; the
events keep their arrival order, a message still being decoded holding back what came after
it; a decoder holds at most its read-ahead; ``stop`` ends the decoders."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest

from como3r.config import Config, config_to_dict
from como3r.errors import MessageError
from como3r.runtime import ingest
from como3r.transport import codec
from como3r.transport.links import Event, Received, Rejected
from como3r.transport.messages import FROM_AGENT, AgentStarted, AgentTask, KeyframeMessage
from como3r.transport.zenoh_decoding import Decoder, Decoding
from como3r.transport.zenoh_protocol import INCARNATION, STREAM, Keys

from ..keyframe_packets import mast3r_packet

HOLDER = 0x1234  # the incarnation that takes agent 0's task
MAX_BYTES = 100_000


class _Bytes:
    """A Zenoh payload or attachment."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, data: bytes, attachment: bytes | None) -> None:
        self.key_expr, self.payload = key, _Bytes(data)
        self.attachment = None if attachment is None else _Bytes(attachment)


class _Query:
    def __init__(self, key: str, attachment: bytes) -> None:
        self.key_expr, self.attachment = key, _Bytes(attachment)
        self.answers: list[Any] = []

    def reply(self, key: str, payload: bytes) -> None:
        self.answers.append(payload)

    def reply_err(self, error: bytes) -> None:
        self.answers.append(error.decode())

    def drop(self) -> None:
        """Nothing to free."""


class _Entity:
    def undeclare(self) -> None:
        """Nothing to undeclare."""


class _Session:
    """What the hub asks of a Zenoh session; keeps the callbacks it is given (the test
    calls them as Zenoh's threads would)."""

    def __init__(self) -> None:
        self.on_sample: Any = None
        self.on_query: Any = None

    def declare_subscriber(self, key: str, callback: Any, **kwargs: Any) -> _Entity:
        if "/up/" in key:
            self.on_sample = callback
        return _Entity()

    def liveliness(self) -> _Session:
        return self

    def declare_token(self, key: str) -> _Entity:
        return _Entity()

    def declare_queryable(self, key: str, callback: Any) -> _Entity:
        self.on_query = callback
        return _Entity()

    def put(self, *args: Any, **kwargs: Any) -> None:
        """Acknowledgements go nowhere."""


class _Hub:
    """A hub for agents 0 and 1 on a :class:`_Session`, agent 0's task taken by
    :data:`HOLDER`."""

    def __init__(self, read_ahead: int = 1_000_000) -> None:
        pytest.importorskip("zenoh")
        from como3r.transport.zenoh_hub import ZenohHub

        self.session, self.keys = _Session(), Keys("test")
        self.hub = ZenohHub(self.session, self.keys, 2, MAX_BYTES, 2.0, read_ahead=read_ahead)
        task = AgentTask(
            agent=0, input_path="", config=config_to_dict(Config()), prior={"name": "simulated"}
        )
        self.hub.start([task], lambda agent: "no rejoining here")
        query = _Query(self.keys.task(0), INCARNATION.pack(HOLDER))
        self.session.on_query(query)
        assert self.hub.events(5.0) == [] and len(query.answers) == 1

    def put(self, data: bytes, seq: int, incarnation: int = HOLDER, agent: int = 0) -> None:
        """``data`` arriving under agent ``agent``'s key as message ``seq``."""
        attachment = STREAM.pack(incarnation, seq, 0, 0.0)
        self.session.on_sample(_Sample(self.keys.up(agent, "AgentStarted"), data, attachment))

    def events(self, count: int) -> list[Event]:
        """The next ``count`` events."""
        out: list[Event] = []
        while len(out) < count:
            got = self.hub.events(30.0)
            assert got, f"{count} events expected, {out} came"
            out += got
        return out


@pytest.fixture
def hub() -> Iterator[_Hub]:
    made = _Hub()
    yield made
    made.hub.stop([], interrupted=True)


def _started(agent: int = 0, pid: int = 1) -> bytes:
    return codec.encode(AgentStarted(agent=agent, pid=pid, frames=4))


def _error(data: bytes) -> str:
    """The codec's error for ``data`` as an agent's message."""
    with pytest.raises(MessageError) as raised:
        codec.decode(data, max_bytes=MAX_BYTES, expected=FROM_AGENT)
    return str(raised.value)


def test_messages_are_decoded_off_the_thread_taking_them_and_rejected_as_before(
    hub, monkeypatch
) -> None:
    """The holder's messages in order: one that decodes (its thread CPU seconds and its
    sequence number with it), one that does not (the codec's error), another agent's
    message under its key, one more that decodes; then a process that does not hold the id:
    its bytes that do not decode are rejected with the codec's error, those that do as not
    the holder's; a message without a sequence number is rejected unread."""
    garbage = b"\x93not a message"
    undecodable = _error(garbage)
    decoded_on: list[threading.Thread] = []
    decode = codec.decode

    def recording(data: bytes, *args: Any, **kwargs: Any) -> Any:
        decoded_on.append(threading.current_thread())
        return decode(data, *args, **kwargs)

    monkeypatch.setattr(codec, "decode", recording)
    hub.put(_started(pid=1), 0)
    hub.put(garbage, 1)
    hub.put(_started(agent=1), 2)
    hub.put(_started(pid=4), 3)
    hub.put(garbage, 0, incarnation=99)
    hub.put(_started(pid=5), 1, incarnation=99)
    hub.session.on_sample(_Sample(hub.keys.up(0, "AgentStarted"), _started(), None))
    first, bad, other, last, stale_bad, stale, unnumbered = hub.events(7)

    assert isinstance(first, Received) and first.message.pid == 1 and first.seq == 0
    assert first.seconds > 0.0
    assert bad == Rejected(0, undecodable)
    assert other == Rejected(0, "an AgentStarted of agent 1 under agent 0's key")
    assert isinstance(last, Received) and last.message.pid == 4 and last.seq == 3
    assert stale_bad == Rejected(0, undecodable)
    assert stale == Rejected(
        0,
        f"from process {99:016x}, which does not hold agent 0's id (process {HOLDER:016x} does)",
    )
    assert unnumbered == Rejected(0, "no sequence number attached")
    assert {t.name for t in decoded_on} == {"como3r-zenoh-decoder-0"}
    assert threading.current_thread() not in decoded_on
    traffic = hub.hub.traffic(0)
    assert traffic.messages_received["AgentStarted"] == 2
    assert traffic.bytes_received["AgentStarted"] == 2 * len(_started())


def test_a_keyframe_decoded_on_its_decoder_is_taken_by_the_ingest_as_coded(hub) -> None:
    """As its agent sent it (the lossy coding): the decode's record of the coded maps
    crosses threads, so the coordinator's ingest does not code it again."""
    packet = mast3r_packet(12, 16, encoding=None)
    message = KeyframeMessage(packet=packet, applied_seq=0, T_WC_previous=None)
    hub.put(codec.encode(message, lossy=True), 0)
    (event,) = hub.events(1)
    assert isinstance(event, Received) and event.seconds > 0.0
    assert ingest.coded(event.message.packet)
    assert ingest.received(event.message.packet) is event.message.packet


def test_a_message_being_decoded_holds_back_what_came_after_it(hub, monkeypatch) -> None:
    """Arrival order across kinds: an oversized message (rejected unread) behind one still
    being decoded waits for it; a wait of 0 returns at once."""
    release = threading.Event()
    decode = codec.decode

    def slow(data: bytes, *args: Any, **kwargs: Any) -> Any:
        release.wait()
        return decode(data, *args, **kwargs)

    monkeypatch.setattr(codec, "decode", slow)
    hub.put(_started(), 0)
    hub.put(b"x" * (MAX_BYTES + 1), 1)
    assert hub.hub.events(0.0) == []
    release.set()
    first, oversized = hub.events(2)
    assert isinstance(first, Received) and first.seq == 0
    assert oversized == Rejected(
        0, f"message of {MAX_BYTES + 1} bytes exceeds the cap of {MAX_BYTES} bytes"
    )


def test_a_decoder_holds_at_most_its_read_ahead_and_ends_at_stop() -> None:
    """With room for one message, the next is decoded only once the first was taken; the
    decodes keep the order they were fed in."""
    bell = threading.Condition()
    decoder = Decoder(0, MAX_BYTES, bell, limit=1)
    with bell:
        fed = [decoder.feed(_started(pid=pid)) for pid in range(3)]
    outcomes = []
    for decoding in fed:
        with bell:
            bell.wait_for(lambda d=decoding: d.item is not None)
            assert [d.item is not None for d in fed].count(True) == 1 + len(outcomes)
            outcomes.append(decoder.take(decoding))
    assert [o.message.pid for o in outcomes if isinstance(o, Received)] == [0, 1, 2]
    with bell:
        waiting = decoder.feed(_started())  # decoded, held, never taken
        bell.wait_for(lambda: waiting.item is not None)
        late: Decoding = decoder.feed(_started())  # no room: never decoded
        decoder.stop()
    decoder.thread.join()
    assert late.item is None and not decoder.thread.is_alive()


def test_stop_ends_every_decoder() -> None:
    made = _Hub()
    made.hub.stop([], interrupted=True)
    made.hub.stop([], interrupted=True)
    assert not [t for t in threading.enumerate() if t.name.startswith("como3r-zenoh-decoder")]
