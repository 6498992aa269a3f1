"""What ``como3r run``, ``demo``, ``synth``, ``export`` and ``weights fetch`` show while
they work (manual: docs/commands/index.md, "Progress").

Progress goes to stderr, as the progress bar always did (stdout keeps the final summary
tables, so ``como3r run ... > summary.txt`` stays clean), in one of three modes chosen when
the command starts:

* ``rich``, when stderr is a terminal: a live display with one bar per agent (frames
  done/total, frames per second, keyframes, lost and relocalized frames, tracking state,
  time left at the agent's pace after its warm-up, :data:`PACE_FRAMES`) and, once the
  agents are done, one bar for the coordinator's current phase
  (:class:`~como3r.progress.PhaseEvent`: queued keyframes, focal refinement, cleanup
  passes, alternation rounds, outputs, evaluation, report) with the time since that phase
  started. Erased when the work fails, so the ``error:`` line is all that remains.
* ``plain``, when stderr is not a terminal (CI logs, ``2>&1 | tee run.log``): plain lines,
  ``[H:MM:SS] subject: text`` with the time since the command started: per agent at most one
  every :data:`PLAIN_INTERVAL_S` seconds plus its last frame and its failure; for the
  coordinator one as each phase starts, and for a further step of the phase (the next
  alternation round, queued keyframe) one once :data:`PLAIN_INTERVAL_S` seconds have passed
  since its last line.
  They are written through the command's stderr console with rich's markup, highlighting
  and wrapping off, not through :mod:`logging`: they are the command's output, not
  diagnostics, so they do not depend on ``-v`` or on how a library configured the root
  logger, and a log shows them in order with the ``error:`` line and the warnings.
* ``quiet`` (``--quiet``): nothing. Warnings, errors and the final summary still print.

``export`` and ``weights fetch`` show counted work the same way (:meth:`RunProgress.steps`:
keyframes exported, bytes downloaded).
"""

from __future__ import annotations

import contextlib
import datetime
import math
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
)

from como3r import cli_common
from como3r.progress import AgentProgress, PhaseEvent, ProgressEvent

#: plain mode: the least time between two lines of one agent (or of one phase's steps)
PLAIN_INTERVAL_S = 5.0

MODES = ("rich", "plain", "quiet")

#: the ``--quiet`` option's help, the same for every command that has it
QUIET_HELP = "No progress output: only warnings, errors and the final summary."


def _columns() -> tuple[ProgressColumn, ...]:
    """The rich display's columns; ``info`` holds an agent's :meth:`_Agent.text` or a
    phase's detail."""
    return (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}", markup=False),
        TimeElapsedColumn(),
    )


def progress_mode(quiet: bool) -> str:
    """``"quiet"`` under ``--quiet``, else ``"rich"`` on a terminal, else ``"plain"``."""
    if quiet:
        return "quiet"
    return "rich" if cli_common.err_console.is_terminal else "plain"


def _clock_text(seconds: float) -> str:
    """``H:MM:SS`` of a non-negative duration."""
    return str(datetime.timedelta(seconds=int(seconds)))


#: an agent's pace (its fps and time left) spans the later half of the frames it has done,
#: at most this many: the warm-up (compilation, the first keyframes) is slower than the run
#: and stays in the earlier half; a demo's first estimate from the pace since the start was
#: 4:42 for a 1-minute run
PACE_FRAMES = 30
#: no time left is shown before the pace spans this many frames
MIN_PACE_FRAMES = 3


@dataclass
class _Agent:
    """One agent as the display knows it: its latest event and its pace.

    Attributes:
        event: the latest event.
        first_done: frames done at its first event (the pace counts the frames after it).
        printed: clock time of its last plain line.
        task: its rich task.
        marks: ``(frames done, clock time)`` when the count went up, first event included,
            back to :data:`PACE_FRAMES` frames before the latest.
    """

    event: AgentProgress
    first_done: int
    printed: float
    task: TaskID | None = None
    marks: deque[tuple[int, float]] = field(default_factory=deque)

    def update(self, event: AgentProgress, now: float) -> None:
        """Take the agent's new event, seen at clock time ``now``."""
        self.event = event
        if not self.marks or event.frames_done > self.marks[-1][0]:
            self.marks.append((event.frames_done, now))
        while len(self.marks) > 1 and self.marks[1][0] <= event.frames_done - PACE_FRAMES:
            self.marks.popleft()

    def pace(self, now: float) -> tuple[float, int] | None:
        """Frames per second over the later half of the frames done since its first event
        (at most the last :data:`PACE_FRAMES`), and how many frames that is; None before
        a second frame."""
        done = self.event.frames_done
        span = min(PACE_FRAMES, (done - self.first_done) // 2)
        if span < 1:
            return None
        mark = next(((f, t) for f, t in reversed(self.marks) if f <= done - span), None)
        if mark is None or now <= mark[1]:  # the count went back, or no time passed
            return None
        return (done - mark[0]) / (now - mark[1]), done - mark[0]

    def text(self, now: float) -> str:
        """``2.1 fps, 5 keyframes, 3 lost, 1 relocalized, tracking, 0:00:12 left``."""
        e, pace = self.event, self.pace(now)
        fps = pace[0] if pace is not None else None
        parts = [
            f"{fps:.2f} fps" if fps is not None else "- fps",
            f"{e.keyframes} keyframe{'' if e.keyframes == 1 else 's'}",
            f"{e.lost} lost",
        ]
        if e.relocalized:
            parts.append(f"{e.relocalized} relocalized")
        parts.append(e.state)
        left = e.frames_total - e.frames_done if e.frames_total is not None else 0
        if pace is not None and pace[1] >= MIN_PACE_FRAMES and left > 0 and e.state != "failed":
            parts.append(f"{_clock_text(left / pace[0])} left")
        return ", ".join(parts)


def phase_text(event: PhaseEvent) -> str:
    """``alternation round 3/100 (agents 0, 1; previous max |ds| 0.0041)``."""
    step = f" {event.done + 1}/{event.total}" if event.total is not None else ""
    detail = f" ({event.detail})" if event.detail else ""
    return f"{event.name}{step}{detail}"


class RunProgress:
    """The progress display of one command; call it with every
    :class:`~como3r.progress.ProgressEvent` (the ``progress`` callback of a run).

    Args:
        bar: the rich display (disabled outside ``rich`` mode).
        mode: one of :data:`MODES`.
        interval: plain mode's least seconds between two lines of one subject.
        clock: monotonic seconds (tests pass a fake one).
    """

    def __init__(
        self,
        bar: Progress,
        mode: str,
        interval: float = PLAIN_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"progress mode {mode!r} is not one of {MODES}")
        self.bar, self.mode, self.interval, self.clock = bar, mode, interval, clock
        self.start = clock()
        self.agents: dict[int, _Agent] = {}
        self._phase: PhaseEvent | None = None
        self._phase_task: TaskID | None = None
        self._phase_printed = -math.inf

    def __call__(self, event: ProgressEvent) -> None:
        if isinstance(event, AgentProgress):
            self.agent(event)
        else:
            self.phase(event)

    def agent(self, event: AgentProgress) -> None:
        """An agent's new state: its bar, or a plain line when one is due."""
        now = self.clock()
        agent = self.agents.get(event.agent)
        if agent is None:
            agent = self.agents[event.agent] = _Agent(event, event.frames_done, self.start)
        agent.update(event, now)
        if self.mode == "rich":
            if agent.task is None:
                agent.task = self.bar.add_task(f"agent {event.agent}", info="")
            self.bar.update(
                agent.task,
                completed=event.frames_done,
                total=event.frames_total,
                info=agent.text(now),
            )
        elif self.mode == "plain" and (
            now - agent.printed >= self.interval
            or event.frames_done >= (event.frames_total or math.inf)
            or event.state == "failed"
        ):
            agent.printed = now
            total = f"/{event.frames_total}" if event.frames_total is not None else ""
            self._line(
                f"agent {event.agent}", f"{event.frames_done}{total} frames, {agent.text(now)}"
            )

    def phase(self, event: PhaseEvent) -> None:
        """A coordinator step starts: the coordinator's bar, or a plain line when due."""
        now, previous = self.clock(), self._phase
        self._phase = event
        if self.mode == "rich":
            task = self._phase_task
            if task is None or previous is None or previous.name != event.name:
                if task is not None:  # a new phase: a new bar, with its own elapsed time
                    self.bar.remove_task(task)
                task = self._phase_task = self.bar.add_task(event.name, total=event.total, info="")
            self.bar.update(task, completed=event.done, info=event.detail)
        elif self.mode == "plain" and (
            previous is None
            or previous.name != event.name
            or event.done == 0
            or now - self._phase_printed >= self.interval
        ):
            self._phase_printed = now
            self._line("coordinator", phase_text(event))

    def counter(self, name: str, total: int) -> Callable[[], None]:
        """A plain count of ``total`` steps (rendering frames); call the result after each."""
        task = self.bar.add_task(name, total=total, info="")
        done, printed = 0, self.start

        def advance() -> None:
            nonlocal done, printed
            self.bar.advance(task)
            done += 1
            now = self.clock()
            if self.mode == "plain" and (now - printed >= self.interval or done >= total):
                printed = now
                self._line(name, f"{done}/{total}")

        return advance

    def steps(
        self, name: str, unit: Callable[[int], str] = str
    ) -> Callable[[int, int | None], None]:
        """A count whose worker reports how far it is (keyframes exported, bytes
        downloaded): call the result with ``(done, total)``, ``total`` None while unknown.
        Plain mode prints at most one line every :attr:`interval` and the one that
        completes it (none for a total of 0).

        Args:
            name: the bar's description and the plain lines' subject.
            unit: how plain lines write a count (default: the number).
        """
        task = self.bar.add_task(name, total=None, info="")
        printed, finished = self.start, False

        def update(done: int, total: int | None) -> None:
            nonlocal printed, finished
            self.bar.update(task, completed=done, total=total)
            now, complete = self.clock(), bool(total) and done >= total
            if (
                self.mode == "plain"
                and not finished
                and (now - printed >= self.interval or complete)
            ):
                printed, finished = now, complete
                of = f"/{unit(total)}" if total is not None else ""
                self._line(name, f"{unit(done)}{of}")

        return update

    def _line(self, subject: str, text: str) -> None:
        cli_common.err_console.print(
            f"[{_clock_text(self.clock() - self.start)}] {subject}: {text}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


@contextlib.contextmanager
def run_progress(
    quiet: bool = False, columns: Sequence[ProgressColumn] = ()
) -> Iterator[RunProgress]:
    """The progress display of a command in the mode :func:`progress_mode` picks; a rich
    display is erased when the block fails or is interrupted.

    Args:
        quiet: ``--quiet``.
        columns: the rich display's columns (default: description, bar, done/total, the
            agent's or phase's text, elapsed time).
    """
    mode = progress_mode(quiet)
    with cli_common.progress_bar(*(columns or _columns()), shown=mode == "rich") as bar:
        yield RunProgress(bar, mode)
