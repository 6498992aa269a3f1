"""Freed memory goes back to the system after a page-out, and a coordinator's threads share
one heap (heap.py)."""

from __future__ import annotations

import ctypes.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from como3r.heap import give_back_freed_memory


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
