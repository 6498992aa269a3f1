"""Freed memory goes back to the system after a page-out (heap.py)."""

from __future__ import annotations

import ctypes.util
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
