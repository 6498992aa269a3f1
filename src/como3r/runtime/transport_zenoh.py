"""The transport across machines: Zenoh in peer mode (``como3r coordinator`` / ``agent``).

The typed msgpack messages of :mod:`como3r.runtime.messages` are the payloads, unchanged.
Key expressions name the session, the agent and the message kind::

    como3r/<session>/coordinator              liveliness token of the coordinator
    como3r/<session>/agent/<a>                liveliness token of agent a (join / leave)
    como3r/<session>/agent/<a>/task           queryable: agent a's AgentTask (late joiners)
    como3r/<session>/agent/<a>/up/<Type>      agent -> coordinator; attachment <QQ:
                                              incarnation (random per agent process), seq
    como3r/<session>/agent/<a>/down/<Type>    coordinator -> agent
    como3r/<session>/agent/<a>/ack            coordinator -> agent <QQ: incarnation, the
                                              last seq stored (every one up to it is)

Delivery is reliable with congestion control ``BLOCK`` (``DROP`` loses messages under a
slow subscriber), and acknowledged: an agent keeps every message until the coordinator
has stored it, re-sends the unacknowledged ones when the coordinator's token reappears, and
leaves (:meth:`ZenohAgentLink.close`) only once the last one is stored. The coordinator
takes an agent's messages in sequence, drops duplicates of re-sent ones, and logs and drops
whatever is not a valid message (oversized, malformed, unknown agent, another incarnation).
Zenoh's callbacks only queue bytes; decoding happens on the coordinator's own thread, and
sends go through a background thread, so neither side ever blocks Zenoh or its own loop.
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from como3r.errors import InputError
from como3r.runtime import codec
from como3r.runtime.messages import FROM_AGENT, TO_AGENT, AgentTask, KeyframeMessage, Shutdown
from como3r.runtime.transport import Event, Joined, Left, Received, Rejected, Traffic

logger = logging.getLogger(__name__)

_SEQ = struct.Struct("<QQ")  # incarnation, sequence number


@dataclass(frozen=True)
class ZenohOptions:
    """How a process joins the Zenoh network.

    Attributes:
        listen: endpoints to listen on (``tcp/0.0.0.0:7447``).
        connect: endpoints to connect to (``tcp/HOST:7447``); retried until they answer.
        scouting: multicast scouting (peers find each other on the LAN); off: only the
            explicit endpoints.
        config_file: a Zenoh configuration file (JSON5) to start from: TLS, access
            control, authentication as Zenoh documents them. The options above are set on
            top of it.
        session: the run's name in every key expression (several runs on one network).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    scouting: bool = False
    config_file: Path | None = None
    session: str = "como3r"


def open_session(options: ZenohOptions) -> Any:
    """A Zenoh session in peer mode on ``options``.

    Raises:
        InputError: an unreadable configuration file, a bad endpoint or a port in use.
    """
    import zenoh

    try:
        config = (zenoh.Config.from_file(str(options.config_file))
                  if options.config_file is not None else zenoh.Config())
        config.insert_json5("mode", json.dumps("peer"))
        config.insert_json5("scouting/multicast/enabled", json.dumps(options.scouting))
        if options.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
        if options.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
        return zenoh.open(config)
    except zenoh.ZError as exc:
        where = f" ({options.config_file})" if options.config_file is not None else ""
        raise InputError(f"zenoh{where}: {' '.join(str(exc).split())}") from None


class Keys:
    """The key expressions of one session (see the module docstring)."""

    def __init__(self, session: str) -> None:
        if not session or any(c in session for c in "/*$?#"):
            raise InputError(f"session name {session!r}: use letters, digits, - and _")
        self.root = f"como3r/{session}"

    def coordinator(self) -> str:
        return f"{self.root}/coordinator"

    def agent(self, agent: int | str) -> str:
        return f"{self.root}/agent/{agent}"

    def task(self, agent: int | str) -> str:
        return f"{self.agent(agent)}/task"

    def up(self, agent: int | str, kind: str) -> str:
        return f"{self.agent(agent)}/up/{kind}"

    def down(self, agent: int | str, kind: str) -> str:
        return f"{self.agent(agent)}/down/{kind}"

    def ack(self, agent: int | str) -> str:
        return f"{self.agent(agent)}/ack"

    def agent_of(self, key: str) -> str:
        """The agent field of a key under ``agent/`` (as written: not checked)."""
        return key[len(self.root) + len("/agent/"):].split("/", 1)[0]


class _Sender:
    """Puts ``(key, payload, attachment)`` on the network from a background thread."""

    def __init__(self, session: Any) -> None:
        import zenoh

        self.session = session
        self.block = zenoh.CongestionControl.BLOCK
        self.queue: queue.Queue[tuple[str, bytes, bytes | None] | None] = queue.Queue()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        self.queue.put((key, payload, attachment))

    def close(self, timeout: float) -> None:
        self.queue.put(None)
        self.thread.join(timeout)

    def _loop(self) -> None:
        while (item := self.queue.get()) is not None:
            key, payload, attachment = item
            try:
                self.session.put(key, payload, attachment=attachment,
                                 congestion_control=self.block)
            except Exception as exc:  # a closed session: nothing more can be sent
                logger.debug("put on %s failed: %s", key, exc)


@dataclass
class _Stream:
    """Where the coordinator is in one agent's message sequence."""

    incarnation: int | None = None
    next_seq: int = 0
    ack_due: bool = False


class ZenohHub:
    """The coordinator's end (:class:`~como3r.runtime.transport.Hub`) over Zenoh.

    Args:
        session: an open Zenoh session (the caller closes it).
        keys: the run's key expressions.
        agents: agent ids ``0 .. agents-1`` take part; others are logged and dropped.
        max_bytes: size cap of one message.
        grace_s: how long :meth:`stop` waits for its last sends.
    """

    name = "zenoh"

    def __init__(self, session: Any, keys: Keys, agents: int, max_bytes: int,
                 grace_s: float) -> None:
        self.session, self.keys, self.agents = session, keys, agents
        self.max_bytes, self.grace_s = max_bytes, grace_s
        self._traffic = [Traffic() for _ in range(agents)]
        self._streams = [_Stream() for _ in range(agents)]
        self._tasks: dict[int, bytes] = {}
        self._inbox: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self._sender = _Sender(session)
        self._declared = [
            session.declare_subscriber(keys.up("*", "*"), self._on_sample),
            session.liveliness().declare_subscriber(keys.agent("*"), self._on_liveliness,
                                                    history=True),
        ]
        self._stopped = False

    # ------------------------------------------------------------ Zenoh's threads

    def _on_sample(self, sample: Any) -> None:
        agent, size = self.keys.agent_of(str(sample.key_expr)), len(sample.payload)
        if size > self.max_bytes:  # not even copied
            self._inbox.put(("reject", agent, f"message of {size} bytes exceeds the cap of "
                                              f"{self.max_bytes} bytes"))
            return
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        self._inbox.put(("message", agent, attachment, sample.payload.to_bytes()))

    def _on_liveliness(self, sample: Any) -> None:
        import zenoh

        self._inbox.put(("alive", self.keys.agent_of(str(sample.key_expr)),
                         sample.kind == zenoh.SampleKind.PUT))

    def _on_query(self, query: Any) -> None:
        agent = self._agent_id(self.keys.agent_of(str(query.key_expr)))
        if agent is None:
            query.reply_err(f"no agent {self.keys.agent_of(str(query.key_expr))} in this run "
                            f"(agents 0 to {self.agents - 1})".encode())
        else:
            query.reply(query.key_expr, self._tasks[agent])

    # ------------------------------------------------------------ the coordinator's thread

    def start(self, tasks: Sequence[AgentTask]) -> None:
        for task in tasks:
            self._tasks[task.agent] = codec.encode(task, max_bytes=self.max_bytes)
        # agents get their tasks, then see the coordinator, once it can answer them
        self._declared.append(self.session.declare_queryable(self.keys.task("*"),
                                                             self._on_query))
        self._declared.append(self.session.liveliness().declare_token(self.keys.coordinator()))

    def events(self, timeout: float) -> list[Event]:
        try:
            items = [self._inbox.get(timeout=timeout) if timeout > 0 else
                     self._inbox.get_nowait()]
        except queue.Empty:
            return []
        while True:
            try:
                items.append(self._inbox.get_nowait())
            except queue.Empty:
                break
        return [event for item in items if (event := self._event(item)) is not None]

    def _agent_id(self, text: str) -> int | None:
        return int(text) if text.isdigit() and int(text) < self.agents else None

    def _event(self, item: tuple[Any, ...]) -> Event | None:
        kind, name = item[0], item[1]
        agent = self._agent_id(name)
        if agent is None:
            logger.warning("dropped a message for unknown agent %r (this run has agents 0 to "
                           "%d)", name, self.agents - 1)
            return None
        if kind == "reject":
            return Rejected(agent, item[2])
        if kind == "alive":
            return (Joined(agent) if item[2] else
                    Left(agent, "left (its liveliness token is gone: the process ended or "
                                "its link was lost)"))
        return self._message(agent, item[2], item[3])

    def _message(self, agent: int, attachment: bytes, data: bytes) -> Event | None:
        if len(attachment) != _SEQ.size:
            return Rejected(agent, "no sequence number attached")
        incarnation, seq = _SEQ.unpack(attachment)
        stream = self._streams[agent]
        if stream.incarnation is not None and incarnation != stream.incarnation:
            return Rejected(agent, f"from another process with this id (incarnation "
                                   f"{incarnation:016x}, not {stream.incarnation:016x})")
        if seq < stream.next_seq:  # re-sent after a reconnect: stored already
            stream.ack_due = True
            return None
        if seq > stream.next_seq:
            return Rejected(agent, f"message {seq} before {stream.next_seq} (a gap: the agent "
                                   f"re-sends)")
        try:
            message = codec.decode(data, max_bytes=self.max_bytes, expected=FROM_AGENT)
        except codec.MessageError as exc:
            error = str(exc)
        else:
            sender = (message.packet.agent if isinstance(message, KeyframeMessage)
                      else message.agent)
            error = (None if sender == agent else
                     f"an {type(message).__name__} of agent {sender} under agent {agent}'s key")
        if error is not None:
            if stream.incarnation is not None:  # the agent's own: skipped, not waited for
                stream.next_seq += 1
                stream.ack_due = True
            return Rejected(agent, error)
        stream.incarnation = incarnation
        stream.next_seq += 1
        stream.ack_due = True
        self._traffic[agent].received(message, len(data))
        return Received(agent, message)

    def acknowledge(self) -> None:
        for agent, stream in enumerate(self._streams):
            if stream.ack_due and stream.incarnation is not None:
                self._sender.put(self.keys.ack(agent),
                                 _SEQ.pack(stream.incarnation, stream.next_seq - 1))
                stream.ack_due = False

    def send(self, agent: int, message: Any) -> None:
        data = codec.encode(message, max_bytes=self.max_bytes)
        self._traffic[agent].sent(message, len(data))
        self._sender.put(self.keys.down(agent, type(message).__name__), data)

    def drop(self, agent: int) -> None:
        self.send(agent, Shutdown("the coordinator counts this agent as failed"))

    def stop(self, live: Sequence[int], interrupted: bool) -> None:
        if self._stopped:
            return
        self._stopped = True
        for agent in live:
            self.send(agent, Shutdown("the coordinator is stopping"))
        self.acknowledge()
        self._sender.close(self.grace_s)
        for entity in reversed(self._declared):
            entity.undeclare()

    def traffic(self, agent: int) -> Traffic:
        return self._traffic[agent]

    def exitcode(self, agent: int) -> int | None:
        return None


class ZenohAgentLink:
    """An agent's end (:class:`~como3r.runtime.transport.AgentLink`) over Zenoh.

    Declares the agent's subscribers, then its liveliness token (the coordinator sees it
    join). Messages are put only while the coordinator's token is present; each is kept
    until acknowledged.

    Args:
        session: an open Zenoh session (the caller closes it).
        keys: the run's key expressions.
        agent: this agent's id.
        wait_log_s: how often :meth:`fetch_task` and :meth:`close` say what they wait for.
    """

    def __init__(self, session: Any, keys: Keys, agent: int, wait_log_s: float = 30.0) -> None:
        self.session, self.keys, self.agent = session, keys, agent
        self.max_bytes = codec.DEFAULT_MAX_BYTES
        self.wait_log_s = wait_log_s
        self.traffic = Traffic()
        self.incarnation = int.from_bytes(os.urandom(8), "little")
        self._next_seq = 0
        self._pending: deque[tuple[int, str, bytes]] = deque()  # not put yet
        self._unacked: dict[int, tuple[str, bytes]] = {}  # put, not stored yet
        self._present = False
        self._closed = False
        self._discard = False  # after a Shutdown: the coordinator takes nothing more
        self._cond = threading.Condition()
        self._inbox: queue.Queue[bytes] = queue.Queue()
        self._peeked: bytes | None = None
        self._declared = [
            session.declare_subscriber(keys.down(agent, "*"),
                                       lambda s: self._inbox.put(s.payload.to_bytes())),
            session.declare_subscriber(keys.ack(agent), self._on_ack),
            session.liveliness().declare_subscriber(keys.coordinator(), self._on_coordinator,
                                                    history=True),
        ]
        self._declared.append(session.liveliness().declare_token(keys.agent(agent)))
        self._sender = threading.Thread(target=self._send_loop, daemon=True)
        self._sender.start()

    def fetch_task(self) -> AgentTask:
        """This agent's task from the coordinator, asked until it answers.

        Raises:
            InputError: the coordinator has no agent with this id.
        """
        said = -math.inf
        while True:
            for reply in self.session.get(self.keys.task(self.agent), timeout=5.0):
                if reply.ok is None:
                    raise InputError(f"agent {self.agent}: the coordinator says: "
                                     f"{reply.err.payload.to_string()}")
                task = codec.decode(reply.ok.payload.to_bytes(), expected=AgentTask)
                self.max_bytes = task.max_message_bytes
                return task
            if time.monotonic() - said > self.wait_log_s:
                logger.warning("agent %d: waiting for the coordinator (%s)", self.agent,
                               self.keys.root)
                said = time.monotonic()
            time.sleep(0.5)

    # ------------------------------------------------------------ AgentLink

    def send(self, message: Any) -> None:
        data = codec.encode(message, max_bytes=self.max_bytes)
        self.traffic.sent(message, len(data))
        with self._cond:
            self._pending.append((self._next_seq, self.keys.up(self.agent,
                                                               type(message).__name__), data))
            self._next_seq += 1
            self._cond.notify_all()

    def poll(self, timeout: float = 0.0) -> bool:
        if self._peeked is None:
            try:
                self._peeked = (self._inbox.get(timeout=timeout) if timeout > 0
                                else self._inbox.get_nowait())
            except queue.Empty:
                return False
        return True

    def receive(self) -> Any:
        data, self._peeked = (self._peeked if self._peeked is not None
                              else self._inbox.get()), None
        message = codec.decode(data, max_bytes=self.max_bytes, expected=TO_AGENT)
        self.traffic.received(message, len(data))
        if isinstance(message, Shutdown):
            with self._cond:
                self._discard = True
                self._cond.notify_all()
        return message

    def close(self) -> None:
        """Wait until the coordinator has stored every message (or sent a Shutdown), then
        leave: the liveliness token goes last."""
        with self._cond:
            said = time.monotonic()
            while (self._pending or self._unacked) and not self._discard:
                self._cond.wait(1.0)
                if time.monotonic() - said > self.wait_log_s:
                    logger.warning("agent %d: waiting for the coordinator to store %d "
                                   "message(s)", self.agent,
                                   len(self._pending) + len(self._unacked))
                    said = time.monotonic()
            self._closed = True
            self._cond.notify_all()
        self._sender.join()
        for entity in reversed(self._declared):
            entity.undeclare()

    # ------------------------------------------------------------ threads

    def _send_loop(self) -> None:
        import zenoh

        while True:
            with self._cond:
                while not (self._closed or (self._present and self._pending)):
                    self._cond.wait()
                if self._closed:
                    return
                seq, key, data = self._pending.popleft()
                self._unacked[seq] = (key, data)
            try:
                self.session.put(key, data, attachment=_SEQ.pack(self.incarnation, seq),
                                 congestion_control=zenoh.CongestionControl.BLOCK)
            except Exception as exc:  # the session is closing
                logger.debug("put on %s failed: %s", key, exc)

    def _on_ack(self, sample: Any) -> None:
        data = sample.payload.to_bytes()
        if len(data) != _SEQ.size:
            return
        incarnation, seq = _SEQ.unpack(data)
        if incarnation != self.incarnation:
            return
        with self._cond:
            for stored in [s for s in self._unacked if s <= seq]:
                del self._unacked[stored]
            while self._pending and self._pending[0][0] <= seq:
                self._pending.popleft()
            self._cond.notify_all()

    def _on_coordinator(self, sample: Any) -> None:
        import zenoh

        present = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            if present and self._unacked:  # it may have lost them: again, in order
                logger.info("agent %d: the coordinator is back; re-sending %d message(s)",
                            self.agent, len(self._unacked))
                self._pending.extendleft(reversed([(s, *v) for s, v in
                                                   sorted(self._unacked.items())]))
                self._unacked.clear()
            elif not present:
                logger.warning("agent %d: the coordinator is gone; keeping messages until "
                               "it is back", self.agent)
            self._present = present
            self._cond.notify_all()
