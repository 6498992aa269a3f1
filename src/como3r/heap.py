"""Giving freed memory back to the system (issue 41): one ``malloc_trim`` for every part
that lets go of large arrays.

glibc's ``malloc`` keeps the blocks a process frees in its heap, to hand them out again,
and returns them to the system only from the heap's top. Arrays of 0.1-3 MB freed below a
live block (below glibc's mmap threshold once freed blocks have raised it) so stay in the
process's resident memory. ``malloc_trim(0)`` gives the free pages back. Its callers, each
with what it measured:

* the coordinator's page-out (:func:`~como3r.store.paging.page_out`): a 4-agent 320x240
  synthetic team, multi-process lockstep run, ``session.resident_keyframes=1``, 21
  keyframes: the coordinator's RSS at the end of the stream 857 MB without, 709 MB with it
  after each page-out; 200 MB of 100 kB tensors freed below a live one: RSS 411 MB before,
  220 MB after;
* an agent's frame loop (:mod:`como3r.runtime.agent_loop`), after every frame;
* the deferred verification at the end of the input
  (:meth:`~como3r.coordination.deferral.DeferredVerification._verify_all_deferred`), after
  every chunk;
* a coordinator's batch (:meth:`~como3r.coordination.coordinator.Coordinator.add_keyframes`),
  after each keyframe's verification and before the journal's transaction, once resident
  memory has grown by :data:`TRIM_GROWTH` since (:class:`TrimOnGrowth`). A batch's
  verifications free and allocate several GB of 0.1-20 MB arrays on three threads; what
  they freed stayed resident until the batch's page-out. Measured (the long 16-agent
  replay below, with the simulated prior's features made in blocks): peak resident memory
  5076 MB without, 4582 MB with a ``malloc_trim`` after every keyframe's verification (23 ms
  each), 4488 MB with :class:`TrimOnGrowth`; the coordinator thread's CPU 398, 425 and 427
  ms per keyframe (one run each).

A coordinator's process also keeps one heap for all its threads (:func:`one_heap_arena`).
glibc gives a thread a heap of its own ("arena", up to 8 per core) when it first allocates
while another holds the heap, and each heap keeps what was freed in it for its own reuse:
the coordinator's verification pool decodes on its threads, its session store codes on
others, and its own thread frees much of what they made, so each heap holds its own
high-water mark of freed blocks. Measured (the long 16-agent capture of
``benchmarks/coordinator_replay.py``, 190 keyframes, ``--store --census``,
``OMP_NUM_THREADS=1``, 2 cores): peak resident memory 6490 -> 5430 MB with one arena
(``MALLOC_ARENA_MAX=1``, what :func:`one_heap_arena` sets), the coordinator thread's CPU
427 -> 424 ms per keyframe, the verification's 1550 -> 1610. A fixed mmap threshold
instead (``M_MMAP_THRESHOLD``, 1 or 4 MB) gave 5208 / 5380 MB but cost 49 / 9 % of the
thread's CPU and 52 / 40 % of the verification's (every large array then faults its pages
in anew).

On a C library without ``malloc_trim`` or ``mallopt`` (musl, macOS) nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable

#: ``mallopt`` parameter: the most heaps ("arenas") threads may allocate from
M_ARENA_MAX = -8

#: growth of resident memory [bytes] after which :class:`TrimOnGrowth` gives freed memory
#: back: two to three of a 512x384 pair's decodes (about 100 MB each), so a batch trims
#: every few keyframes, not after each (a ``malloc_trim`` walks the whole heap: 23 ms at 4 GB)
TRIM_GROWTH = 256 * 2**20


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name) if name else None
    except OSError:
        return None


_LIBC = _libc()  # looked up once at import (find_library runs ldconfig)
_MALLOC_TRIM: Callable[[int], int] | None = getattr(_LIBC, "malloc_trim", None)
_MALLOPT: Callable[[int, int], int] | None = getattr(_LIBC, "mallopt", None)
_PAGE_SIZE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def give_back_freed_memory() -> bool:
    """Return the heap's free pages to the system; whether the C library can."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True


def one_heap_arena() -> bool:
    """Let this process's threads share one heap from now on (the module docstring); whether
    the C library took it. Called before the threads that allocate much start: a heap made
    already stays in use."""
    if _MALLOPT is None:
        return False
    return bool(_MALLOPT(M_ARENA_MAX, 1))


def resident_bytes() -> int | None:
    """This process's resident memory [bytes], or None where ``/proc`` does not tell it."""
    try:
        with open("/proc/self/statm", encoding="ascii") as statm:
            return int(statm.read().split()[1]) * _PAGE_SIZE
    except (OSError, IndexError, ValueError):
        return None


class TrimOnGrowth:
    """Gives freed memory back (:func:`give_back_freed_memory`) once resident memory has
    grown by ``growth`` bytes over the lowest it was seen at since the last time.

    Args:
        growth: bytes of growth that make :meth:`check` trim.
        resident: reads resident memory (None: not known, nothing is done).
        trim: gives freed memory back.
    """

    def __init__(
        self,
        growth: int = TRIM_GROWTH,
        resident: Callable[[], int | None] = resident_bytes,
        trim: Callable[[], bool] = give_back_freed_memory,
    ) -> None:
        self.growth, self._resident, self._trim = growth, resident, trim
        self._floor: int | None = None
        #: trims made so far
        self.trims = 0

    def check(self) -> bool:
        """Trim if resident memory has grown enough (the class docstring); whether it did."""
        now = self._resident()
        if now is None:
            return False
        if self._floor is None or now < self._floor:
            self._floor = now
        if now - self._floor < self.growth or not self._trim():
            return False
        self.trims += 1
        self._floor = self._resident()
        return True
