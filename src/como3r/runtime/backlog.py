"""How far the coordinator of the multi-process runtime trails its agents (issue 41).

Keyframes wait in the runtime's queue (:mod:`.processes`) for two reasons: their turn in
the ``(timestamp, agent)`` order has not come (another agent may still send an earlier
one), or the coordinator is busy with earlier keyframes. Each time the coordinator turns
to the queue, before it takes a batch, :class:`Backlog` samples

* ``keyframes``: the keyframes received and not yet handed to the coordinator;
* ``seconds``: seconds of input it is behind, the newest received keyframe's timestamp
  minus the newest handled one's (before the first is handled: minus the oldest waiting
  one's).

A coordinator that keeps up leaves a few keyframes waiting for their turn and trails by
about one keyframe interval of input; one that falls behind trails by more and more.
``metrics.json`` (``runtime.backlog``) reports the largest of each over the run and the
sample at the *end of the input* (the first time the coordinator turns to the queue after
every agent stopped streaming: what it still had to do then), with ``drain_seconds``, the
wall time from then until the last keyframe was handled. The progress display shows the
latest sample as the coordinator's line while the agents run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any


@dataclass
class Backlog:
    """The coordinator's backlog as sampled (module docstring)."""

    #: keyframes handed to the coordinator so far
    handled: int = 0
    #: the newest timestamp handed to it [s] (-inf before the first)
    newest_handled: float = -math.inf
    keyframes: int = 0
    seconds: float = 0.0
    max_keyframes: int = 0
    max_seconds: float = 0.0
    #: the sample at the end of the input (None while agents stream)
    end_keyframes: int | None = None
    end_seconds: float | None = None
    _end_clock: float | None = None
    drain_seconds: float | None = None

    def sample(self, waiting: Iterable[float], input_ended: bool) -> None:
        """Take a sample: ``waiting`` are the timestamps [s] of the keyframes received and
        not handed over; ``input_ended``: every agent has stopped streaming."""
        stamps = list(waiting)
        self.keyframes = len(stamps)
        if stamps:
            since = self.newest_handled if self.handled else min(stamps)
            self.seconds = max(0.0, max(stamps) - since)
        else:
            self.seconds = 0.0
        self.max_keyframes = max(self.max_keyframes, self.keyframes)
        self.max_seconds = max(self.max_seconds, self.seconds)
        if input_ended and self.end_keyframes is None:
            self.end_keyframes, self.end_seconds = self.keyframes, self.seconds
            self._end_clock, self.drain_seconds = time.monotonic(), 0.0

    def handed(self, timestamps: Iterable[float]) -> None:
        """Keyframes with these timestamps [s] were handed to the coordinator (and done)."""
        stamps = list(timestamps)
        if not stamps:
            return
        self.handled += len(stamps)
        self.newest_handled = max(self.newest_handled, *stamps)
        if self._end_clock is not None:
            self.drain_seconds = time.monotonic() - self._end_clock

    def text(self) -> str:
        """``3 keyframes waiting, 0.8 s of input behind``."""
        plural = "" if self.keyframes == 1 else "s"
        return f"{self.keyframes} keyframe{plural} waiting, {self.seconds:.1f} s of input behind"

    def advice(self, agents: int) -> str | None:
        """A note for a coordinator that verified itself and trailed ``agents`` agents by
        more keyframes than one each when their input ended (a coordinator that keeps up
        leaves those of the last moment): the agents can verify (issue 41); else None."""
        if agents < 2 or self.end_keyframes is None or self.end_keyframes <= agents:
            return None
        return (
            f"the coordinator trailed the {agents} agents by {self.end_keyframes} keyframes "
            f"({self.end_seconds or 0.0:.1f} s of input) when their input ended; "
            "--set verification.on_agents=true lets the agents verify the candidates "
            "(docs: networked.md, Large teams)"
        )

    def to_json(self) -> dict[str, Any]:
        """The ``runtime.backlog`` section of ``metrics.json``."""
        return {
            "keyframes_handled": self.handled,
            "max_keyframes": self.max_keyframes,
            "max_seconds": self.max_seconds,
            "end_keyframes": self.end_keyframes,
            "end_seconds": self.end_seconds,
            "drain_seconds": self.drain_seconds,
        }
