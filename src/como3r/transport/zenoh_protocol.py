"""The transport across machines: Zenoh in peer mode (``como3r coordinator`` / ``agent``);
what both ends share. The coordinator's end is :mod:`.zenoh_hub`, an agent's
:mod:`.zenoh_agent`.

The typed msgpack messages of :mod:`como3r.transport.messages` are the payloads, unchanged.
Key expressions name the session, the agent and the message kind::

    como3r/<session>/coordinator              liveliness token of the coordinator
    como3r/<session>/agent/<a>/alive/<inc>    liveliness token of agent a's process with
                                              incarnation <inc> (16 hex digits, random per
                                              process): join / leave
    como3r/<session>/agent/<a>/task           queryable: agent a's AgentTask; the query's
                                              attachment <Q: the asking process's incarnation
    como3r/<session>/agent/<a>/up/<Type>      agent -> coordinator; attachment <QQQd:
                                              incarnation, seq, the sender's backlog
                                              (bytes queued after this put) and rate
                                              limit (bytes/s, 0: none); or, for each piece
                                              of a message over PIECE_BYTES, <QQIIQd:
                                              incarnation, seq, piece, pieces, backlog,
                                              rate; in a team run the key ends in
                                              /<sender's certificate name>
    como3r/<session>/agent/<a>/up/Bye         agent -> coordinator, attachment <Q: its
                                              incarnation: every message is stored and
                                              the process leaves (:data:`BYE`)
    como3r/<session>/agent/<a>/down/<Type>    coordinator -> agent; attachment <Q: the
                                              incarnation it is meant for
    como3r/<session>/agent/<a>/ack            coordinator -> agent <QQ: incarnation, the
                                              last seq stored (every one up to it is)

Delivery is reliable with congestion control ``BLOCK`` (``DROP`` loses messages under a
slow subscriber), and acknowledged: an agent keeps every message until the coordinator has
stored it (:mod:`como3r.transport.spool`: in memory, on disk past a limit), re-sends the
unacknowledged ones when the coordinator's token reappears, and leaves
(:class:`~como3r.transport.zenoh_agent.ZenohAgentLink`) only once the last one is stored. The
coordinator takes an agent's messages in sequence, drops duplicates of re-sent ones, notes the backlog
the agent says it has (``metrics.json``: ``bandwidth[].send_backlog``), and
logs and drops whatever is not a valid message (oversized, malformed, unknown agent, a
process that does not hold the agent's id). "Stored" means in the session store: the
runtime acknowledges a message once its effect is committed there (a keyframe waiting for
its turn is not, nor is anything after it), and the hub's own state (who holds each id,
where its stream is) goes into the same store first
(:meth:`~como3r.transport.zenoh_hub.ZenohHub.durable`), so a coordinator restarted with
``--resume`` (:meth:`~como3r.transport.zenoh_hub.ZenohHub.resume`) takes each agent's stream
up where the store has it and the agents' re-sent messages fill in the rest.

Leaving. The last acknowledgement can be lost like any other (a link cut as it goes out),
and a coordinator that has stored everything may end its run while an agent still waits for
it. So an agent that has its last acknowledgement says so (``Bye``) as it leaves, and the
coordinator, its outputs written, waits for the ``Bye`` of every agent it acknowledged
(:meth:`~como3r.transport.zenoh_hub.ZenohHub.linger`, up to ``--away-timeout``), answering
what a reconnecting agent re-sends.

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

Rate. Under ``--max-mbps`` (:attr:`ZenohOptions.max_mbps`) what a process puts goes at most
at that rate (:mod:`como3r.transport.pacing`): an agent's pieces one by one as its token
bucket allows, so Zenoh's queue holds at most a piece of a keyframe ahead of anything else;
the :class:`Sender` of the coordinator and of a robot puts small messages ahead of large
ones.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from como3r.errors import InputError
from como3r.transport.pacing import Lanes, bytes_per_s

logger = logging.getLogger(__name__)

SEQ = struct.Struct("<QQ")  # incarnation, sequence number (an acknowledgement)
#: incarnation, sequence number, the sender's backlog in bytes, its rate limit in bytes/s
STREAM = struct.Struct("<QQQd")
#: incarnation, sequence number, piece index, pieces, backlog, rate (as :data:`STREAM`)
PIECE = struct.Struct("<QQIIQd")
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
        max_mbps: the rate limit of what this process sends, Mbit/s (``--max-mbps``; 0:
            none; :mod:`como3r.transport.pacing`).
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    scouting: bool = False
    config_file: Path | None = None
    session: str = "como3r"
    settings: tuple[tuple[str, str], ...] = ()
    member: str | None = None
    on_open: Callable[[Any], None] | None = field(default=None, compare=False)
    max_mbps: float = 0.0

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

    def kind_of(self, key: str) -> str | None:
        """The message kind of a key under ``up/`` (None: not such a key)."""
        parts = self._fields(key)
        return parts[2] if len(parts) > 2 and parts[1] == "up" else None

    def sender_of(self, key: str) -> str | None:
        """The certificate name a message key under ``up/`` ends in (None: none)."""
        parts = self._fields(key)
        return parts[3] if len(parts) > 3 else None

    def _fields(self, key: str) -> list[str]:
        """The fields of a key under ``agent/``: the agent, then what follows it."""
        return key[len(self.root) + len("/agent/") :].split("/")

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
        return self._fields(key)[0]


#: the message kind (``up/<Type>``) of an agent's last put: it has its last acknowledgement
BYE = "Bye"

#: Zenoh priority of what the coordinator sends (acknowledgements, pose updates, Shutdown)
CONTROL_PRIORITY = "INTERACTIVE_HIGH"
#: Zenoh priority of an agent's messages (keyframes and the rest of its ordered stream)
STREAM_PRIORITY = "DATA"


class Sender:
    """Puts ``(key, payload, attachment)`` on the network from a background thread, at most
    ``max_mbps`` (:mod:`como3r.transport.pacing`: control before bulk).

    Args:
        session: the Zenoh session.
        publishers: declared publishers by key (declared with congestion control
            ``BLOCK``); a key without one is put through the session.
        priority: the Zenoh priority (a ``zenoh.Priority`` name) of the session's puts.
        express: send each put at once instead of batching it with the next.
        max_mbps: the rate limit of this process's link (0: none).
        control: which puts go in the control lane, by payload size (default: all; a put
            order that matters within a lane is kept, not across lanes).
    """

    def __init__(
        self,
        session: Any,
        publishers: dict[str, Any] | None = None,
        priority: str = STREAM_PRIORITY,
        express: bool = False,
        max_mbps: float = 0.0,
        control: Callable[[int], bool] = lambda nbytes: True,
    ) -> None:
        import zenoh

        self.session = session
        self.publishers = publishers if publishers is not None else {}
        self.block = zenoh.CongestionControl.BLOCK
        self.priority = getattr(zenoh.Priority, priority)
        self.express = express
        self.control = control
        self.lanes: Lanes[tuple[str, bytes, bytes | None]] = Lanes(bytes_per_s(max_mbps))
        self.bytes_put = 0
        self._closing = False
        self._cond = threading.Condition()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        with self._cond:
            self.lanes.add((key, payload, attachment), len(payload), self.control(len(payload)))
            self._cond.notify_all()

    def close(self, timeout: float) -> None:
        """Put what is queued (for up to ``timeout`` seconds), then stop."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while True:
                    item, wait = self.lanes.next()
                    if item is not None or (self._closing and not len(self.lanes)):
                        break
                    self._cond.wait(None if wait == float("inf") else wait)
            if item is None:
                return
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
                self.bytes_put += len(payload)
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
            ``(attachment, payload)`` of the whole message (its attachment a :data:`STREAM`
            with the last piece's backlog)
            once its last piece is in; a reason to reject it once it exceeds the cap; None
            while it is incomplete, and for a piece out of order (dropped, with what came
            of its message).
        """
        incarnation, seq, index, count, backlog, rate = PIECE.unpack(attachment)
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
            return STREAM.pack(incarnation, seq, backlog, rate), b"".join(parts)
