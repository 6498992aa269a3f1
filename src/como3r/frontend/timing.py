"""Wall time per stage of a run (metrics.json ``stage_seconds``).

:class:`StageTimer` accumulates wall seconds per named stage into a dict it is given (no
global state). Stages nest exclusively: entering a stage pauses the enclosing one, so the
stages of one timer never count a second twice and add up to the time spent inside them.
:class:`TimedPrior` charges a prior's work to the stages ``prior_encode``, ``prior_decode``
and ``prior_retrieval`` of a timer; :func:`with_remainder` adds the ``other`` stage that
makes the stages sum to a measured total.

Timing is host wall time: on an asynchronous device (CUDA) a stage is charged with the work
it waits for, which is where the time is spent from the caller's point of view.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any

from como3r.prior.base import Encoding, PairPrediction, Prior, View

#: the stage that :func:`with_remainder` fills with time no named stage covered
OTHER = "other"


class StageTimer:
    """Exclusive wall-clock seconds per stage, accumulated into ``seconds``.

    Args:
        seconds: the dict to accumulate into (e.g. a stats field); a new one if None.
    """

    def __init__(self, seconds: dict[str, float] | None = None) -> None:
        self.seconds: dict[str, float] = {} if seconds is None else seconds
        self._stack: list[str] = []
        self._mark = 0.0

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Charge the wall time of the ``with`` block (minus nested stages) to ``name``."""
        self._switch(name)
        try:
            yield
        finally:
            self._switch(None)

    def charge(self, name: str, seconds: float) -> None:
        """Add ``seconds`` measured elsewhere (outside any running stage) to ``name``."""
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def _switch(self, entering: str | None) -> None:
        """Charge the time since the last switch to the running stage, then push or pop."""
        now = time.perf_counter()
        if self._stack:
            running = self._stack[-1]
            self.seconds[running] = self.seconds.get(running, 0.0) + (now - self._mark)
        if entering is None:
            self._stack.pop()
        else:
            self._stack.append(entering)
        self._mark = now


def with_remainder(seconds: Mapping[str, float], total: float) -> dict[str, float]:
    """The stages plus ``other = total - sum(stages)`` (clamped at 0), so they sum to
    ``total`` whenever the stages fit inside it."""
    stages = {k: v for k, v in seconds.items() if k != OTHER}
    stages[OTHER] = seconds.get(OTHER, 0.0) + max(0.0, total - sum(seconds.values()))
    return stages


class TimedPrior:
    """A prior whose encode, decode and retrieval work is charged to a timer's stages.

    Every other attribute is the wrapped prior's.

    Args:
        prior: the prior to wrap.
        timer: the timer to charge.
        decoded: told how many ordered pairs each decode call decoded (None: nobody).
    """

    def __init__(
        self, prior: Prior, timer: StageTimer, decoded: Callable[[int], None] | None = None
    ) -> None:
        self._prior = prior
        self._timer = timer
        self._decoded = decoded or (lambda pairs: None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._prior, name)

    def encode(self, view: View) -> Encoding:
        """The prior's per-image work (stage ``prior_encode``)."""
        with self._timer.stage("prior_encode"):
            return self._prior.encode(view)

    def decode(self, enc_i: Encoding, enc_j: Encoding) -> PairPrediction:
        """The prior's per-pair work (stage ``prior_decode``)."""
        self._decoded(1)
        with self._timer.stage("prior_decode"):
            return self._prior.decode(enc_i, enc_j)

    def decode_pairs(self, pairs: Sequence[tuple[Encoding, Encoding]]) -> list[PairPrediction]:
        """Every ordered pair (stage ``prior_decode``)."""
        self._decoded(len(pairs))
        with self._timer.stage("prior_decode"):
            return self._prior.decode_pairs(pairs)

    def decode_symmetric(
        self, pairs: Sequence[tuple[Encoding, Encoding]]
    ) -> list[tuple[PairPrediction, PairPrediction]]:
        """Both orders of every pair (stage ``prior_decode``)."""
        self._decoded(2 * len(pairs))
        with self._timer.stage("prior_decode"):
            return self._prior.decode_symmetric(pairs)

    def retrieval_features(self, enc: Encoding) -> Any:
        """The prior's retrieval head (stage ``prior_retrieval``)."""
        with self._timer.stage("prior_retrieval"):
            return self._prior.retrieval_features(enc)
