"""The transport across machines: Zenoh in peer mode (``como3r coordinator`` / ``agent``).

The typed msgpack messages of :mod:`como3r.transport.messages` are the payloads, unchanged.
Key expressions name the session, the agent and the message kind::

    como3r/<session>/coordinator              liveliness token of the coordinator
    como3r/<session>/agent/<a>/alive/<inc>    liveliness token of agent a's process with
                                              incarnation <inc> (16 hex digits, random per
                                              process): join / leave
    como3r/<session>/agent/<a>/task           queryable: agent a's AgentTask; the query's
                                              attachment <Q: the asking process's incarnation
    como3r/<session>/agent/<a>/up/<Type>      agent -> coordinator; attachment <QQ:
                                              incarnation, seq; or, for each piece of a
                                              message over PIECE_BYTES, <QQII:
                                              incarnation, seq, piece, pieces; in a team
                                              run the key ends in /<sender's certificate
                                              name>
    como3r/<session>/agent/<a>/down/<Type>    coordinator -> agent; attachment <Q: the
                                              incarnation it is meant for
    como3r/<session>/agent/<a>/ack            coordinator -> agent <QQ: incarnation, the
                                              last seq stored (every one up to it is)

Delivery is reliable with congestion control ``BLOCK`` (``DROP`` loses messages under a
slow subscriber), and acknowledged: an agent keeps every message until the coordinator has
stored it (:mod:`como3r.transport.spool`: in memory, on disk past a limit), re-sends the
unacknowledged ones when the coordinator's token reappears, and leaves
(:class:`~como3r.transport.zenoh_agent.ZenohAgentLink`) only once the last one is stored. The
coordinator takes an agent's messages in sequence, drops duplicates of re-sent ones, and
logs and drops whatever is not a valid message (oversized, malformed, unknown agent, a
process that does not hold the agent's id). "Stored" means in the session store: the
runtime acknowledges a message once its effect is committed there (a keyframe waiting for
its turn is not, nor is anything after it), and the hub's own state (who holds each id,
where its stream is) goes into the same store first (:meth:`ZenohHub.durable`), so a
coordinator restarted with ``--resume`` (:meth:`ZenohHub.resume`) takes each agent's stream
up where the store has it and the agents' re-sent messages fill in the rest.

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

Pieces. Zenoh gives one put 5 s (``block/wait_before_close``) to enter the link's queue
and closes the link when it cannot: a keyframe of a megabyte put whole on a 1 Mbit/s link
closed it, and the agent's re-sending closed it again, for ever. An agent therefore puts a
message larger than :data:`PIECE_BYTES` in pieces, in order; the coordinator joins them
(:class:`Pieces`) and takes the message once its last piece is in. A piece out of order
(its message's start was lost with a link) is dropped with its message, which the agent
re-sends whole when the coordinator is back.

Priorities. Zenoh queues each link's messages by priority and sends the higher first, so
what the coordinator sends (acknowledgements, pose updates, ``Shutdown``: small, and what
lets an agent free its spool and correct its map) goes at ``INTERACTIVE_HIGH`` and
``express`` (not held back to fill a batch), ahead of bulk on the same link: a capped radio
link busy with keyframes still carries them at once (``benchmarks/links.py``). An agent's
own messages go at ``DATA``, all of them: they form one sequence, which the coordinator
takes in order, and Zenoh keeps order only within a priority.

Zenoh's callbacks only queue; decoding, answering task queries and admitting processes
happen on the coordinator's own thread, in arrival order, and sends go through a background
thread, so neither side ever blocks Zenoh or its own loop.
"""

from __future__ import annotations

import json
import logging
import queue
import struct
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from como3r.errors import InputError, MessageError
from como3r.transport import codec
from como3r.transport.links import Event, Joined, Left, Received, Rejected, Rejoin, Traffic
from como3r.transport.messages import FROM_AGENT, AgentTask, KeyframeMessage, Shutdown

logger = logging.getLogger(__name__)

SEQ = struct.Struct("<QQ")  # incarnation, sequence number
PIECE = struct.Struct("<QQII")  # incarnation, sequence number, piece index, pieces
#: the largest piece of a message an agent puts at once (see "Pieces" above): 1 s of a
#: 1 Mbit/s link
PIECE_BYTES = 128 * 1024
INCARNATION = struct.Struct("<Q")
#: the start of a task query's error that means "ask again later", not "give up"
WAIT = "wait: "
#: Zenoh's own log in a team run: its TLS layer's refusals (not its name-check notice)
ZENOH_TEAM_LOG = "error,zenoh_link_tls=warn,zenoh_link_tls::utils=error"


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
        settings: Zenoh configuration entries ``(path, JSON value)`` set last: a team
            member's mutual TLS and access control
            (:func:`como3r.transport.team_access.zenoh_settings`).
        member: a team member's certificate name (its message keys end in it); None: an
            open network.
        on_open: called with the session once it is open (a team member's watch on who
            connects, :class:`como3r.transport.team_access.LinkWatch`).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    scouting: bool = False
    config_file: Path | None = None
    session: str = "como3r"
    settings: tuple[tuple[str, str], ...] = ()
    member: str | None = None
    on_open: Callable[[Any], None] | None = field(default=None, compare=False)

    def where(self) -> str:
        """Where this process looks for its peers, for a person (``session 'como3r',
        connecting to tcp/10.0.0.2:7447``): what to check when nobody answers."""
        parts = [f"session {self.session!r}"]
        if self.connect:
            parts.append(f"connecting to {', '.join(self.connect)}")
        if self.listen:
            parts.append(f"listening on {', '.join(self.listen)}")
        if self.scouting:
            parts.append("scouting by UDP multicast")
        if self.config_file is not None:
            parts.append(f"Zenoh configuration {self.config_file}")
        return ", ".join(parts)


def open_session(options: ZenohOptions) -> Any:
    """A Zenoh session in peer mode on ``options``.

    Raises:
        InputError: an unreadable configuration file, a bad endpoint or a port in use.
    """
    import zenoh

    try:
        config = (
            zenoh.Config.from_file(str(options.config_file))
            if options.config_file is not None
            else zenoh.Config()
        )
        config.insert_json5("mode", json.dumps("peer"))
        config.insert_json5("scouting/multicast/enabled", json.dumps(options.scouting))
        if options.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
        if options.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
        for path, value in options.settings:
            config.insert_json5(path, value)
        if options.settings:  # Zenoh logs the peers its TLS handshake refuses, and why
            zenoh.init_log_from_env_or(ZENOH_TEAM_LOG)
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        where = f" ({options.config_file})" if options.config_file is not None else ""
        raise InputError(f"zenoh{where}: {' '.join(str(exc).split())}") from None
    if options.on_open is not None:
        options.on_open(session)
    return session


class Keys:
    """The key expressions of one session (see the module docstring)."""

    def __init__(self, session: str, member: str | None = None) -> None:
        if not session or any(c in session for c in "/*$?#"):
            raise InputError(f"session name {session!r}: use letters, digits, - and _")
        self.root = f"como3r/{session}"
        self.member = member  # this process's certificate name in a team run

    def coordinator(self) -> str:
        return f"{self.root}/coordinator"

    def agent(self, agent: int | str) -> str:
        return f"{self.root}/agent/{agent}"

    def task(self, agent: int | str) -> str:
        return f"{self.agent(agent)}/task"

    def up(self, agent: int | str, kind: str) -> str:
        key = f"{self.agent(agent)}/up/{kind}"
        return key if self.member is None else f"{key}/{self.member}"

    def up_all(self) -> str:
        """Every agent's messages to the coordinator, team run or not."""
        return f"{self.agent('*')}/up/**"

    def sender_of(self, key: str) -> str | None:
        """The certificate name a message key under ``up/`` ends in (None: none)."""
        parts = key[len(self.root) + len("/agent/") :].split("/")
        return parts[3] if len(parts) > 3 else None

    def down(self, agent: int | str, kind: str) -> str:
        return f"{self.agent(agent)}/down/{kind}"

    def ack(self, agent: int | str) -> str:
        return f"{self.agent(agent)}/ack"

    def alive(self, agent: int | str, incarnation: int | str) -> str:
        """The liveliness token of agent ``agent``'s process ``incarnation`` (an int, or
        ``*`` in a subscription)."""
        label = f"{incarnation:016x}" if isinstance(incarnation, int) else incarnation
        return f"{self.agent(agent)}/alive/{label}"

    def agent_of(self, key: str) -> str:
        """The agent field of a key under ``agent/`` (as written: not checked)."""
        return key[len(self.root) + len("/agent/") :].split("/", 1)[0]


#: Zenoh priority of what the coordinator sends (acknowledgements, pose updates, Shutdown)
CONTROL_PRIORITY = "INTERACTIVE_HIGH"
#: Zenoh priority of an agent's messages (keyframes and the rest of its ordered stream)
STREAM_PRIORITY = "DATA"


class Sender:
    """Puts ``(key, payload, attachment)`` on the network from a background thread.

    Args:
        session: the Zenoh session.
        publishers: declared publishers by key (declared with congestion control
            ``BLOCK``); a key without one is put through the session.
        priority: the Zenoh priority (a ``zenoh.Priority`` name) of the session's puts.
        express: send each put at once instead of batching it with the next.
    """

    def __init__(
        self,
        session: Any,
        publishers: dict[str, Any] | None = None,
        priority: str = STREAM_PRIORITY,
        express: bool = False,
    ) -> None:
        import zenoh

        self.session = session
        self.publishers = publishers if publishers is not None else {}
        self.block = zenoh.CongestionControl.BLOCK
        self.priority = getattr(zenoh.Priority, priority)
        self.express = express
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
                if key in self.publishers:
                    self.publishers[key].put(payload, attachment=attachment)
                else:
                    self.session.put(
                        key,
                        payload,
                        attachment=attachment,
                        congestion_control=self.block,
                        priority=self.priority,
                        express=self.express,
                    )
            except Exception as exc:  # a closed session: nothing more can be sent
                logger.debug("put on %s failed: %s", key, exc)


class Pieces:
    """Joins the pieces of the agents' messages (one message at a time per agent, its pieces
    in order).

    Args:
        max_bytes: size cap of one whole message.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._open: dict[str, tuple[tuple[int, int, int], list[bytes], int]] = {}
        self._lock = threading.Lock()  # Zenoh may call back from several threads

    def add(self, agent: str, attachment: bytes, data: bytes) -> tuple[bytes, bytes] | str | None:
        """Take one piece (``attachment`` of :data:`PIECE`) of agent ``agent``'s message.

        Returns:
            ``(attachment, payload)`` of the whole message (its attachment a :data:`SEQ`)
            once its last piece is in; a reason to reject it once it exceeds the cap; None
            while it is incomplete, and for a piece out of order (dropped, with what came
            of its message).
        """
        incarnation, seq, index, count = PIECE.unpack(attachment)
        which = (incarnation, seq, count)
        with self._lock:
            if index == 0:
                self._open[agent] = (which, [], 0)
            current = self._open.get(agent)
            if current is None or current[0] != which or len(current[1]) != index:
                self._open.pop(agent, None)
                logger.debug(
                    "agent %s: piece %d of message %d out of order: dropped", agent, index, seq
                )
                return None
            _, parts, size = current
            size += len(data)
            if size > self.max_bytes:
                del self._open[agent]
                return f"message of over {size} bytes exceeds the cap of {self.max_bytes} bytes"
            parts.append(data)
            if index + 1 < count:
                self._open[agent] = (which, parts, size)
                return None
            del self._open[agent]
            return SEQ.pack(incarnation, seq), b"".join(parts)


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
        certified: a team run: a message counts only if its key ends in the certificate
            name of the agent it claims to come from (Zenoh's access control makes that
            name its sender's, :mod:`como3r.transport.team_access`).
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
        self._sender = Sender(session, priority=CONTROL_PRIORITY, express=True)
        self._pieces = Pieces(max_bytes)
        self._declared = [
            session.declare_subscriber(keys.up_all(), self._on_sample),
            session.liveliness().declare_subscriber(
                keys.alive("*", "*"), self._on_liveliness, history=True
            ),
        ]
        self._stopped = False

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
        if len(attachment) == PIECE.size and self._agent_id(agent) is not None:
            whole = self._pieces.add(agent, attachment, data)
            if isinstance(whole, str):
                self._inbox.put(("reject", agent, whole))
            if not isinstance(whole, tuple):
                return
            attachment, data = whole
        self._inbox.put(("message", agent, attachment, data))

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
            out.extend(self._event(self._backlog.popleft()))
        return out

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
        holder.ack_due, holder.dropped = False, False
        holder.task = (
            answer if isinstance(answer, bytes) else codec.encode(answer, max_bytes=self.max_bytes)
        )
        _reply(query, holder.task)
        return [Joined(agent)] if incarnation in holder.present else []

    def _message(self, agent: int, attachment: bytes, data: bytes) -> Event | None:
        if len(attachment) != SEQ.size:
            return Rejected(agent, "no sequence number attached")
        incarnation, seq = SEQ.unpack(attachment)
        holder = self._holders[agent]
        if incarnation != holder.incarnation:
            _, error = self._decode(agent, data)
            return Rejected(
                agent,
                error
                or f"from process {incarnation:016x}, which does not "
                f"hold agent {agent}'s id ({holder.describe()})",
            )
        if holder.dropped:
            logger.debug("agent %d counts as failed: message %d ignored", agent, seq)
            return None
        if seq < holder.next_seq:  # re-sent after a reconnect: stored already
            holder.ack_due = True
            return None
        if seq > holder.next_seq:
            return Rejected(
                agent, f"message {seq} before {holder.next_seq} (a gap: the agent re-sends)"
            )
        holder.next_seq += 1  # the holder's own: taken, or skipped, never waited for
        message, error = self._decode(agent, data)
        if error is not None:
            return Rejected(agent, error)
        self._traffic[agent].received(message, len(data))
        return Received(agent, message, seq)

    def _decode(self, agent: int, data: bytes) -> tuple[Any, str | None]:
        """The message of ``data`` sent under agent ``agent``'s key, or why it is not one."""
        try:
            message = codec.decode(data, max_bytes=self.max_bytes, expected=FROM_AGENT)
        except MessageError as exc:
            return None, str(exc)
        sender = message.packet.agent if isinstance(message, KeyframeMessage) else message.agent
        if sender != agent:
            return None, f"an {type(message).__name__} of agent {sender} under agent {agent}'s key"
        return message, None

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
        if self._stopped:
            return
        self._stopped = True
        for agent in live:
            self.send(agent, Shutdown("the coordinator is stopping"))
        self._sender.close(self.grace_s)
        for entity in reversed(self._declared):
            entity.undeclare()

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
