"""A compiled loop's first call holds a lock among processes (:mod:`como3r.jit`), so that
processes starting together on a cold cache compile each loop once."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numba import prange

from como3r import jit

#: exits 0 when it takes the lock at argv[1] without waiting, 1 when another process holds it
TRY_LOCK = (
    "import fcntl, sys\n"
    "with open(sys.argv[1], 'a') as f:\n"
    "    try:\n"
    "        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
    "    except BlockingIOError:\n"
    "        sys.exit(1)\n"
)


def _doubled(x: np.ndarray, out: np.ndarray) -> None:
    for i in prange(x.shape[0]):
        out[i] = 2.0 * x[i]


def _free(path: Path) -> bool:
    return subprocess.run([sys.executable, "-c", TRY_LOCK, str(path)], timeout=60).returncode == 0


def test_the_compile_lock_excludes_other_processes_until_released(tmp_path) -> None:
    path = tmp_path / "cache" / "loop.lock"
    with jit._compile_lock(path):
        assert not _free(path)
    assert _free(path)


def test_only_a_loops_first_call_takes_the_lock_next_to_its_cache(monkeypatch) -> None:
    taken: list[Path] = []

    @contextlib.contextmanager
    def recorded(path: Path) -> Iterator[None]:
        taken.append(path)
        yield

    monkeypatch.setattr(jit, "_compile_lock", recorded)
    jit._variant.cache_clear()  # a new dispatcher: in this process, no call yet
    x = np.arange(5, dtype=np.float64)
    for _ in range(2):
        out = np.zeros_like(x)
        jit.compiled(_doubled)(x, out)
        np.testing.assert_array_equal(out, 2.0 * x)
    assert len(taken) == 1
    kernel = jit.compiled(_doubled)
    assert taken[0] == Path(kernel._cache.cache_path) / f"{kernel.py_func.__qualname__}.lock"
    assert taken[0].name.startswith("_doubled_")


def test_a_lock_that_cannot_be_made_does_not_stop_the_compile(tmp_path) -> None:
    blocker = tmp_path / "cache"
    blocker.write_text("a file where the cache folder would be")
    with jit._compile_lock(blocker / "loop.lock"):
        ran = True
    assert ran
