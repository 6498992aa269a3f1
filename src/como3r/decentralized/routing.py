"""How the robots' messages travel in one machine's mission (:mod:`.protocol`): the
:class:`Router` in the driver delivers a message only when sender and recipient are both in
range at the message's round time (:mod:`.schedule`) and counts the bytes of every delivered
message per robot and per message type (:class:`TrafficCounter`); a robot reaches it through
a :class:`ThreadLink` (robots as threads, for tests) or a :class:`PipeLink` (robots as
processes), both a :class:`Link`, the robot's radio as it sees it (``como3r robot``'s Zenoh
link is one too, and tells it of a peer gone for good with :class:`PeerLeft`).
"""

from __future__ import annotations

import queue
import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Protocol

from como3r.decentralized.messages import (
    ROBOT_MESSAGES,
    RobotProgress,
    RobotReport,
    RobotTask,
)
from como3r.decentralized.schedule import Schedule
from como3r.transport import codec

MissionProgress = Callable[[RobotProgress | RobotReport], None]


@dataclass
class TrafficCounter:
    """Bytes and messages delivered, per robot and message type and per robot and round;
    messages dropped (out of range, or to a robot that is gone) per type."""

    sent: dict[int, Counter] = field(default_factory=dict)
    received: dict[int, Counter] = field(default_factory=dict)
    sent_by_round: dict[int, Counter] = field(default_factory=dict)
    peers_by_round: dict[int, dict[int, set[int]]] = field(default_factory=dict)
    messages: Counter = field(default_factory=Counter)
    bytes_by_type: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)

    def count(self, sender: int, recipient: int, kind: str, size: int, round: int = -1) -> None:
        self.sent.setdefault(sender, Counter())[kind] += size
        self.received.setdefault(recipient, Counter())[kind] += size
        self.sent_by_round.setdefault(sender, Counter())[round] += size
        self.peers_by_round.setdefault(sender, {}).setdefault(round, set()).add(recipient)
        self.messages[kind] += 1
        self.bytes_by_type[kind] += size

    def max_sent_per_round(self) -> int:
        """The most bytes one robot sent in one round (0 before any traffic): what must
        stay bounded as the team grows."""
        return max(
            (b for rounds in self.sent_by_round.values() for b in rounds.values()), default=0
        )

    def max_peers_per_round(self) -> int:
        """The most robots one robot sent to in one round."""
        return max(
            (len(peers) for rounds in self.peers_by_round.values() for peers in rounds.values()),
            default=0,
        )

    def to_json(self, robots: Sequence[int]) -> dict[str, Any]:
        per_robot = {
            str(r): {
                "sent": dict(self.sent.get(r, {})),
                "received": dict(self.received.get(r, {})),
                "sent_total": sum(self.sent.get(r, Counter()).values()),
                "received_total": sum(self.received.get(r, Counter()).values()),
                "sent_by_round": {
                    str(k): v for k, v in sorted(self.sent_by_round.get(r, Counter()).items())
                },
            }
            for r in robots
        }
        return {
            "per_robot": per_robot,
            "max_sent_per_round": self.max_sent_per_round(),
            "max_peers_per_round": self.max_peers_per_round(),
            "bytes_by_type": dict(self.bytes_by_type),
            "messages_by_type": dict(self.messages),
            "bytes_per_message": {k: v / self.messages[k] for k, v in self.bytes_by_type.items()},
            "total_bytes": sum(self.bytes_by_type.values()),
            "dropped": dict(self.dropped),
        }


class Router:
    """Delivers robot messages that the schedule allows and counts them.

    Args:
        schedule: rendezvous schedule.
        deliver: ``deliver(recipient, data)`` hands raw bytes to a robot.
        max_bytes: size cap of a message.
        robots: the robot ids; messages to any other id are dropped.
        progress: called with every :class:`RobotProgress` and :class:`RobotReport`, one at
            a time (robot threads route concurrently).
    """

    def __init__(
        self,
        schedule: Schedule,
        deliver: Any,
        max_bytes: int,
        robots: Sequence[int],
        progress: MissionProgress | None = None,
    ) -> None:
        self.robots = set(robots)
        self.schedule = schedule
        self.deliver = deliver
        self.max_bytes = max_bytes
        self.progress = progress
        self.traffic = TrafficCounter()
        self.reports: dict[int, RobotReport] = {}
        self.gone: set[int] = set()
        self._lock = threading.Lock()

    def route(self, data: bytes) -> None:
        """Validate, check range, count and forward one encoded message."""
        message = codec.decode(
            data, max_bytes=self.max_bytes, expected=(*ROBOT_MESSAGES, RobotProgress, RobotReport)
        )
        with self._lock:
            if isinstance(message, RobotReport):
                self.reports[message.sender] = message
                self.gone.add(message.sender)
            if isinstance(message, (RobotProgress, RobotReport)):
                if self.progress is not None and message.sender in self.robots:
                    self.progress(message)
                return
            kind = type(message).__name__
            sender, recipient, time_s = message.sender, message.recipient, message.time_s
            if (
                recipient not in self.robots
                or recipient in self.gone
                or not self.schedule.hears(recipient, sender, time_s)
            ):
                self.traffic.dropped[kind] += 1
                return
            self.traffic.count(sender, recipient, kind, len(data), message.round)
        self.deliver(recipient, data)


class Link(Protocol):
    """A robot's radio: messages out to the router, messages in from it."""

    def send(self, message: Any) -> None:
        """Queue a message (never blocks on the other side)."""

    def receive(self, timeout: float) -> Any | None:
        """The next message, or None after ``timeout`` seconds without one."""


@dataclass(frozen=True)
class PeerLeft:
    """What a link that sees its peers' processes (``como3r robot``'s, by Zenoh liveliness)
    hands its robot when a peer is gone for good: nobody waits for it any more."""

    robot: int


class ThreadLink:
    """A robot's link in single-process mode: straight into the router, a queue back."""

    def __init__(self, router: Router, max_bytes: int) -> None:
        self.router = router
        self.inbox: queue.Queue[bytes] = queue.Queue()
        self.max_bytes = max_bytes

    def send(self, message: Any) -> None:
        self.router.route(codec.encode(message, max_bytes=self.max_bytes))

    def receive(self, timeout: float) -> Any | None:
        try:
            data = self.inbox.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return None
        return codec.decode(data, max_bytes=self.max_bytes, expected=ROBOT_MESSAGES)


class PipeLink:
    """A robot process's link: raw bytes over two one-way pipes, sends from a thread so a
    full pipe never blocks computation."""

    def __init__(self, inbox: Connection, outbox: Connection, max_bytes: int) -> None:
        self.inbox = inbox
        self.outbox = outbox
        self.max_bytes = max_bytes
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._sender = threading.Thread(target=self._send_loop, daemon=True)
        self._sender.start()

    def send(self, message: Any) -> None:
        self._queue.put(codec.encode(message, max_bytes=self.max_bytes))

    def receive(self, timeout: float) -> Any | None:
        if not self.inbox.poll(max(timeout, 0.0)):
            return None
        try:
            data = self.inbox.recv_bytes(self.max_bytes)
        except (EOFError, OSError):
            return None
        return codec.decode(data, max_bytes=self.max_bytes, expected=(*ROBOT_MESSAGES, RobotTask))

    def close(self, timeout: float = 60.0) -> None:
        """Flush queued messages, then close both pipes."""
        self._queue.put(None)
        self._sender.join(timeout)
        self.inbox.close()
        self.outbox.close()

    def _send_loop(self) -> None:
        while (data := self._queue.get()) is not None:
            try:
                self.outbox.send_bytes(data)
            except OSError:
                return
