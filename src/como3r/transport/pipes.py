"""The transport on one machine: two one-way pipes per agent process (``como3r run``).

:class:`PipeHub` is the coordinator's :class:`~como3r.transport.links.Hub`: it starts one
process per agent and talks to it over a :class:`Channel`, the agent's
:class:`~como3r.transport.links.AgentLink`. Only raw bytes of
:mod:`como3r.transport.codec` cross the pipes (``Connection.send_bytes``, never ``send``,
which pickles).
"""

from __future__ import annotations

import logging
import multiprocessing
import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from multiprocessing.connection import Connection
from typing import Any

from como3r.transport import codec
from como3r.transport.child_signals import children_ignore_sigint
from como3r.transport.links import Event, Left, Received, Rejected, Rejoin, Traffic
from como3r.transport.messages import FROM_AGENT, AgentTask, Shutdown
from como3r.transport.pipe_readers import READ_AHEAD_BYTES, Died, PipeReader

logger = logging.getLogger(__name__)


#: what an agent process codes exactly all the same (:class:`Channel`'s ``coded``): a
#: keyframe's encoding, as the single-process ingest hands it over (never float16 tokens)
EXACT_ON_PIPES = frozenset({"KeyframePacket.encoding"})


class Channel:
    """Typed messages over two one-way pipes; sends go through a background thread.

    Args:
        inbox: the receiving end, or None.
        outbox: the sending end, or None.
        max_bytes: size cap of a message in either direction.
        accepts: message classes :meth:`receive` accepts.
        coded: send in the lossy wire codings, as a link across machines does, but each
            keyframe's encoding exact (:data:`EXACT_ON_PIPES`): an agent process's end,
            so that the coordinator only decodes what it would code otherwise
            (:mod:`como3r.runtime.ingest`). Else every message is sent bit-exact.
    """

    def __init__(
        self,
        inbox: Connection | None,
        outbox: Connection | None,
        max_bytes: int,
        accepts: tuple[type, ...],
        coded: bool = False,
    ) -> None:
        self.inbox = inbox
        self.outbox = outbox
        self.max_bytes = max_bytes
        self.accepts = accepts
        self.coded = coded
        self.traffic = Traffic()
        self.broken = False
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._sender: threading.Thread | None = None
        if outbox is not None:
            self._sender = threading.Thread(target=self._send_loop, daemon=True)
            self._sender.start()

    def send(self, message: Any) -> None:
        """Encode ``message`` and queue it; never blocks on the pipe."""
        data = codec.encode(
            message, max_bytes=self.max_bytes, lossy=self.coded, exact=EXACT_ON_PIPES
        )
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
        return self.receive_timed()[0]

    def receive_timed(self) -> tuple[Any, float]:
        """The next message (blocking) and the CPU seconds its decode took on this thread;
        raises as :meth:`receive`."""
        assert self.inbox is not None
        data = self.inbox.recv_bytes(self.max_bytes)
        message, seconds = self.decode(data)
        self.traffic.received(message, len(data))
        return message, seconds

    def decode(self, data: bytes) -> tuple[Any, float]:
        """The message of ``data`` as received here (not counted in :attr:`traffic`) and
        the CPU seconds (``time.thread_time``) its decode took on the calling thread.

        Raises:
            MessageError: the bytes are not an acceptable message.
        """
        start = time.thread_time()
        message = codec.decode(data, max_bytes=self.max_bytes, expected=self.accepts)
        return message, time.thread_time() - start

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

    Each agent's pipe is read and decoded by a :class:`~.pipe_readers.PipeReader` thread
    as its messages arrive; :meth:`events` only collects what the readers decoded, so the
    decode (the lossy codings of keyframes and refreshes) is off the coordinator's thread.
    ``Received.seconds`` is that decode's CPU time on its reader's thread.

    Args:
        target: the agent processes' entry point, ``target(agent, inbox, outbox)``.
        max_bytes: size cap of one message.
        grace_s: how long a stopping agent may take before it is terminated.
        read_ahead: pipe bytes of the decoded messages a reader holds before it waits for
            :meth:`events` (:data:`~.pipe_readers.READ_AHEAD_BYTES`).
    """

    name = "pipes"

    def __init__(
        self,
        target: Callable[[int, Connection, Connection], None],
        max_bytes: int,
        grace_s: float,
        read_ahead: int = READ_AHEAD_BYTES,
    ) -> None:
        self.target = target
        self.max_bytes = max_bytes
        self.grace_s = grace_s
        self.read_ahead = read_ahead
        self.processes: dict[int, Any] = {}
        self.channels: dict[int, Channel] = {}
        self.readers: dict[int, PipeReader] = {}
        self._gone: set[int] = set()  # Left reported
        self._bell = threading.Condition()
        # closed by stop(): wakes every reader waiting on its pipe
        self._wake, self._wake_writer = multiprocessing.Pipe(duplex=False)

    def start(self, tasks: Sequence[AgentTask], rejoin: Rejoin) -> None:
        """Start one process per task, send it its task and start its pipe's reader.
        ``rejoin`` is never asked: a process this hub started that ends is gone for good."""
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
            self.readers[task.agent] = PipeReader(
                task.agent, channel, process.sentinel, self._wake, self._bell, self.read_ahead
            )

    def events(self, timeout: float) -> list[Event]:
        if all(agent in self._gone for agent in self.readers):
            return []
        with self._bell:
            self._bell.wait_for(lambda: any(r.ready() for r in self.readers.values()), timeout)
            taken = [(a, r.take()) for a, r in sorted(self.readers.items()) if r.ready()]
        out: list[Event] = []
        for agent, items in taken:  # each agent's in order: its last words before its Left
            for item, nbytes in items:
                if isinstance(item, Received):
                    self.channels[agent].traffic.received(item.message, nbytes)
                    out.append(item)
                elif isinstance(item, Rejected):
                    out.append(item)
                elif isinstance(item, Died):
                    self.processes[agent].join(5.0)  # the sentinel fires just before the status
                    self._gone.add(agent)
                    out.append(
                        Left(agent, f"process died ({exit_reason(self.processes[agent].exitcode)})")
                    )
                else:  # Broken: its framing is lost, nothing after it can be read
                    self.drop(agent)
                    self._gone.add(agent)
                    out.append(
                        Left(
                            agent,
                            f"protocol error: unreadable message ({item.error}); "
                            f"cap {self.max_bytes} bytes",
                        )
                    )
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
        """Stop the agents (see :class:`~como3r.transport.links.Hub`), then end the readers
        (what they still hold is dropped) and close the pipes."""
        for agent, process in self.processes.items():
            if process.is_alive() and interrupted:
                process.terminate()
            elif process.is_alive() and agent in live:
                self.channels[agent].send(Shutdown("the coordinator is stopping"))
        deadline = time.monotonic() + self.grace_s
        for process in self.processes.values():
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.terminate()
                process.join(self.grace_s)
        with self._bell:
            for reader in self.readers.values():
                reader.stop()
        self._wake_writer.close()
        for reader in self.readers.values():
            reader.thread.join(self.grace_s)
            if reader.thread.is_alive():  # a read blocked on a pipe that some process holds
                logger.warning("agent %d: its pipe's reader did not end", reader.agent)
        for channel in self.channels.values():
            channel.close(timeout=self.grace_s)
        self._wake.close()

    def traffic(self, agent: int) -> Traffic:
        return self.channels[agent].traffic

    def exitcode(self, agent: int) -> int | None:
        return self.processes[agent].exitcode
