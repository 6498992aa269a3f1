"""Compiled CPU loops: numba compilation for this process's PyTorch thread count.

The per-pixel and per-match loops of como3r's CPU kernels (:mod:`como3r.frontend.
cpu_kernels`, :mod:`como3r.optim.cpu_kernels`) are plain Python functions written in the
subset numba compiles, one loop iteration per pixel or per block of matches, with ``prange``
for the outer loop. :func:`compiled` gives a loop's machine code (compiled once per machine
and cached on disk): serial on one PyTorch thread, parallel over ``torch.get_num_threads()``
threads otherwise, so a kernel uses the cores the process was given and no more.

A loop's first call in a process holds a lock file next to its cache: processes starting
together on a cold cache (a run's agents, parallel test workers) would each compile the same
loop (seconds of CPU); the later ones wait and load the first one's machine code instead.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numba
import torch
from numba import njit

try:
    import fcntl
except ImportError:  # Windows: no lock, each process compiles what its cache lacks
    fcntl = None  # type: ignore[assignment]

__all__ = ["compiled"]

logger = logging.getLogger(__name__)


@functools.cache
def _variant(loop: Callable, parallel: bool, fastmath: frozenset, error_model: str) -> Callable:
    # numba names a cache file after the function, not its options: each variant is a
    # copy of the function under its own name, so neither loads the other's machine code.
    # A closure keeps its cells: numba compiles their values as constants (and keys its
    # cache on them), so a loop made by a factory is specialised to the factory's arguments
    copy = types.FunctionType(
        loop.__code__, loop.__globals__, loop.__name__, loop.__defaults__, loop.__closure__
    )
    copy.__qualname__ = f"{loop.__qualname__}_{'parallel' if parallel else 'serial'}"
    return njit(
        parallel=parallel,
        fastmath=set(fastmath) if fastmath else False,
        cache=True,
        boundscheck=False,
        error_model=error_model,
    )(copy)


def compiled(
    loop: Callable, fastmath: set[str] | None = None, error_model: str = "python"
) -> Callable:
    """``loop`` compiled for this process's PyTorch thread count: serial on one thread (no
    thread pool: a parallel loop's idle workers spin and would take another process's
    core), else parallel over ``torch.get_num_threads()`` threads.

    Args:
        loop: a function numba can compile, its outer loop a ``numba.prange``; a closure's
            variables are compile-time constants.
        fastmath: LLVM fast-math flags (e.g. ``{"reassoc", "contract"}`` to vectorise sums);
            none by default.
        error_model: ``"python"`` (a float division by zero raises) or ``"numpy"`` (it gives
            inf or nan, as numpy does): a loop that divides vectorises only without the
            Python model's check of every divisor.
    """
    threads = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    kernel = _variant(loop, threads > 1, frozenset(fastmath or ()), error_model)
    if threads > 1 and numba.get_num_threads() != threads:
        numba.set_num_threads(threads)
    return kernel if kernel.signatures else functools.partial(_first_call, kernel)


def _first_call(kernel: Any, *args: Any) -> Any:
    """``kernel(*args)`` compiled, or loaded from its cache, while no other process of this
    machine compiles it: one that does compile it first, and this call then loads its code."""
    with _compile_lock(Path(kernel._cache.cache_path) / f"{kernel.py_func.__qualname__}.lock"):
        return kernel(*args)


@contextlib.contextmanager
def _compile_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (created; kept, as removing it would race) among
    processes; released when the holder ends, however it ends."""
    if fcntl is None:
        yield
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        held = open(path, "a")  # closed below, after the caller's block
    except OSError as error:  # a cache folder this process cannot write: compile unlocked
        logger.debug("jit: no compile lock at %s (%s)", path, error)
        held = None
    if held is None:
        yield
        return
    with held:
        fcntl.flock(held, fcntl.LOCK_EX)
        yield  # closing the file releases the lock
