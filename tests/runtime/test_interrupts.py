"""Interrupts are checkpoints (runtime/interrupts.py): the first Ctrl-C or SIGTERM is noted
and ends the run at its next checkpoint, a second aborts at once; once the input is read a
first one lets the run finish; a signal ignored before stays ignored."""

from __future__ import annotations

import os
import signal
import time

import pytest

from como3r.runtime.interrupts import (
    RunInterrupted,
    checkpoint,
    finishing,
    interrupts_are_checkpoints,
)


def _send(signum: int) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.05)  # the handler runs between two bytecodes


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_the_first_signal_stops_at_the_checkpoint_and_the_second_aborts(signum) -> None:
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with interrupts_are_checkpoints():
        checkpoint()  # nothing yet
        _send(signum)  # noted, not raised here
        with pytest.raises(RunInterrupted) as stopped:
            checkpoint()
        assert stopped.value.signum == signum
        with pytest.raises(KeyboardInterrupt) as aborted:
            _send(signal.SIGINT)
        assert not isinstance(aborted.value, RunInterrupted)
    assert {s: signal.getsignal(s) for s in before} == before
    checkpoint()  # the next run starts afresh


def test_once_the_input_is_read_a_first_signal_lets_the_run_finish() -> None:
    with interrupts_are_checkpoints():
        finishing()
        _send(signal.SIGTERM)
        checkpoint()  # the terminal work goes on
        with pytest.raises(KeyboardInterrupt):
            _send(signal.SIGINT)


def test_a_signal_ignored_before_stays_ignored() -> None:
    """A command started in the background by a shell ignores Ctrl-C."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with interrupts_are_checkpoints():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            _send(signal.SIGINT)
            checkpoint()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
