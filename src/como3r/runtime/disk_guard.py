"""A run stops before its disk is full (issue 39 item 4; manual: docs/sessions.md, "A disk
that fills up").

After every transaction of the session store (:attr:`~como3r.store.writer.SessionStore.on_commit`)
:class:`DiskGuard` reads the free space of the output folder's file system and measures how
fast the run fills it: the free space lost per keyframe stored since the run (or its resume)
began, which counts the store's files (its write-ahead log included) and whatever else the
run writes there. From the agents' progress (:class:`~como3r.progress.AgentProgress`) it
knows the input left: the frames still to read times the keyframes per frame so far.

* When, at that rate, the input left and the outputs would not fit, it warns once (a log
  line, which the command line shows), saying how much space the run needs.
* When the free space falls under the reserve (``session.disk_reserve_mb``; by default eight
  keyframes at the measured rate plus the outputs, estimated as large as the store's files:
  beside the store the outputs weighed 0.3 times it on the 64x48 test scene, 1.3 times on
  the demo scene; at least 16 MB), it
  stops the run at its next checkpoint (:func:`~como3r.runtime.interrupts.stop_at_checkpoint`)
  with a full disk's error (``ENOSPC``): the run ends as on a full disk, ``OUT.partial`` kept
  with its store, and the command line names the space needed and the ``--resume`` command.
  The terminal work and the outputs are written in the reserve.
"""

from __future__ import annotations

import errno
import logging
import shutil
from pathlib import Path
from typing import Any

from como3r.progress import AgentProgress, ProgressCallback, ProgressEvent
from como3r.runtime.interrupts import stop_at_checkpoint
from como3r.store.writer import SessionStore

logger = logging.getLogger(__name__)

MB = 2**20
#: keyframes' worth of space the automatic reserve keeps free
RESERVE_KEYFRAMES = 8
#: the automatic reserve's floor
RESERVE_FLOOR_BYTES = 16 * MB


def free_bytes(folder: Path) -> int:
    """Free space of the file system holding ``folder``, for an unprivileged user."""
    return shutil.disk_usage(folder).free


class DiskGuard:
    """Watches the free space of a run's output folder as its store grows.

    Args:
        reserve_mb: stop under this much free space (0: automatic, see the module).
        progress: the run's progress callback, which :meth:`progress` forwards to.
    """

    def __init__(self, reserve_mb: float, progress: ProgressCallback | None) -> None:
        self.reserve_mb = reserve_mb
        self.forward = progress
        self.folder: Path | None = None
        self.agents: dict[int, AgentProgress] = {}
        self.warned = False
        self.stopped = False
        self.lowest_free: int | None = None
        self.per_keyframe: float | None = None
        self._start: tuple[int, int] | None = None  # (free bytes, keyframes) at the start

    def progress(self, event: ProgressEvent) -> None:
        """The run's progress callback: notes each agent's frames and keyframes."""
        if isinstance(event, AgentProgress):
            self.agents[event.agent] = event
        if self.forward is not None:
            self.forward(event)

    def watch(self, store: SessionStore) -> None:
        """Check the free space after each of ``store``'s transactions, from now on."""
        self.folder = store.path.parent
        self._start = (free_bytes(self.folder), store.written_metrics()["keyframes"])
        store.on_commit = self.check

    def reserve(self, store_bytes: int) -> int:
        """The free space below which the run stops, in bytes."""
        if self.reserve_mb > 0:
            return int(self.reserve_mb * MB)
        per_keyframe = self.per_keyframe or 0.0
        return max(RESERVE_FLOOR_BYTES, int(RESERVE_KEYFRAMES * per_keyframe + store_bytes))

    def keyframes_left(self) -> float | None:
        """Keyframes the input left will make at the rate so far (None: not known yet, or a
        live input of unknown length)."""
        done = sum(p.frames_done for p in self.agents.values())
        if not done or any(p.frames_total is None for p in self.agents.values()):
            return None
        left = sum(max(0, (p.frames_total or 0) - p.frames_done) for p in self.agents.values())
        return left * sum(p.keyframes for p in self.agents.values()) / done

    def check(self, store: SessionStore) -> None:
        """After a transaction: warn once if the input left would not fit, stop the run if
        the free space is under the reserve."""
        assert self.folder is not None and self._start is not None, "watch() first"
        free = free_bytes(self.folder)
        self.lowest_free = free if self.lowest_free is None else min(self.lowest_free, free)
        written = store.written_metrics()
        keyframes = written["keyframes"] - self._start[1]
        if keyframes > 0:
            self.per_keyframe = max(0.0, (self._start[0] - free) / keyframes)
        reserve = self.reserve(written["file_bytes"])
        left = self.keyframes_left()
        needed = reserve + (left or 0.0) * (self.per_keyframe or 0.0)
        if not self.warned and left is not None and self.per_keyframe and needed > free:
            self.warned = True
            logger.warning(
                "disk: at %.1f MB per keyframe the input left (about %.0f keyframes) and the "
                "outputs need %.1f MB in %s, which has %.1f MB free: the run will stop, "
                "resumable, when under %.1f MB are left",
                self.per_keyframe / MB,
                left,
                needed / MB,
                self.folder,
                free / MB,
                reserve / MB,
            )
        if free < reserve and not self.stopped:
            error = OSError(
                errno.ENOSPC,
                f"{self.folder} has {free / MB:.1f} MB free, under the reserve of "
                f"{reserve / MB:.1f} MB for the outputs (session.disk_reserve_mb): the run "
                f"stopped before its disk is full; it needs about "
                f"{(needed - free) / MB:.1f} MB more free space to finish",
            )
            self.stopped = stop_at_checkpoint(error)
            if not self.stopped:  # past its input, or live: no resumable stop now
                logger.warning("disk: %s; past its input or live, the run goes on", error.strerror)

    def to_json(self) -> dict[str, Any]:
        """``metrics.json``'s ``store.disk``: the disk's use as the run saw it."""
        return {
            "free_bytes_lowest": self.lowest_free,
            "disk_bytes_per_keyframe": self.per_keyframe,
            "reserve_mb": self.reserve_mb or None,
            "warned": self.warned,
        }


def store_metrics(store: SessionStore) -> dict[str, Any]:
    """``metrics.json``'s ``store``: what the store wrote
    (:meth:`~como3r.store.writer.SessionStore.written_metrics`) and, under a guard, ``disk``."""
    metrics = store.written_metrics()
    guard = getattr(store.on_commit, "__self__", None)
    if isinstance(guard, DiskGuard):
        metrics["disk"] = guard.to_json()
    return metrics
