"""Frames read and encoded ahead on a worker thread (como3r.runtime.prefetch)."""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import pytest
import torch

from como3r.prior.base import View
from como3r.runtime.prefetch import prepared_frames


class _CountingPrior:
    """Encodes a view as its (agent, index); records the threads that encoded."""

    def __init__(self) -> None:
        self.threads: set[str] = set()

    def encode(self, view: View) -> tuple[int, int]:
        self.threads.add(threading.current_thread().name)
        return view.agent, view.index


def _load(agent: int, index: int) -> tuple[View, float, np.ndarray]:
    if index == 13:
        raise OSError("frame 13 is unreadable")
    view = View(image=torch.zeros(3, 4, 4), agent=agent, index=index)
    return view, 0.1 * index, np.zeros((4, 4, 3), np.uint8)


@pytest.mark.parametrize("depth", [0, 1, 3])
def test_frames_arrive_in_schedule_order_encoded(depth: int) -> None:
    schedule = [(0, 0), (1, 0), (0, 2), (1, 2), (0, 4)]
    prior = _CountingPrior()
    with contextlib.closing(prepared_frames(iter(schedule), _load, prior, depth)) as frames:
        got = [(f.agent, f.index, f.encoding, f.timestamp) for f in frames]
    assert got == [(a, i, (a, i), 0.1 * i) for a, i in schedule]
    assert prior.threads == ({"MainThread"} if depth == 0 else {"como3r-prefetch"})


@pytest.mark.parametrize("depth", [0, 2])
def test_a_failed_frame_raises_when_it_is_due(depth: int) -> None:
    frames = prepared_frames(((0, i) for i in range(11, 16)), _load, _CountingPrior(), depth)
    with contextlib.closing(frames):
        assert [next(frames).index, next(frames).index] == [11, 12]
        with pytest.raises(OSError, match="frame 13"):
            next(frames)


def test_closing_early_stops_the_worker() -> None:
    frames = prepared_frames(((0, i) for i in range(1000)), _load, _CountingPrior(), 2)
    next(frames)
    frames.close()
    assert not [t for t in threading.enumerate() if t.name == "como3r-prefetch"]
