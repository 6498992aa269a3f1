"""Worker processes leave Ctrl-C to the process that started them.

Ctrl-C in a terminal sends SIGINT to the whole foreground process group: the agent (or
robot) processes as well as the main one. The main process turns it into one
``interrupted:`` line and stops its workers; a worker that handled it too would print its own
``KeyboardInterrupt`` traceback, from wherever it was (often still importing torch).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def children_ignore_sigint() -> Iterator[None]:
    """Processes started inside the block ignore SIGINT from their first instruction on.

    A spawned child inherits an ignored signal through ``exec`` and Python then installs no
    ``KeyboardInterrupt`` handler of its own; setting the handler in the child's target would
    come too late (after its imports). Outside the main thread signal handlers cannot be
    changed and the block does nothing. SIGTERM (how workers are stopped) is unaffected.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
