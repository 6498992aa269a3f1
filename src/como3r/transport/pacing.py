"""A sender that knows its link: a rate limit and priorities (issue 39 item 3; manual:
docs/networked.md, "Radio links").

``--max-mbps`` caps what one process puts on the network (its radio link) with a token
bucket (:class:`TokenBucket`): bytes accrue at the rate, up to a burst, and a put spends its
bytes. A put is never split here and may take the level below zero (a debt); the next put
that waits on the bucket goes once the debt is paid. What the sender puts in pieces
(an agent's keyframes, :data:`~como3r.transport.zenoh_protocol.PIECE_BYTES` each) therefore
leaves at the rate, piece by piece, and Zenoh's queues and the link never hold more than
a piece of it: whatever else the process sends is not stuck behind a whole keyframe.

Priorities (:class:`Lanes`): small messages (acknowledgements, pose updates, a robot's pose
graphs and estimates; Zenoh's own liveliness and keep-alives never pass through here) go
in a *control* lane, paced by a bucket of their own, so they never wait for the debt of a
large message; large ones in a *bulk* lane wait until the shared bucket, which both lanes
spend, is out of debt. Over any stretch of time the bytes put are at most the rate times
its length plus a few bursts and the largest message (or piece) put.

The backlog is what waits: its bytes over the rate are the seconds it takes to send
(:meth:`Lanes.backlog_s`; ``metrics.json``: ``bandwidth[].send_backlog``).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

#: bytes per second of one Mbit/s
MBPS = 1e6 / 8
#: the largest message that goes in the control lane (a pose update of a thousand keyframes)
CONTROL_BYTES = 64 * 1024

T = TypeVar("T")


def bytes_per_s(max_mbps: float) -> float | None:
    """``--max-mbps`` in bytes per second (None: 0, no limit)."""
    return max_mbps * MBPS if max_mbps > 0 else None


class TokenBucket:
    """Bytes allowed on a link of ``rate`` bytes per second, ``burst`` bytes at once.

    Args:
        rate: bytes per second.
        burst: the most bytes that accrue while nothing is sent (the first put goes at once).
        clock: seconds, monotonic (tests pass their own).
    """

    def __init__(
        self, rate: float, burst: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if rate <= 0:
            raise ValueError(f"rate {rate}: must be positive")
        self.rate, self.burst, self.clock = float(rate), float(burst), clock
        self.level = float(burst)
        self._stamp = clock()

    def _refill(self) -> None:
        now = self.clock()
        self.level = min(self.burst, self.level + (now - self._stamp) * self.rate)
        self._stamp = now

    def spend(self, nbytes: int) -> None:
        """Count ``nbytes`` put on the link (the level may go below zero)."""
        self._refill()
        self.level -= nbytes

    def delay(self) -> float:
        """Seconds until the level is back to zero (0: a put may go now)."""
        self._refill()
        return 0.0 if self.level >= 0 else -self.level / self.rate


@dataclass
class _Item(Generic[T]):
    item: T
    nbytes: int


class Lanes(Generic[T]):
    """Two queues, control before bulk, under one rate limit; not thread-safe (the caller
    holds its lock).

    Args:
        rate: bytes per second (None: no limit, the lanes only order).
        burst: the shared bucket's burst, in bytes.
        clock: as for :class:`TokenBucket`.
    """

    def __init__(
        self,
        rate: float | None,
        burst: float = CONTROL_BYTES,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rate = rate
        self.shared = TokenBucket(rate, burst, clock) if rate is not None else None
        self.control_bucket = TokenBucket(rate, CONTROL_BYTES, clock) if rate is not None else None
        self._control: deque[_Item[T]] = deque()
        self._bulk: deque[_Item[T]] = deque()
        self.queued_bytes = 0
        self.peak_bytes = 0

    def __len__(self) -> int:
        return len(self._control) + len(self._bulk)

    def add(self, item: T, nbytes: int, control: bool) -> None:
        """Queue ``item`` of ``nbytes`` in the control or the bulk lane (each in order)."""
        (self._control if control else self._bulk).append(_Item(item, nbytes))
        self.queued_bytes += nbytes
        self.peak_bytes = max(self.peak_bytes, self.queued_bytes)

    def next(self) -> tuple[T | None, float]:
        """The item to put now (spent from the buckets) and 0, or None and how long to wait
        for one (``inf``: both lanes empty)."""
        waits = [float("inf")]
        if self._control:
            wait = 0.0 if self.control_bucket is None else self.control_bucket.delay()
            if wait == 0.0:
                return self._take(self._control), 0.0
            waits.append(wait)
        if self._bulk:
            wait = 0.0 if self.shared is None else self.shared.delay()
            if wait == 0.0:
                return self._take(self._bulk), 0.0
            waits.append(wait)
        return None, min(waits)

    def _take(self, lane: deque[_Item[T]]) -> T:
        entry = lane.popleft()
        self.queued_bytes -= entry.nbytes
        if self.shared is not None and self.control_bucket is not None:
            self.shared.spend(entry.nbytes)
            if lane is self._control:
                self.control_bucket.spend(entry.nbytes)
        return entry.item

    def backlog_s(self) -> float | None:
        """Seconds the queued bytes take at the rate (None: no limit)."""
        return None if self.rate is None else self.queued_bytes / self.rate
