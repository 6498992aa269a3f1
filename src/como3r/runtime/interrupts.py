"""Interrupts are checkpoints: Ctrl-C and SIGTERM end a run the same way (manual:
docs/sessions.md, "Interrupting and resuming a run").

Inside :func:`interrupts_are_checkpoints` the first SIGINT or SIGTERM only takes note; the
run's loops call :func:`checkpoint` between messages (a frame in one process, a keyframe
handed to the coordinator, a batch of agent messages), where the session store holds every
message handled, complete, and it raises :class:`RunInterrupted` there: the run stops
reading its input, the store is closed and ``OUT.partial`` is kept for ``--resume``. Once
the input is read (:func:`finishing`) a first signal no longer stops the run: what is left
is the terminal work on what was processed, and the outputs are written. A second signal
aborts at once (``KeyboardInterrupt`` wherever the run is); the store still holds every
transaction committed before it, so the run resumes from there as after ``kill -9``.

A run that must stop for another reason (its disk filling up: :mod:`.disk_guard`) asks for
it with :func:`stop_at_checkpoint`: the next checkpoint raises that error instead, and the
run ends as on a full disk, its store kept for ``--resume``.

Why a checkpoint and not the signal itself: a ``KeyboardInterrupt`` raised in the middle of
a global BA or a store transaction leaves nothing wrong on disk (the transaction rolls
back), but it throws away the keyframe being handled, and SIGTERM's default action would
end the process without closing anything. Agent processes ignore SIGINT
(:mod:`como3r.transport.child_signals`) and are stopped by the run.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from typing import Any

logger = logging.getLogger(__name__)

#: the signals that end a run at its next checkpoint
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class RunInterrupted(KeyboardInterrupt):
    """The run stopped at a checkpoint after a first Ctrl-C or SIGTERM (``signum``); its
    session store holds every message handled before it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _State:
    """What the handlers share with :func:`checkpoint` (one run at a time per process)."""

    def __init__(self) -> None:
        self.active = False
        self.signum: int | None = None
        self.finishing = False
        self.stop: BaseException | None = None  # raised at the next checkpoint


_STATE = _State()


def _name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def _on_signal(signum: int, frame: Any) -> None:
    if _STATE.signum is not None:  # the second: abort (committed transactions are kept)
        raise KeyboardInterrupt
    _STATE.signum = signum
    if _STATE.finishing:
        logger.warning(
            "%s: every input was read; the run finishes and writes its outputs "
            "(again to abort: the session store is kept)",
            _name(signum),
        )
    else:
        logger.warning(
            "%s: the run stops reading its input and keeps its session store "
            "for --resume (again to abort at once)",
            _name(signum),
        )


@contextlib.contextmanager
def interrupts_are_checkpoints() -> Iterator[None]:
    """Within the block SIGINT and SIGTERM end the run at its next :func:`checkpoint`.

    A signal that is ignored when the block starts (SIGINT of a command started in the
    background by a shell) stays ignored. Outside the main thread, where Python delivers no
    signal, and inside another such block, it does nothing.
    """
    if threading.current_thread() is not threading.main_thread() or _STATE.active:
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}
    _STATE.active, _STATE.signum, _STATE.finishing, _STATE.stop = True, None, False, None
    try:
        for signum, handler in previous.items():
            if handler is not signal.SIG_IGN:
                signal.signal(signum, _on_signal)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _STATE.active, _STATE.signum, _STATE.finishing, _STATE.stop = False, None, False, None


def stop_at_checkpoint(error: BaseException) -> bool:
    """Have the next :func:`checkpoint` raise ``error`` (the first asked for wins); whether
    one will: only inside :func:`interrupts_are_checkpoints` and while the run reads input
    (a live run's store cannot be resumed)."""
    if not _STATE.active or _STATE.finishing:
        return False
    if _STATE.stop is None:
        _STATE.stop = error
    return True


def checkpoint() -> None:
    """Raise :class:`RunInterrupted` if a first signal came and the run still reads input,
    or the error :func:`stop_at_checkpoint` was given.

    Call it only where the session store holds everything handled so far."""
    if _STATE.finishing:
        return
    if _STATE.signum is not None:
        raise RunInterrupted(_STATE.signum)
    if _STATE.stop is not None:
        raise _STATE.stop


def finishing() -> None:
    """Every input was read: a first signal from now on lets the terminal work and the
    outputs finish; one that came already stops the run here (nothing of the terminal work
    is stored yet)."""
    checkpoint()
    _STATE.finishing = _STATE.active
