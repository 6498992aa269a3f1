"""The coordinator's end of the transport across machines (``como3r coordinator``; the
protocol, its key expressions and what both ends share are in
:mod:`como3r.transport.zenoh_protocol`).

Who holds an id. The coordinator hands agent a's task to the first process that asks and
from then on takes a's messages from that incarnation only. When that process's token goes
(a crash, a lost link, a frozen coordinator: Zenoh cannot tell them apart), the agent is
reported as :class:`~como3r.transport.links.Left` with ``may_return``; if the same
process reconnects, its token comes back (:class:`~como3r.transport.links.Joined`) and its
stream continues. A new process asking for a's task while the holder's token is present is
told to wait (the holder may be dead with its lease not yet expired, or a second process
started with the same id by mistake); once the holder's token is gone, the runtime's
:data:`~como3r.transport.links.Rejoin` decides, and the newcomer takes over the id with a
fresh message sequence. Messages to an agent carry the incarnation they are meant for, so a
superseded process never applies its successor's updates.

Zenoh's callbacks only queue; answering task queries, admitting processes and deciding on
each message happen on the coordinator's own thread, in arrival order; messages are decoded
on a thread per agent id (:mod:`.zenoh_decoding`) and sends go through a background thread,
so neither side ever blocks Zenoh or its own loop.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from como3r.errors import InputError
from como3r.transport import codec
from como3r.transport.links import (
    Event,
    Joined,
    Left,
    Received,
    Rejected,
    Rejoin,
    SendBacklog,
    Traffic,
)
from como3r.transport.messages import AgentTask, Shutdown
from como3r.transport.pipe_readers import READ_AHEAD_BYTES
from como3r.transport.zenoh_decoding import Decoder, Decoding
from como3r.transport.zenoh_protocol import (
    BYE,
    CONTROL_PRIORITY,
    INCARNATION,
    PIECE,
    SEQ,
    STREAM,
    WAIT,
    Keys,
    Pieces,
    Sender,
)

logger = logging.getLogger(__name__)

#: how long :meth:`ZenohHub.linger` waits quietly (agents normally say ``Bye`` during the
#: coordinator's final solve) before it says what it waits for
LINGER_QUIET_S = 2.0


@dataclass
class _Holder:
    """The coordinator's view of one agent id: which process holds it, where its message
    sequence is, and which of its processes are connected."""

    incarnation: int | None = None
    task: bytes = b""  # the holder's task (asked again: the same answer)
    next_seq: int = 0
    acked: int = -1  # the last seq acknowledged (every one up to it is stored)
    ack_due: bool = False  # a duplicate came: acknowledge again
    dropped: bool = False
    acknowledged_here: bool = False  # this coordinator process acknowledged some message
    said_bye: bool = False  # the holder has its last acknowledgement and left
    present: set[int] = field(default_factory=set)  # incarnations with a liveliness token
    superseded: set[int] = field(default_factory=set)  # earlier holders

    def describe(self) -> str:
        return (
            "no process holds it yet"
            if self.incarnation is None
            else f"process {self.incarnation:016x} does"
        )


class ZenohHub:
    """The coordinator's end (:class:`~como3r.transport.links.Hub`) over Zenoh.

    Args:
        session: an open Zenoh session (the caller closes it).
        keys: the run's key expressions.
        agents: agent ids ``0 .. agents-1`` take part; others are logged and dropped.
        max_bytes: size cap of one message.
        grace_s: how long :meth:`stop` waits for its last sends.
        max_mbps: the rate limit of what the coordinator sends (0: none); all of it goes in
            the control lane (:class:`~como3r.transport.zenoh_protocol.Sender`), in order
            (an agent applies its pose updates in sequence).
        certified: a team run: a message counts only if its key ends in the certificate
            name of the agent it claims to come from (Zenoh's access control makes that
            name its sender's, :mod:`como3r.transport.team_access`).
        read_ahead: bytes of decoded messages an agent's decoder holds before it waits for
            :meth:`events` (:data:`~.pipe_readers.READ_AHEAD_BYTES`).
    """

    name = "zenoh"

    def __init__(
        self,
        session: Any,
        keys: Keys,
        agents: int,
        max_bytes: int,
        grace_s: float,
        certified: bool = False,
        max_mbps: float = 0.0,
        read_ahead: int = READ_AHEAD_BYTES,
    ) -> None:
        self.session, self.keys, self.agents = session, keys, agents
        self.certified = certified
        self.max_bytes, self.grace_s = max_bytes, grace_s
        self._traffic = [Traffic() for _ in range(agents)]
        self._holders = [_Holder() for _ in range(agents)]
        self._tasks: dict[int, bytes] = {}
        self._rejoin: Rejoin | None = None
        self._inbox: queue.Queue[tuple[Any, ...]] = queue.Queue()
        self._backlog: deque[tuple[Any, ...]] = deque()
        self._sender = Sender(session, priority=CONTROL_PRIORITY, express=True, max_mbps=max_mbps)
        self._pieces = Pieces(max_bytes)
        # the decoders' condition; the inbox and a decoder are fed under it together
        self._bell = threading.Condition()
        self._decoders = [
            Decoder(agent, max_bytes, self._bell, read_ahead) for agent in range(agents)
        ]
        self._declared = [
            session.declare_subscriber(keys.up_all(), self._on_sample),
            session.liveliness().declare_subscriber(
                keys.alive("*", "*"), self._on_liveliness, history=True
            ),
        ]
        self._stopped = False
        self._closed = False

    # ------------------------------------------------------------ Zenoh's threads

    def _on_sample(self, sample: Any) -> None:
        key, size = str(sample.key_expr), len(sample.payload)
        agent, sender = self.keys.agent_of(key), self.keys.sender_of(key)
        if self.certified and sender != f"agent-{agent}":
            self._inbox.put(
                (
                    "reject",
                    agent,
                    f"sent under agent {agent}'s id by the holder of certificate {sender}",
                )
            )
            return
        if size > self.max_bytes:  # not even copied
            self._inbox.put(
                (
                    "reject",
                    agent,
                    f"message of {size} bytes exceeds the cap of {self.max_bytes} bytes",
                )
            )
            return
        attachment, data = _attachment(sample), sample.payload.to_bytes()
        if self.keys.kind_of(key) == BYE:
            self._inbox.put(("bye", agent, _incarnation(attachment)))
            return
        if len(attachment) == PIECE.size and self._agent_id(agent) is not None:
            whole = self._pieces.add(agent, attachment, data)
            if isinstance(whole, str):
                self._inbox.put(("reject", agent, whole))
            if not isinstance(whole, tuple):
                return
            attachment, data = whole
        known = self._agent_id(agent)
        if known is None or len(attachment) != STREAM.size:  # dropped or rejected unread
            self._inbox.put(("message", agent, attachment, None))
            return
        with self._bell:  # its decoder decodes in the inbox's order
            self._inbox.put(("message", agent, attachment, self._decoders[known].feed(data)))

    def _on_liveliness(self, sample: Any) -> None:
        import zenoh

        key = str(sample.key_expr)
        self._inbox.put(
            (
                "alive",
                self.keys.agent_of(key),
                key.rsplit("/", 1)[-1],
                sample.kind == zenoh.SampleKind.PUT,
            )
        )

    def _on_query(self, query: Any) -> None:
        self._inbox.put(
            ("query", self.keys.agent_of(str(query.key_expr)), _attachment(query), query)
        )

    # ------------------------------------------------------------ the coordinator's thread

    def start(self, tasks: Sequence[AgentTask], rejoin: Rejoin) -> None:
        for task in tasks:
            self._tasks[task.agent] = codec.encode(task, max_bytes=self.max_bytes)
            holder = self._holders[task.agent]
            if holder.incarnation is not None and not holder.task:  # resumed
                holder.task = self._tasks[task.agent]
        self._rejoin = rejoin
        # agents get their tasks, then see the coordinator, once it can answer them
        self._declared.append(self.session.declare_queryable(self.keys.task("*"), self._on_query))
        self._declared.append(self.session.liveliness().declare_token(self.keys.coordinator()))

    def events(self, timeout: float) -> list[Event]:
        deadline = time.monotonic() + timeout
        if not self._backlog:
            try:
                self._backlog.append(
                    self._inbox.get(timeout=timeout) if timeout > 0 else self._inbox.get_nowait()
                )
            except queue.Empty:
                return []
        while True:
            try:
                self._backlog.append(self._inbox.get_nowait())
            except queue.Empty:
                break
        out: list[Event] = []
        while self._backlog:
            if out and self._asks_rejoin(self._backlog[0]):
                break  # decided once the runtime has handled what came before it
            wait = 0.0 if out else deadline - time.monotonic()  # for the first event only
            if not self._decoded(self._backlog[0], wait):
                break
            out.extend(self._event(self._backlog.popleft()))
        return out

    def _decoded(self, item: tuple[Any, ...], wait: float) -> bool:
        """Whether ``item`` is not a message still being decoded, waiting up to ``wait``
        seconds for its decode."""
        decoding = item[3] if item[0] == "message" else None
        if not isinstance(decoding, Decoding):
            return True
        with self._bell:
            return self._bell.wait_for(lambda: decoding.item is not None, wait)

    def _agent_id(self, text: str) -> int | None:
        return int(text) if text.isdigit() and int(text) < self.agents else None

    def _event(self, item: tuple[Any, ...]) -> list[Event]:
        kind, name = item[0], item[1]
        agent = self._agent_id(name)
        if agent is None:
            text = f"unknown agent {name!r} (this run has agents 0 to {self.agents - 1})"
            if kind == "query":
                _reply(
                    item[3], error=f"no agent {name} in this run (agents 0 to {self.agents - 1})"
                )
            elif kind != "alive":
                logger.warning("dropped a message for %s", text)
            return []
        if kind == "reject":
            return [Rejected(agent, item[2])]
        if kind == "alive":
            return self._liveliness(agent, item[2], item[3])
        if kind == "query":
            return self._query(agent, item[2], item[3])
        if kind == "bye":
            holder = self._holders[agent]
            holder.said_bye |= item[2] is not None and item[2] == holder.incarnation
            return []
        event = self._message(agent, item[2], item[3])
        return [] if event is None else [event]

    def _liveliness(self, agent: int, label: str, present: bool) -> list[Event]:
        try:
            incarnation = int(label, 16)
        except ValueError:
            return []
        holder = self._holders[agent]
        (holder.present.add if present else holder.present.discard)(incarnation)
        if present and incarnation in holder.superseded:  # back after it was replaced
            self._send(
                agent, incarnation, Shutdown(f"another process has taken over agent {agent}'s id")
            )
        if incarnation != holder.incarnation:
            return []  # a process not (or no longer) holding the id
        if not present:
            return [
                Left(
                    agent,
                    "left (its liveliness token is gone: the process ended or its link was lost)",
                    may_return=True,
                )
            ]
        if holder.dropped:  # back after it was counted as failed: it may have missed it
            self._shutdown(agent)
        return [Joined(agent)]

    # ------------------------------------------------------------ who holds an id

    def _asks_rejoin(self, item: tuple[Any, ...]) -> bool:
        if item[0] != "query" or (agent := self._agent_id(item[1])) is None:
            return False
        incarnation = _incarnation(item[2])
        return incarnation is not None and _decision(self._holders[agent], incarnation) == "rejoin"

    def _query(self, agent: int, attachment: bytes, query: Any) -> list[Event]:
        """Answer a process asking for agent ``agent``'s task."""
        holder, incarnation = self._holders[agent], _incarnation(attachment)
        if incarnation is None:
            _reply(
                query, error="the task query carries no incarnation (a como3r of another version?)"
            )
            return []
        if self._stopped:
            _reply(query, error="the run is over: the coordinator has stopped taking agents")
            return []
        decision = _decision(holder, incarnation)
        if decision == "again":
            _reply(query, holder.task)
            return []
        if decision == "wait":
            _reply(
                query,
                error=f"{WAIT}another process with id {agent} "
                f"({holder.incarnation:016x}) is still connected",
            )
            return []
        assert self._rejoin is not None, "start() first"
        answer = self._tasks[agent] if decision == "first" else self._rejoin(agent)
        if isinstance(answer, str):
            _reply(query, error=answer)
            return []
        if holder.incarnation is not None:
            logger.info(
                "agent %d: process %016x takes over the id from %016x",
                agent,
                incarnation,
                holder.incarnation,
            )
            holder.superseded.add(holder.incarnation)
        holder.incarnation, holder.next_seq, holder.acked = incarnation, 0, -1
        holder.ack_due, holder.dropped, holder.said_bye = False, False, False
        holder.task = (
            answer if isinstance(answer, bytes) else codec.encode(answer, max_bytes=self.max_bytes)
        )
        _reply(query, holder.task)
        return [Joined(agent)] if incarnation in holder.present else []

    def _message(self, agent: int, attachment: bytes, decoding: Decoding | None) -> Event | None:
        if decoding is None:
            return Rejected(agent, "no sequence number attached")
        with self._bell:
            item = self._decoders[agent].take(decoding)
        incarnation, seq, queued, rate = STREAM.unpack(attachment)
        holder = self._holders[agent]
        if incarnation == holder.incarnation:
            traffic = self._traffic[agent]
            if traffic.backlog is None:
                traffic.backlog = SendBacklog()
            traffic.backlog.note(queued, rate)
        if incarnation != holder.incarnation:
            if isinstance(item, Rejected):
                return item
            return Rejected(
                agent,
                f"from process {incarnation:016x}, which does not "
                f"hold agent {agent}'s id ({holder.describe()})",
            )
        if holder.dropped:
            logger.debug("agent %d counts as failed: message %d ignored", agent, seq)
            return None
        if seq < holder.next_seq:  # re-sent after a reconnect: stored already
            holder.ack_due = True
            return None
        if self._stopped:  # the run is over: nothing more is stored, nor acknowledged
            logger.warning("agent %d: message %d came after the run ended: dropped", agent, seq)
            return None
        if seq > holder.next_seq:
            return Rejected(
                agent, f"message {seq} before {holder.next_seq} (a gap: the agent re-sends)"
            )
        holder.next_seq += 1  # the holder's own: taken, or skipped, never waited for
        if isinstance(item, Received):
            self._traffic[agent].received(item.message, decoding.nbytes)
            item = dataclasses.replace(item, seq=seq)
        return item

    # ------------------------------------------------------------ to the agents

    def durable(self, held: Mapping[int, int]) -> dict[str, Any]:
        return {
            "holders": [
                {
                    "incarnation": h.incarnation,
                    "next_seq": self._storable(agent, held) + 1,
                    "superseded": sorted(h.superseded),
                    "dropped": h.dropped,
                }
                for agent, h in enumerate(self._holders)
            ]
        }

    def acknowledge(self, held: Mapping[int, int]) -> None:
        for agent, holder in enumerate(self._holders):
            upto = self._storable(agent, held)
            if (
                holder.incarnation is None
                or holder.dropped
                or upto < 0
                or not (holder.ack_due or upto > holder.acked)
            ):
                continue
            self._sender.put(self.keys.ack(agent), SEQ.pack(holder.incarnation, upto))
            holder.acked, holder.ack_due = max(holder.acked, upto), False
            holder.acknowledged_here = True

    def _storable(self, agent: int, held: Mapping[int, int]) -> int:
        """The last seq of ``agent``'s holder that is stored: every one handed over, up to
        the first the runtime holds back."""
        next_seq = self._holders[agent].next_seq
        return min(next_seq, held.get(agent, next_seq)) - 1

    def resume(self, state: Mapping[str, Any]) -> dict[int, int]:
        holders = state.get("holders", [])
        if len(holders) != self.agents:
            raise InputError(
                f"the stored session has {len(holders)} agents, this "
                f"coordinator {self.agents} (--agents)"
            )
        for holder, saved in zip(self._holders, holders):
            holder.incarnation = saved["incarnation"]
            holder.next_seq = saved["next_seq"]
            holder.acked = saved["next_seq"] - 1
            holder.superseded = set(saved["superseded"])
            holder.dropped = saved["dropped"]
        return {
            agent: h.acked for agent, h in enumerate(self._holders) if h.incarnation is not None
        }

    def send(self, agent: int, message: Any) -> None:
        incarnation = self._holders[agent].incarnation
        if incarnation is not None:  # else no process has taken the task: nobody to tell
            self._send(agent, incarnation, message)

    def _send(self, agent: int, incarnation: int, message: Any) -> None:
        data = codec.encode(message, max_bytes=self.max_bytes)
        self._traffic[agent].sent(message, len(data))
        self._sender.put(
            self.keys.down(agent, type(message).__name__), data, INCARNATION.pack(incarnation)
        )

    def drop(self, agent: int) -> None:
        self._holders[agent].dropped = True
        self._shutdown(agent)

    def _shutdown(self, agent: int) -> None:
        self.send(agent, Shutdown("the coordinator counts this agent as failed"))

    def stop(self, live: Sequence[int], interrupted: bool) -> None:
        """Tell the ``live`` agents to stop; ``interrupted``: :meth:`close` at once, else
        the hub stays open for :meth:`linger` (then :meth:`close`)."""
        if self._stopped:
            return
        self._stopped = True
        for agent in live:
            self.send(agent, Shutdown("the coordinator is stopping"))
        if interrupted:
            self.close()

    def linger(self, timeout_s: float) -> list[int]:
        """After :meth:`stop`: wait up to ``timeout_s`` seconds until every agent this
        process acknowledged messages to has said ``Bye`` (it has its last acknowledgement),
        acknowledging again what an agent re-sends once it reconnects (one whose link was
        cut as the last acknowledgement went out). Returns the agents that did not say it
        (they may still wait, their messages all stored)."""
        started, said = time.monotonic(), False
        while waiting := self.unconfirmed():
            waited = time.monotonic() - started
            if waited >= timeout_s:
                return waiting
            if not said and waited >= LINGER_QUIET_S:
                logger.warning(
                    "the outputs are written; waiting up to %g s for agent(s) %s to take "
                    "their last acknowledgement (Ctrl-C stops waiting)",
                    timeout_s,
                    ", ".join(map(str, waiting)),
                )
                said = True
            self.events(min(0.5, timeout_s - waited))  # duplicates make an ack due
            self.acknowledge({})  # every message is stored
        return []

    def unconfirmed(self) -> list[int]:
        """The agents :meth:`linger` still waits for."""
        return [
            agent
            for agent, h in enumerate(self._holders)
            if h.acknowledged_here and not h.said_bye and not h.dropped
        ]

    def close(self) -> None:
        """Put what is queued (for up to ``grace_s``) and leave the session."""
        if self._closed:
            return
        self._closed = True
        self._stopped = True
        self._sender.close(self.grace_s)
        for entity in reversed(self._declared):
            entity.undeclare()
        with self._bell:  # what they still hold is dropped
            for decoder in self._decoders:
                decoder.stop()
        for decoder in self._decoders:
            decoder.thread.join(self.grace_s)

    def traffic(self, agent: int) -> Traffic:
        return self._traffic[agent]

    def exitcode(self, agent: int) -> int | None:
        return None


def _attachment(sample_or_query: Any) -> bytes:
    attachment = sample_or_query.attachment
    return attachment.to_bytes() if attachment is not None else b""


def _incarnation(attachment: bytes) -> int | None:
    return INCARNATION.unpack(attachment)[0] if len(attachment) == INCARNATION.size else None


def _decision(holder: _Holder, incarnation: int) -> str:
    """What a task query of process ``incarnation`` gets: ``again`` (the holder asks
    again), ``first`` (nobody held the id), ``wait`` (the holder is still connected) or
    ``rejoin`` (the holder left, or the id failed: the runtime decides)."""
    if incarnation == holder.incarnation:
        return "again"
    if holder.incarnation is None and not holder.dropped:
        return "first"
    return "wait" if holder.incarnation in holder.present else "rejoin"


def _reply(query: Any, payload: bytes = b"", error: str | None = None) -> None:
    """Answer a task query (its asker may have given up waiting: then nobody hears it)."""
    try:
        if error is None:
            query.reply(query.key_expr, payload)
        else:
            query.reply_err(error.encode())
    except Exception as exc:  # the session is closing
        logger.debug("task reply failed: %s", exc)
    finally:
        query.drop()
