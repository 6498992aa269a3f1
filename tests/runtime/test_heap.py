"""Freed memory goes back to the system after a page-out, and a coordinator's threads share
one heap (heap.py)."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from como3r.heap import TrimOnGrowth, give_back_freed_memory, resident_bytes


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(
    not Path("/proc/self/status").exists() or ctypes.util.find_library("c") is None,
    reason="needs Linux's /proc and a C library to load",
)
def test_memory_freed_below_a_live_block_leaves_the_process() -> None:
    # 200 MB in 100 kB blocks (below glibc's mmap threshold: they come from the heap), the
    # last one kept alive above the others, as a working-set keyframe keeps its arrays
    blocks = [torch.ones(25_000) for _ in range(2000)]
    kept = blocks[-1]
    del blocks
    before = _rss_mb()
    if not give_back_freed_memory():
        pytest.skip("this C library has no malloc_trim")
    # measured: 411 -> 220 MB
    assert before - _rss_mb() > 100
    assert kept.sum() == 25_000


#: a process whose threads each allocate, then count glibc's heaps (``malloc_info``)
_HEAPS_SCRIPT = """
import ctypes, ctypes.util, sys, threading
import numpy as np
from como3r.heap import one_heap_arena
if sys.argv[1] == "one":
    assert one_heap_arena()
arrays, ready = [], threading.Barrier(4)
def work():
    ready.wait()  # all four allocate at once
    arrays.append(np.ones(1 << 18))
threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads: t.start()
for t in threads: t.join()
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
path = sys.argv[2]
stream = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, stream)
libc.fclose(stream)
print(open(path).read().count("<heap nr="))
"""


@pytest.mark.skipif(
    ctypes.util.find_library("c") is None or not hasattr(ctypes.CDLL(None), "malloc_info"),
    reason="needs glibc (malloc_info)",
)
def test_one_heap_arena_keeps_threads_on_one_heap(tmp_path: Path) -> None:
    def heaps(mode: str) -> int:
        info = tmp_path / f"{mode}.xml"
        run = subprocess.run(
            [sys.executable, "-c", _HEAPS_SCRIPT, mode, str(info)], capture_output=True, text=True
        )
        assert run.returncode == 0, run.stderr
        return int(run.stdout.split()[-1])

    # threads that allocate at once get heaps of their own by default, not after the call
    assert heaps("default") > 1
    assert heaps("one") == 1


def test_a_trim_on_growth_trims_once_memory_grew_past_its_lowest_by_the_growth() -> None:
    readings = iter([500, 400, 600, 656, 300, 350, 557, None])
    trims: list[int] = []
    watch = TrimOnGrowth(256, lambda: next(readings), lambda: trims.append(1) or True)
    # 500, 400: the lowest so far; 600 is 200 over it; 656 is 256 over: trimmed, and the
    # reading after the trim (300) is the new lowest; 350 is 50 over, 557 is 257 over
    assert [watch.check() for _ in range(4)] == [False, False, False, True]
    assert [watch.check() for _ in range(1)] == [False]
    assert watch.check() is True and watch.trims == 2 and len(trims) == 2


def test_a_trim_on_growth_does_nothing_where_memory_or_trimming_is_unknown() -> None:
    assert not TrimOnGrowth(1, lambda: None, lambda: True).check()
    watch = TrimOnGrowth(1, iter([0, 10]).__next__, lambda: False)  # no malloc_trim
    assert not watch.check() and not watch.check() and watch.trims == 0


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux's /proc")
def test_resident_bytes_reads_this_process() -> None:
    resident = resident_bytes()
    assert resident is not None and abs(resident / 2**20 - _rss_mb()) < 50
