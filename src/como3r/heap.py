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
  every chunk.

On a C library without ``malloc_trim`` (musl, macOS) nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Callable


def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


_MALLOC_TRIM = _malloc_trim()


def give_back_freed_memory() -> bool:
    """Return the heap's free pages to the system; whether the C library can."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True
