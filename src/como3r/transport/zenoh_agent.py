"""An agent's end of the Zenoh transport (``como3r agent``; the protocol is in
:mod:`como3r.transport.zenoh_protocol`).

The agent's frame loop never waits on the network: :meth:`ZenohAgentLink.send` puts the
message in the agent's :class:`~como3r.transport.spool.Spool` and a background thread puts it
on the network while the coordinator's liveliness token is present. While the coordinator is
away the agent keeps tracking and the spool grows (on disk past its memory limit); when the
coordinator is back, everything it has not acknowledged is put again, oldest first.
Messages are encoded ``lossy`` (:func:`~como3r.transport.codec.encode`): keyframe pointmaps,
their confidences and MASt3R's encoder tokens travel in half precision.

Under ``--max-mbps`` the pieces leave at the rate (:class:`~como3r.transport.pacing.TokenBucket`):
the link and Zenoh's queues never hold more than a piece of a keyframe, so what the
coordinator sends back, and Zenoh's liveliness, cross at once. The agent's own messages
stay one sequence, oldest first (the coordinator takes them in order: a keyframe's
sequential edge needs its predecessor). Each put tells the coordinator the bytes still
queued behind it (:data:`~como3r.transport.zenoh_protocol.STREAM`); :meth:`ZenohAgentLink.status`
says the same here.
"""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from como3r.errors import InputError
from como3r.transport import codec
from como3r.transport.links import Traffic
from como3r.transport.messages import TO_AGENT, AgentTask, Shutdown
from como3r.transport.pacing import TokenBucket, bytes_per_s
from como3r.transport.spool import Spool
from como3r.transport.zenoh_protocol import (
    BYE,
    CONTROL_PRIORITY,
    INCARNATION,
    PIECE,
    PIECE_BYTES,
    SEQ,
    STREAM,
    STREAM_PRIORITY,
    WAIT,
    Keys,
)

#: the error reply Zenoh itself gives a query no queryable answered in time
ZENOH_QUERY_TIMEOUT = "Timeout"

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SendStatus:
    """What an agent has sent and what waits (its progress line).

    Attributes:
        bytes_put: payload bytes put on the network so far (re-sends included).
        backlog_bytes: bytes made and not yet put.
        max_mbps: the rate limit (None: none).
        peak_backlog_bytes: the most that waited at once.
    """

    bytes_put: int
    backlog_bytes: int
    max_mbps: float | None
    peak_backlog_bytes: int

    def seconds(self, nbytes: int) -> float | None:
        """``nbytes`` in seconds at the rate limit (None: none)."""
        return None if self.max_mbps is None else nbytes * 8 / (self.max_mbps * 1e6)

    def line(self) -> str:
        """One line for a person: ``sent 12.3 MB; backlog 4.1 s (0.5 MB at 1 Mbit/s)``."""
        text = f"sent {self.bytes_put / 1e6:.1f} MB; backlog "
        seconds = self.seconds(self.backlog_bytes)
        if seconds is None:
            return text + f"{self.backlog_bytes / 1e6:.1f} MB"
        return (
            text
            + f"{seconds:.1f} s ({self.backlog_bytes / 1e6:.1f} MB at {self.max_mbps:g} Mbit/s)"
        )


class ZenohAgentLink:
    """An agent's end (:class:`~como3r.transport.links.AgentLink`) over Zenoh.

    Declares the agent's subscribers, then the liveliness token of this process (the
    coordinator sees it join). Messages are put only while the coordinator's token is
    present; each is kept in the spool until acknowledged.

    Args:
        session: an open Zenoh session (the caller closes it).
        keys: the run's key expressions.
        agent: this agent's id.
        spool: where unacknowledged messages wait (None: a default one).
        wait_log_s: how often :meth:`fetch_task` and :meth:`close` say what they wait for.
        where: where the session looks for the coordinator
            (:meth:`~como3r.transport.zenoh_protocol.ZenohOptions.where`), named while it
            waits; empty: the run's key expressions.
        max_mbps: the rate limit of what it sends (0: none).
        on_status: called from the sending thread with :meth:`status`, every
            ``status_s`` seconds while something waits to be put, and once it has all gone.
        status_s: see ``on_status``.
    """

    def __init__(
        self,
        session: Any,
        keys: Keys,
        agent: int,
        spool: Spool | None = None,
        wait_log_s: float = 30.0,
        where: str = "",
        max_mbps: float = 0.0,
        on_status: Callable[[SendStatus], None] | None = None,
        status_s: float = 10.0,
    ) -> None:
        self.session, self.keys, self.agent = session, keys, agent
        self.where = where or keys.root
        self.max_bytes = codec.DEFAULT_MAX_BYTES
        self.wait_log_s = wait_log_s
        self.traffic = Traffic()
        self.incarnation = int.from_bytes(os.urandom(8), "little")
        self.spool = spool if spool is not None else Spool(label=f"agent-{agent}")
        self._mine = INCARNATION.pack(self.incarnation)
        self._present = False
        self._gone_at: float | None = None  # when the coordinator's token went
        self._made_away = 0  # messages made since then
        self._back_at: float | None = None  # when it came back, until it has caught up
        self._catch_up_to = -1  # the last message made before it came back
        self._closed = False
        self._discard = False  # after a Shutdown: the coordinator takes nothing more
        self._cond = threading.Condition()
        self._inbox: queue.Queue[bytes] = queue.Queue()
        self._peeked: bytes | None = None
        rate = bytes_per_s(max_mbps)
        self.rate = rate or 0.0
        self.bucket = TokenBucket(rate, PIECE_BYTES) if rate is not None else None
        self.bytes_put = 0
        self.peak_backlog = 0
        self._in_flight = 0  # bytes of the message being put not put yet
        self._on_status, self._status_s = on_status, status_s
        self._said_status, self._said_queued = -math.inf, False
        self._declared = [
            session.declare_subscriber(keys.down(agent, "*"), self._on_down),
            session.declare_subscriber(keys.ack(agent), self._on_ack),
            session.liveliness().declare_subscriber(
                keys.coordinator(), self._on_coordinator, history=True
            ),
        ]
        self._declared.append(
            session.liveliness().declare_token(keys.alive(agent, self.incarnation))
        )
        self._sender = threading.Thread(target=self._send_loop, daemon=True)
        self._sender.start()

    def fetch_task(self) -> AgentTask:
        """This agent's task from the coordinator, asked until it answers.

        Raises:
            InputError: the coordinator refuses (no agent with this id, or one that has
                failed or finished in this run).
        """
        said, waiting = -math.inf, f"the coordinator ({self.where})"
        while True:
            for reply in self.session.get(
                self.keys.task(self.agent), timeout=5.0, attachment=self._mine
            ):
                if reply.ok is not None:
                    task = codec.decode(reply.ok.payload.to_bytes(), expected=AgentTask)
                    self.max_bytes = task.max_message_bytes
                    return task
                text = reply.err.payload.to_string()
                if text == ZENOH_QUERY_TIMEOUT:  # a busy coordinator (a global BA): ask again
                    waiting = f"the coordinator ({self.where}), busy: no answer within 5 s"
                    continue
                if not text.startswith(WAIT):
                    raise InputError(f"agent {self.agent}: the coordinator says: {text}")
                waiting = text[len(WAIT) :]
            if time.monotonic() - said > self.wait_log_s:
                logger.warning("agent %d: waiting: %s", self.agent, waiting)
                said = time.monotonic()
            time.sleep(0.5)

    # ------------------------------------------------------------ AgentLink

    def send(self, message: Any) -> None:
        data = codec.encode(message, max_bytes=self.max_bytes, lossy=True)
        self.traffic.sent(message, len(data))
        with self._cond:
            self.spool.append(self.keys.up(self.agent, type(message).__name__), data)
            self._made_away += self._gone_at is not None
            self.peak_backlog = max(self.peak_backlog, self._backlog())
            self._cond.notify_all()

    def status(self) -> SendStatus:
        """What was sent and what waits, now."""
        with self._cond:
            return SendStatus(
                self.bytes_put,
                self._backlog(),
                self.rate * 8 / 1e6 if self.rate else None,
                self.peak_backlog,
            )

    def _backlog(self) -> int:
        """Bytes made and not put yet (the caller holds the lock)."""
        return self.spool.pending_bytes() + self._in_flight

    def poll(self, timeout: float = 0.0) -> bool:
        if self._peeked is None:
            try:
                self._peeked = (
                    self._inbox.get(timeout=timeout) if timeout > 0 else self._inbox.get_nowait()
                )
            except queue.Empty:
                return False
        return True

    def receive(self) -> Any:
        data, self._peeked = (self._peeked if self._peeked is not None else self._inbox.get()), None
        message = codec.decode(data, max_bytes=self.max_bytes, expected=TO_AGENT)
        self.traffic.received(message, len(data))
        if isinstance(message, Shutdown):
            with self._cond:
                self._discard = True
                self._cond.notify_all()
        return message

    def close(self) -> None:
        """Wait until the coordinator has stored every message (or sent a Shutdown), say so
        (``Bye``: the coordinator may wait for it), then leave: the liveliness token goes
        last."""
        with self._cond:
            said = time.monotonic()
            while len(self.spool) and not self._discard:
                self._cond.wait(1.0)
                if time.monotonic() - said > self.wait_log_s:
                    away = (
                        ""
                        if self._gone_at is None
                        else f"; it has been gone for {time.monotonic() - self._gone_at:.0f} s "
                        "(they are kept until it is back)"
                    )
                    logger.warning(
                        "agent %d: waiting for the coordinator to store %d message(s)%s",
                        self.agent,
                        len(self.spool),
                        away,
                    )
                    said = time.monotonic()
            self._closed = True
            self._cond.notify_all()
        self._sender.join()
        if not self._discard:
            self._bye()
        for entity in reversed(self._declared):
            entity.undeclare()
        self.spool.close()

    def _bye(self) -> None:
        """Tell the coordinator this process has its last acknowledgement and leaves."""
        import zenoh

        try:
            self.session.put(
                self.keys.up(self.agent, BYE),
                b"",
                attachment=self._mine,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=getattr(zenoh.Priority, CONTROL_PRIORITY),
            )
        except Exception as exc:  # the session is closing
            logger.debug("bye failed: %s", exc)

    # ------------------------------------------------------------ threads

    def _send_loop(self) -> None:
        import zenoh

        priority = getattr(zenoh.Priority, STREAM_PRIORITY)
        while True:
            with self._cond:
                while not (self._closed or (self._present and self.spool.has_next())):
                    self._cond.wait()
                if self._closed:
                    return
                seq, key, data = self.spool.take()
                self._in_flight = len(data)
            pieces = max(1, math.ceil(len(data) / PIECE_BYTES))  # see zenoh_protocol
            try:
                for index in range(pieces):
                    piece = data[index * PIECE_BYTES : (index + 1) * PIECE_BYTES]
                    if not self._paced(len(piece)):
                        return
                    with self._cond:
                        self._in_flight -= len(piece)
                        queued = self._backlog()
                    self.session.put(
                        key,
                        piece,
                        attachment=(
                            STREAM.pack(self.incarnation, seq, queued, self.rate)
                            if pieces == 1
                            else PIECE.pack(self.incarnation, seq, index, pieces, queued, self.rate)
                        ),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        priority=priority,
                    )
                    self.bytes_put += len(piece)
                    self._report(queued)
            except Exception as exc:  # the session is closing
                logger.debug("put on %s failed: %s", key, exc)
            finally:
                with self._cond:
                    self._in_flight = 0

    def _paced(self, nbytes: int) -> bool:
        """Wait until the rate limit lets a piece of ``nbytes`` go (spent at once); False
        once the link is closed."""
        if self.bucket is None:
            return True
        with self._cond:
            while (wait := self.bucket.delay()) > 0:
                if self._closed:
                    return False
                self._cond.wait(wait)
            self.bucket.spend(nbytes)
        return True

    def _report(self, queued: int) -> None:
        """Call ``on_status`` at most every ``status_s`` while something waits, and once
        more when nothing does after that."""
        if self._on_status is None:
            return
        now = time.monotonic()
        if now - self._said_status >= self._status_s and (queued or self._said_queued):
            self._said_status, self._said_queued = now, queued > 0
            self._on_status(self.status())

    def _on_down(self, sample: Any) -> None:
        attachment = sample.attachment
        if attachment is not None and attachment.to_bytes() == self._mine:
            self._inbox.put(sample.payload.to_bytes())  # else: for another process of this id

    def _on_ack(self, sample: Any) -> None:
        data = sample.payload.to_bytes()
        if len(data) != SEQ.size:
            return
        incarnation, seq = SEQ.unpack(data)
        if incarnation != self.incarnation:
            return
        with self._cond:
            self.spool.acknowledge(seq)
            if self._back_at is not None and seq >= self._catch_up_to:
                logger.warning(
                    "agent %d: caught up %.1f s after the coordinator came back: "
                    "it has stored every message made before",
                    self.agent,
                    time.monotonic() - self._back_at,
                )
                self._back_at = None
            self._cond.notify_all()

    def _on_coordinator(self, sample: Any) -> None:
        import zenoh

        present = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            if present and self._gone_at is not None:  # it may have lost some: again, in order
                logger.warning(
                    "agent %d: the coordinator is back after %.1f s; re-sending %d "
                    "message(s), %d of them made while it was away",
                    self.agent,
                    time.monotonic() - self._gone_at,
                    self.spool.rewind(),
                    self._made_away,
                )
                self._gone_at, self._made_away = None, 0
                if len(self.spool):  # else nothing to catch up on
                    self._back_at, self._catch_up_to = time.monotonic(), self.spool.next_seq - 1
            elif not present:
                logger.warning(
                    "agent %d: the coordinator is gone; tracking on and keeping "
                    "messages until it is back",
                    self.agent,
                )
                self._gone_at = time.monotonic()
            self._present = present
            self._cond.notify_all()
