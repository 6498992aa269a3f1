"""How agents and the coordinator reach each other (C-Sec. B.1; manual:
docs/architecture.md, "Processes and messages").

Both ends exchange the typed messages of :mod:`como3r.transport.messages`, encoded by
:mod:`como3r.transport.codec` (no pickle). What carries them is a transport with two faces:

* an agent holds an :class:`AgentLink` (``send``, ``poll``, ``receive``, ``close``): sends
  never block its frame loop, and ``close`` returns only once the coordinator has every
  message the agent sent (or is gone for good), so a slow coordinator never costs a message;
* the coordinator holds a :class:`Hub` over all agents: :meth:`Hub.events` hands over what
  arrived as :class:`Received`, :class:`Rejected`, :class:`Joined` and :class:`Left`
  events, in arrival order per agent, and :meth:`Hub.acknowledge` says which of them are
  stored (the runtime may still hold some back: keyframes waiting for their turn).

Two transports implement it: pipes to child processes (:mod:`como3r.transport.pipes`;
``como3r run``) and Zenoh across machines (:mod:`como3r.transport.zenoh_protocol`;
``como3r coordinator`` / ``como3r agent``). The runtime above them
(:mod:`como3r.runtime.processes`, :mod:`como3r.runtime.agent_worker`) is the same.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from como3r.transport.messages import AgentTask

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ events


@dataclass(frozen=True)
class Received:
    """A valid message from ``agent``; ``seq`` is its number in the sending process's
    stream where the transport numbers messages (None: pipes, which lose nothing);
    ``seconds``: its decode here (a keyframe's lossy codings: the coordinator's ingest),
    the CPU time of the thread that decoded it (pipes: :mod:`.pipe_readers`, Zenoh:
    :mod:`.zenoh_decoding`); ``data``: a keyframe message's bytes, which a receiver that
    holds it waiting keeps in place of the decoded message (a tenth of its size)."""

    agent: int
    message: Any
    seq: int | None = None
    seconds: float = 0.0
    data: bytes | None = None


@dataclass(frozen=True)
class Rejected:
    """Bytes claiming to come from ``agent`` that are not an acceptable message: logged and
    dropped, never fatal to the coordinator."""

    agent: int
    error: str


@dataclass(frozen=True)
class Joined:
    """``agent`` is reachable (its process started, or its liveliness token appeared)."""

    agent: int


@dataclass(frozen=True)
class Left:
    """``agent`` is gone: its process ended or its link was lost (``reason`` says which).

    ``may_return``: the link was lost, not the process seen ending (a network transport
    cannot tell a crash from a radio gap): the agent may reconnect, or a new process may
    take over its id (see :data:`Rejoin`)."""

    agent: int
    reason: str
    may_return: bool = False


Event = Received | Rejected | Joined | Left

Rejoin = Callable[[int], AgentTask | str]
"""Asked by a hub when a new process wants agent ``a``'s id after the one that held it left:
the task the newcomer runs, or why it cannot take over (a reason it is told)."""


@dataclass
class SendBacklog:
    """What a rate-limited sender had queued, as it said with its messages
    (:mod:`como3r.transport.pacing`).

    Attributes:
        max_mbps: its rate limit, Mbit/s (None: none, or nothing heard yet).
        last_bytes: bytes it had queued after its latest message.
        peak_bytes: the most it had queued after any message.
    """

    max_mbps: float | None = None
    last_bytes: int = 0
    peak_bytes: int = 0

    def note(self, queued: int, rate: float) -> None:
        """A message came with ``queued`` bytes behind it at ``rate`` bytes/s (0: none)."""
        self.max_mbps = rate * 8 / 1e6 if rate > 0 else None
        self.last_bytes, self.peak_bytes = queued, max(self.peak_bytes, queued)

    def to_json(self) -> dict[str, Any]:
        """``metrics.json``'s ``send_backlog``: bytes and, under a rate limit, seconds
        (queued bytes over the rate)."""
        rate = None if self.max_mbps is None else self.max_mbps * 1e6 / 8
        return {
            "max_mbps": self.max_mbps,
            "peak_bytes": self.peak_bytes,
            "peak_s": None if rate is None else self.peak_bytes / rate,
            "last_bytes": self.last_bytes,
            "last_s": None if rate is None else self.last_bytes / rate,
        }


@dataclass
class Traffic:
    """Bytes and messages per message type, both directions, as seen by one end, and the
    backlog the other end said it had (a rate-limited Zenoh agent)."""

    bytes_sent: Counter[str] = field(default_factory=Counter)
    bytes_received: Counter[str] = field(default_factory=Counter)
    messages_sent: Counter[str] = field(default_factory=Counter)
    messages_received: Counter[str] = field(default_factory=Counter)
    backlog: SendBacklog | None = None

    def sent(self, message: Any, nbytes: int) -> None:
        """Count one message sent."""
        self.bytes_sent[type(message).__name__] += nbytes
        self.messages_sent[type(message).__name__] += 1

    def received(self, message: Any, nbytes: int) -> None:
        """Count one message received."""
        self.bytes_received[type(message).__name__] += nbytes
        self.messages_received[type(message).__name__] += 1


class AgentLink(Protocol):
    """An agent's end of the transport."""

    traffic: Traffic

    def send(self, message: Any) -> None:
        """Encode and queue ``message`` for the coordinator; never blocks on the network."""

    def poll(self, timeout: float = 0.0) -> bool:
        """Whether a message from the coordinator waits (or the link ended)."""

    def receive(self) -> Any:
        """The next message from the coordinator (blocking).

        Raises:
            EOFError: the coordinator closed the link for good.
            MessageError: bytes that are not an acceptable message.
        """

    def close(self) -> None:
        """Return once the coordinator holds every message sent (or is gone), then close."""


class Hub(Protocol):
    """The coordinator's end of the transport, over agents ``0 .. N-1``."""

    name: str
    """What carries the messages (``metrics.json``: ``runtime.transport``)."""

    def start(self, tasks: Sequence[AgentTask], rejoin: Rejoin) -> None:
        """Make each agent's task available to it (pipes: start its process and send it);
        ``rejoin`` decides on a process taking over the id of an agent that left (only
        transports whose agents start on their own ask it)."""

    def events(self, timeout: float) -> list[Event]:
        """What arrived, waiting up to ``timeout`` seconds for the first event."""

    def durable(self, held: Mapping[int, int]) -> dict[str, Any]:
        """What this hub needs to continue after the coordinator restarts (JSON-able; see
        :meth:`resume`), once the messages :meth:`acknowledge` with ``held`` would
        acknowledge are stored."""

    def acknowledge(self, held: Mapping[int, int]) -> None:
        """Every message handed over by :meth:`events` so far is stored, except agent
        ``a``'s from its number ``held[a]`` on (what the runtime still holds back)."""

    def resume(self, state: Mapping[str, Any]) -> dict[int, int]:
        """Continue from :meth:`durable`'s state (a coordinator resumed from its store),
        before :meth:`start`; returns per agent the number of the last message of its
        process's stream that is stored (its process re-sends the later ones)."""

    def send(self, agent: int, message: Any) -> None:
        """Queue ``message`` for ``agent``; never blocks on the network."""

    def drop(self, agent: int) -> None:
        """Stop a failed agent (it may still be running); what it sends from now on is not
        acknowledged as stored."""

    def stop(self, live: Sequence[int], interrupted: bool) -> None:
        """Ask the ``live`` agents to stop (at once when ``interrupted``), release all."""

    def traffic(self, agent: int) -> Traffic:
        """What crossed to and from ``agent``, counted at this end."""

    def exitcode(self, agent: int) -> int | None:
        """The agent process's exit status where this end started it, else None."""
