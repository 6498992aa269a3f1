"""Agent pipes read and decoded on threads of their own (issue 41, "Teams of sixteen").

An agent process sends its keyframes and pointmap refreshes in the lossy wire coding
(:mod:`como3r.runtime.ingest`); decoding one costs 65-100 ms of CPU at 160x120, which on
the coordinator's thread was serial work that grows with the team. :class:`PipeReader`
receives and decodes one agent's messages on its own thread as they arrive and holds them
until :class:`~como3r.transport.pipes.PipeHub` collects them; torch and numpy release the
interpreter lock inside their large operations, so a coordinator with several cores decodes
while it solves.

What the coordinator's own thread did and what stays the same:

* one thread per agent reads its pipe in order and queues what it read in that order, so
  each agent's messages keep their order;
* when the agent's process ends (its sentinel), the reader first takes every message still
  in the pipe, then says so (:class:`Died`): an exited agent's last messages come before
  its ``Left``;
* the end of the stream ends nothing by itself (the process's end does); unreadable framing
  (``OSError``, a message over the cap included) ends the reader (:class:`Broken`); a
  message that does not decode is a :class:`~como3r.transport.links.Rejected` and the
  reader goes on;
* ``Received.seconds`` is the decode's CPU time on the reader's thread
  (``time.thread_time``), which the runtime charges to the coordinator's
  ``stage_seconds["ingest"]``: the decode's cost to the coordinator's process, no longer on
  its main thread.

Bounded memory: a reader reads the next message only while the decoded messages it holds
came in fewer than ``limit`` bytes through the pipe (so it holds at most one message beyond
that, and any one message whatever its size); past it, it waits until the hub took them: a
slow coordinator stops its readers, and its agents' sends wait in the pipe and their own
queues, as before there were readers (an agent's sends never block its frame loop).

The Zenoh hub decodes on threads of its own the same way (:mod:`.zenoh_decoding`): the
bound (:class:`ReadAhead`) and each message's decode (:func:`decoded`) are shared.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

from como3r.errors import MessageError
from como3r.transport.links import Received, Rejected
from como3r.transport.messages import KeyframeMessage

#: bytes through the pipe of the decoded messages a reader holds before it waits for the
#: hub: about one keyframe message (1.08-1.17 MB in the lossy coding at 512x384, with the
#: agent's exact encoding), so each agent has its next keyframe decoded while the
#: coordinator works on the last, and a team of 16 holds at most 16 decoded keyframes
#: beyond what the runtime took
READ_AHEAD_BYTES = 1_000_000


@dataclass(frozen=True)
class Died:
    """The agent's process ended; every message it wrote came before this."""


@dataclass(frozen=True)
class Broken:
    """The pipe's framing is unreadable (``error``): nothing after it can be read."""

    error: str


Item = Received | Rejected | Died | Broken


class Source(Protocol):
    """What a reader reads through: the coordinator's
    :class:`~como3r.transport.pipes.Channel` to an agent."""

    inbox: Connection | None
    max_bytes: int

    def decode(self, data: bytes) -> tuple[Any, float]:
        """The message of ``data`` and its decode's CPU seconds; raises ``MessageError``."""


def decoded(
    agent: int, decode: Callable[[bytes], tuple[Any, float]], data: bytes
) -> Received | Rejected:
    """``data`` from agent ``agent`` as the hub hands it over: the message ``decode`` makes
    of it with the CPU seconds it says it took, or why it is not one (``decode`` raised
    ``MessageError``)."""
    try:
        message, seconds = decode(data)
    except MessageError as exc:
        return Rejected(agent, str(exc))
    kept = data if isinstance(message, KeyframeMessage) else None
    return Received(agent, message, seconds=seconds, data=kept)


class ReadAhead:
    """What one agent's decoding thread holds for its hub, bounded: it decodes the next
    message only while the decoded ones the hub has not taken came in fewer than ``limit``
    bytes (so it holds at most one message beyond that, and any one message whatever its
    size). Its state is guarded by the hub's condition ``bell``, shared by all its
    agents' threads: notified when one decoded something, and when the hub took something
    or stops.
    """

    def __init__(self, bell: threading.Condition, limit: int) -> None:
        self.limit = limit
        self._bell = bell
        self._held = 0  # bytes the decoded messages not yet taken came in
        self._stopping = False

    def stop(self) -> None:
        """(Under ``bell``) stop decoding: the thread ends at its next wait."""
        self._stopping = True
        self._bell.notify_all()

    def _room(self, waiting: Callable[[], bool] = lambda: True) -> bool:
        """Wait until the hub took enough to decode on and ``waiting()`` (something waits
        to be decoded); False once stopping."""
        with self._bell:
            self._bell.wait_for(lambda: self._stopping or (self._held < self.limit and waiting()))
            return not self._stopping


class PipeReader(ReadAhead):
    """Reads and decodes one agent's pipe on a thread of its own.

    Args:
        agent: the agent whose pipe it reads.
        channel: the coordinator's :class:`~como3r.transport.pipes.Channel` to it (its
            ``inbox`` is read here only, its ``decode`` used).
        sentinel: the agent process's sentinel (ready once it ended).
        stop: a handle that becomes ready when the hub stops (the readers' wake-up).
        bell: the hub's condition, shared by its readers: notified when a reader queued
            something, and when the hub took something or stops.
        limit: :data:`READ_AHEAD_BYTES` unless told.
    """

    def __init__(
        self,
        agent: int,
        channel: Source,
        sentinel: int,
        stop: Connection,
        bell: threading.Condition,
        limit: int = READ_AHEAD_BYTES,
    ) -> None:
        super().__init__(bell, limit)
        self.agent = agent
        self.channel = channel
        assert channel.inbox is not None
        self._inbox = channel.inbox
        self._sentinel = sentinel
        self._stop = stop
        self._items: deque[tuple[Item, int]] = deque()  # with their bytes through the pipe
        self.thread = threading.Thread(
            target=self._run, name=f"como3r-pipe-reader-{agent}", daemon=True
        )
        self.thread.start()

    def ready(self) -> bool:
        """(Under ``bell``) whether something is queued."""
        return bool(self._items)

    def take(self) -> list[tuple[Item, int]]:
        """(Under ``bell``) everything queued, in order, with each message's bytes; the
        reader may read on."""
        items = list(self._items)
        self._items.clear()
        self._held = 0
        self._bell.notify_all()
        return items

    def _run(self) -> None:
        open_ = True  # the pipe is not at its end
        while True:
            handles: list[Connection | int] = [self._sentinel, self._stop]
            ready = wait(handles + ([self._inbox] if open_ else []))
            if self._stop in ready:
                return
            # all that is in the pipe; once the process ended, all it will ever hold
            while open_ and self._inbox.poll(0.0):
                if not self._room():
                    return
                try:
                    open_ = self._read_one()
                except OSError as exc:  # the framing is lost: nothing after it can be read
                    self._queue(Broken(str(exc)), 0)
                    return
            if self._sentinel in ready:
                self._queue(Died(), 0)
                return

    def _read_one(self) -> bool:
        """Read, decode and queue one message; False at the end of the stream."""
        try:
            data = self._inbox.recv_bytes(self.channel.max_bytes)
        except EOFError:
            return False
        self._queue(decoded(self.agent, self.channel.decode, data), len(data))
        return True

    def _queue(self, item: Item, nbytes: int) -> None:
        with self._bell:
            if not self._stopping:
                self._items.append((item, nbytes))
                self._held += nbytes
                self._bell.notify_all()
