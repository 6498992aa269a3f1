"""The session store's codings started ahead of its transaction, on worker threads (issue 41).

Of the journal's serial time in the coordinator (its ``record``, stage ``journal``) nearly
all was coding what the coordinator makes itself: a keyframe's pointmap taken onto its
agent's focal length in the map as it is inserted (and the refreshed pointmap of the
keyframe before it), an agent's pointmaps rescaled at a gauge merge, an inter-agent edge's
matches. Those are coded in the lossy wire coding and decoded again (:mod:`.coded`: the
coordinator then holds what a read gives back), 110-150 ms of CPU per 512x384 pointmap; the
SQLite writes are a few ms. The coordinator knows these values long before its journal
writes them: right after inserting a batch's keyframes, it still verifies them and maybe
solves a global BA (:meth:`~como3r.coordination.coordinator.Journal.prepare`).

:class:`Ahead` codes them meanwhile on worker threads (numpy and Zstandard release the GIL)
and the transaction takes each result (:meth:`Ahead.take`) where it is for the very same
input, unchanged since: the same objects, each tensor at the version (its in-place
operation counter) it had when the coding was submitted; anything else is coded on the
spot, as before. So the store writes the same bytes, the coordinator settles on the same
values, and the transaction and its place before the acknowledgements are untouched: only
the thread that does the coding changes, never what is committed or when. Jobs left unused
(an array replaced before the write) are dropped after each transaction.

Measured (``como3r synth --agents 4 --frames 16 --width 160 --height 120 --overlap 0.5``,
``como3r run`` defaults in lockstep, simulated prior, 19 keyframes; coordinator thread CPU,
``OMP_NUM_THREADS=1``, 2 cores shared with other jobs at a load of 5 to 29): the in-stream
journal 182, 188, 193 -> 22, 23 ms per keyframe (its wall time in ``record`` 374, 425 ->
123, 152 ms: some codings are still waited for), a gauge merge's record 469-741 -> 22-35 ms
of the coordinator's CPU (226-295 ms wall, coded two at a time); trajectories, keyframes,
``map.ply``, ``graph.json`` byte for byte the same, ``session.db`` the same rows and blobs
(49.5 MB). Still waited for: a coding that could not start early (a standalone pointmap
refresh, a merge with no global BA after it, the terminal cleanup's refined pointmaps, whose
record took 4.7-5.9 s of wall against 3.1-4.8 on these two busy cores).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

from torch import Tensor

T = TypeVar("T")

#: worker threads coding ahead: a merge rescales all of an agent's pointmaps at once
WORKERS = min(4, os.cpu_count() or 1)


def state(value: Any) -> Any:
    """What must be the same for a coding of ``value`` to hold for it still: a tensor's
    identity and version, a dataclass's fields', a plain scalar itself; None where that
    cannot be told (an inference tensor counts no versions, a numpy array none at all)."""
    if isinstance(value, Tensor):
        return None if value.is_inference() else (id(value), value._version)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        parts = tuple(state(getattr(value, f.name)) for f in dataclasses.fields(value))
        return None if None in parts else (id(value), parts)
    if _scalar(value):
        return ("value", value)
    return None


@dataclasses.dataclass
class _Job:
    function: Callable[..., Any]
    #: the inputs, held until the job is taken or dropped (their ids stay theirs)
    args: tuple[Any, ...]
    states: tuple[Any, ...]
    future: Future


class Ahead:
    """Codings submitted before the transaction that writes them, keyed by their first
    input (the module docstring).

    Args:
        workers: worker threads (0: none; every coding is then done by :meth:`take`).
    """

    def __init__(self, workers: int = WORKERS) -> None:
        self._pool = (
            ThreadPoolExecutor(workers, thread_name_prefix="como3r-store") if workers > 0 else None
        )
        self._jobs: dict[int, _Job] = {}
        #: codings taken from a worker and done on the spot (:meth:`take`), for tests and probes
        self.taken = 0
        self.inline = 0

    def submit(self, function: Callable[..., Any], *args: Any) -> None:
        """Start ``function(*args)`` on a worker, unless it is running or done already for
        the same unchanged inputs, or they cannot be told unchanged (a new job replaces a
        stale one)."""
        if self._pool is None:
            return
        states = tuple(state(a) for a in args)
        if None in states or self._match(function, args, states) is not None:
            return
        self._jobs[id(args[0])] = _Job(function, args, states, self._pool.submit(function, *args))

    def take(self, function: Callable[..., T], *args: Any) -> T:
        """``function(*args)``: a worker's result for the very same unchanged inputs (waited
        for), else computed here. An exception the coding raised is raised here as it
        would be on the spot."""
        job = self._match(function, args, tuple(state(a) for a in args))
        if job is None:
            self.inline += 1
            return function(*args)
        del self._jobs[id(args[0])]
        self.taken += 1
        return job.future.result()

    def drop(self) -> None:
        """Forget every job not taken (their inputs were replaced, or will be coded again):
        what a transaction did not use is not kept to the next one."""
        for job in self._jobs.values():
            job.future.cancel()
        self._jobs.clear()

    def close(self) -> None:
        """Drop every job and stop the workers (one still coding finishes first)."""
        self.drop()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def _match(
        self, function: Callable[..., Any], args: tuple[Any, ...], states: tuple[Any, ...]
    ) -> _Job | None:
        job = self._jobs.get(id(args[0]))
        if (
            job is None
            or job.function is not function
            or len(job.args) != len(args)
            or any(a is not b for a, b in zip(job.args, args) if not _scalar(a))
            or job.states != states
            or None in states
        ):
            return None
        return job


def _scalar(value: Any) -> bool:
    return value is None or isinstance(value, (bool, int, float, str))
