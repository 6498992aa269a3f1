"""Pipelined input: the next frames are read, pre-processed and encoded by the prior on a
worker thread while the front-end works on the current one (issue "Prior-bound speed").

Encoding a frame needs nothing from the SLAM state, so it can run ahead: a bounded queue of
``input.prefetch_frames`` frames (0: in line, no thread) keeps the worker at most that far
ahead. The prior's decode, which needs the keyframe chosen by the frame before, stays in
line. Torch releases the interpreter lock inside its kernels, so on a CPU the encode of
frame k+1 overlaps the matching and solves of frame k on the other core, and on a GPU the
device encodes while the host runs the Python around the solves.

The wall time the front-end waits for a prepared frame is charged to its stage
``prior_encode`` (the input's I/O, done by the worker, is inside it), so an agent's stages
still add up to its wall time.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from como3r.prior.base import Encoding, Prior, View


@dataclass(frozen=True)
class PreparedFrame:
    """A frame ready for :meth:`como3r.frontend.agent.AgentFrontend.process`.

    Attributes:
        agent: the agent's id; index: the frame's index in its stream.
        timestamp: seconds.
        view: the pre-processed frame; colors: ``(H, W, 3)`` uint8 at network resolution.
        encoding: the prior's encoding of ``view``.
    """

    agent: int
    index: int
    timestamp: float
    view: View
    colors: np.ndarray
    encoding: Encoding


#: reads and pre-processes frame ``index`` of agent ``agent``: ``(view, timestamp, colors)``
LoadFrame = Callable[[int, int], tuple[View, float, np.ndarray]]


def prepared_frames(
    schedule: Iterable[tuple[int, int]], load: LoadFrame, prior: Prior, depth: int
) -> Iterator[PreparedFrame]:
    """Prepared frames in ``schedule`` order, ``depth`` of them made ahead on a thread.

    Args:
        schedule: ``(agent, frame index)`` pairs in processing order.
        load: reads and pre-processes one frame.
        prior: encodes the views (its ``encode`` must be safe to call beside ``decode``).
        depth: frames prepared ahead; 0 prepares each when it is asked for, in this thread.

    Raises:
        Whatever ``load`` or ``prior.encode`` raised, when the frame it failed on is due.
    """
    if depth <= 0:
        for agent, index in schedule:
            yield _prepare(agent, index, load, prior)
        return
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    worker = threading.Thread(
        target=_work, args=(schedule, load, prior, items, stop), name="como3r-prefetch", daemon=True
    )
    worker.start()
    try:
        while True:
            item = items.get()
            if item is None:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while worker.is_alive():  # unblock a worker waiting on a full queue
            try:
                items.get_nowait()
            except queue.Empty:
                worker.join(timeout=0.05)


def _prepare(agent: int, index: int, load: LoadFrame, prior: Prior) -> PreparedFrame:
    view, timestamp, colors = load(agent, index)
    return PreparedFrame(agent, index, timestamp, view, colors, prior.encode(view))


def _work(
    schedule: Iterable[tuple[int, int]],
    load: LoadFrame,
    prior: Prior,
    items: queue.Queue,
    stop: threading.Event,
) -> None:
    """The worker: prepare every frame in order; end with None or the exception."""
    try:
        for agent, index in schedule:
            if stop.is_set():
                return
            items.put(_prepare(agent, index, load, prior))
        items.put(None)
    except BaseException as exc:  # handed to the consumer, raised where the frame is due
        items.put(exc)
