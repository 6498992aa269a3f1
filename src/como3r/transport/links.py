"""How agents and the coordinator reach each other (C-Sec. B.1; DESIGN.md, "One frame loop,
one transport").

Both ends exchange the typed messages of :mod:`como3r.transport.messages`, encoded by
:mod:`como3r.transport.codec` (no pickle). What carries them is a transport with two faces:

* an agent holds an :class:`AgentLink` (``send``, ``poll``, ``receive``, ``close``): sends
  never block its frame loop, and ``close`` returns only once the coordinator has every
  message the agent sent (or is gone for good), so a slow coordinator never costs a message;
* the coordinator holds a :class:`Hub` over all agents: :meth:`Hub.events` hands over what
  arrived as :class:`Received`, :class:`Rejected`, :class:`Joined` and :class:`Left`
  events, in arrival order per agent, and :meth:`Hub.acknowledge` says which of them are
  stored (the runtime may still hold some back: keyframes waiting for their turn).

Two transports implement it: pipes to child processes (:class:`PipeHub`, :class:`Channel`;
``como3r run``) and Zenoh across machines (:mod:`como3r.transport.zenoh_protocol`;
``como3r coordinator`` / ``como3r agent``). The runtime above them
(:mod:`como3r.runtime.processes`, :mod:`como3r.runtime.agent_worker`) is the same.
"""

from __future__ import annotations

import logging
import multiprocessing
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

from como3r.errors import MessageError
from como3r.transport import codec
from como3r.transport.child_signals import children_ignore_sigint
from como3r.transport.messages import FROM_AGENT, AgentTask, Shutdown

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ events


@dataclass(frozen=True)
class Received:
    """A valid message from ``agent``; ``seq`` is its number in the sending process's
    stream where the transport numbers messages (None: pipes, which lose nothing)."""

    agent: int
    message: Any
    seq: int | None = None


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
class Traffic:
    """Bytes and messages per message type, both directions, as seen by one end."""

    bytes_sent: Counter[str] = field(default_factory=Counter)
    bytes_received: Counter[str] = field(default_factory=Counter)
    messages_sent: Counter[str] = field(default_factory=Counter)
    messages_received: Counter[str] = field(default_factory=Counter)

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


# ------------------------------------------------------------------------------ pipes


class Channel:
    """Typed messages over two one-way pipes; sends go through a background thread.

    Args:
        inbox: the receiving end, or None.
        outbox: the sending end, or None.
        max_bytes: size cap of a message in either direction.
        accepts: message classes :meth:`receive` accepts.
    """

    def __init__(
        self,
        inbox: Connection | None,
        outbox: Connection | None,
        max_bytes: int,
        accepts: tuple[type, ...],
    ) -> None:
        self.inbox = inbox
        self.outbox = outbox
        self.max_bytes = max_bytes
        self.accepts = accepts
        self.traffic = Traffic()
        self.broken = False
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._sender: threading.Thread | None = None
        if outbox is not None:
            self._sender = threading.Thread(target=self._send_loop, daemon=True)
            self._sender.start()

    def send(self, message: Any) -> None:
        """Encode ``message`` and queue it; never blocks on the pipe."""
        data = codec.encode(message, max_bytes=self.max_bytes)
        self.traffic.sent(message, len(data))
        self._queue.put(data)

    def poll(self, timeout: float = 0.0) -> bool:
        """Whether a message (or end of stream) is waiting."""
        return self.inbox is not None and self.inbox.poll(timeout)

    def receive(self) -> Any:
        """The next message (blocking).

        Raises:
            EOFError: the other side closed the pipe.
            MessageError: the bytes are not an acceptable message.
            OSError: the pipe's framing is unreadable (the stream is lost).
        """
        assert self.inbox is not None
        data = self.inbox.recv_bytes(self.max_bytes)
        message = codec.decode(data, max_bytes=self.max_bytes, expected=self.accepts)
        self.traffic.received(message, len(data))
        return message

    def close(self, timeout: float | None = None) -> None:
        """Flush queued messages and close both ends.

        Args:
            timeout: seconds to wait for the flush; None waits until the other side has
                read everything or is gone. An agent closes with None: its last messages
                (keyframes, the final report) sit in the pipe for as long as the
                coordinator is busy (a global BA can take minutes), and closing the pipe
                under a half-sent message made the coordinator read a truncated one and
                count a finished agent as failed.
        """
        if self._sender is not None:
            self._queue.put(None)
            self._sender.join(timeout)
        for conn in (self.inbox, self.outbox):
            if conn is not None:
                conn.close()

    def _send_loop(self) -> None:
        assert self.outbox is not None
        while (data := self._queue.get()) is not None:
            if self.broken:
                continue
            try:
                self.outbox.send_bytes(data)
            except OSError:  # the other side is gone; later messages are dropped too
                self.broken = True


def exit_reason(code: int | None) -> str:
    """``killed by signal N`` or ``exit code N`` of a process's exit status."""
    return f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"


class PipeHub:
    """One spawned process per agent, two pipes each (``como3r run``).

    Args:
        target: the agent processes' entry point, ``target(agent, inbox, outbox)``.
        max_bytes: size cap of one message.
        grace_s: how long a stopping agent may take before it is terminated.
    """

    name = "pipes"

    def __init__(
        self, target: Callable[[int, Connection, Connection], None], max_bytes: int, grace_s: float
    ) -> None:
        self.target = target
        self.max_bytes = max_bytes
        self.grace_s = grace_s
        self.processes: dict[int, Any] = {}
        self.channels: dict[int, Channel] = {}
        self._open: set[int] = set()  # inbox not at end of stream
        self._gone: set[int] = set()  # Left reported

    def start(self, tasks: Sequence[AgentTask], rejoin: Rejoin) -> None:
        """Start one process per task and send it its task. ``rejoin`` is never asked: a
        process this hub started that ends is gone for good."""
        context = multiprocessing.get_context("spawn")
        for task in tasks:
            to_agent_r, to_agent_w = context.Pipe(duplex=False)
            from_agent_r, from_agent_w = context.Pipe(duplex=False)
            process = context.Process(
                target=self.target,
                args=(task.agent, to_agent_r, from_agent_w),
                name=f"como3r-agent-{task.agent}",
                daemon=True,
            )
            with children_ignore_sigint():  # Ctrl-C is the coordinator's to handle
                process.start()
            to_agent_r.close()  # the child holds its own copies; ours would hide its death
            from_agent_w.close()
            channel = Channel(from_agent_r, to_agent_w, self.max_bytes, FROM_AGENT)
            channel.send(task)
            self.processes[task.agent], self.channels[task.agent] = process, channel
            self._open.add(task.agent)

    def events(self, timeout: float) -> list[Event]:
        handles: dict[Any, int] = {}
        for agent, process in self.processes.items():
            if agent not in self._gone:
                handles[process.sentinel] = agent
                if agent in self._open:
                    handles[self.channels[agent].inbox] = agent
        if not handles:
            return []
        ready = wait(list(handles), timeout)
        out: list[Event] = []
        for handle in ready:  # messages first: an exited agent's last words are in its pipe
            if handle is not self.processes[handles[handle]].sentinel:
                out.extend(self._drain(handles[handle]))
        for handle in ready:
            agent = handles[handle]
            if handle is self.processes[agent].sentinel:
                out.extend(self._drain(agent))
                self.processes[agent].join(5.0)  # the sentinel fires just before the status
                self._gone.add(agent)
                out.append(
                    Left(agent, f"process died ({exit_reason(self.processes[agent].exitcode)})")
                )
        return out

    def _drain(self, agent: int) -> list[Event]:
        channel, out = self.channels[agent], []
        while agent in self._open:
            try:
                if not channel.poll(0.0):
                    break
                message = channel.receive()
            except EOFError:
                self._open.discard(agent)
            except OSError as exc:  # the framing is lost: nothing after it can be read
                self._open.discard(agent)
                self.drop(agent)
                out.append(
                    Left(
                        agent,
                        f"protocol error: unreadable message ({exc}); cap {self.max_bytes} bytes",
                    )
                )
                self._gone.add(agent)
            except MessageError as exc:
                out.append(Rejected(agent, str(exc)))
            else:
                out.append(Received(agent, message))
        return out

    def durable(self, held: Mapping[int, int]) -> dict[str, Any]:
        """Nothing: agents on pipes end with the coordinator."""
        return {}

    def acknowledge(self, held: Mapping[int, int]) -> None:
        """Nothing to do: a pipe's writer is done once its reader took the bytes."""

    def resume(self, state: Mapping[str, Any]) -> dict[int, int]:
        """Nothing to continue: a resumed run starts its agents' processes afresh."""
        return {}

    def send(self, agent: int, message: Any) -> None:
        self.channels[agent].send(message)

    def drop(self, agent: int) -> None:
        if self.processes[agent].is_alive():
            self.processes[agent].terminate()

    def stop(self, live: Sequence[int], interrupted: bool) -> None:
        for agent, process in self.processes.items():
            if process.is_alive() and interrupted:
                process.terminate()
            elif process.is_alive() and agent in live:
                self.channels[agent].send(Shutdown("the coordinator is stopping"))
        deadline = time.monotonic() + self.grace_s
        for agent, process in self.processes.items():
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.terminate()
                process.join(self.grace_s)
            self.channels[agent].close(timeout=self.grace_s)

    def traffic(self, agent: int) -> Traffic:
        return self.channels[agent].traffic

    def exitcode(self, agent: int) -> int | None:
        return self.processes[agent].exitcode
