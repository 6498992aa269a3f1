"""Rendezvous schedules of the decentralized mode (:mod:`.protocol`): which robots are in
communication range when, the exchange rounds they imply, and who is elected to optimise in
a round's group.

A schedule file has one line per robot,

    robot_id,start_s,end_s[,start_s,end_s...]

listing the mission-time windows [s] in which the robot is in communication range (of the
rendezvous point; two robots can talk when both are in range). A robot without a line is
never in range; without a schedule every robot always is. Exchange rounds happen when a
window closes, every ``round_period_s`` while robots are in range, and at the end of the
mission; the group of a round is every robot in range at its time. The robot with the
smallest id in a group is elected to optimise (Swarm-SLAM, F-[9]; :func:`elect`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from como3r.decentralized.robot import RoundPlan
from como3r.errors import InputError


@dataclass(frozen=True)
class Schedule:
    """When each robot is in communication range.

    Attributes:
        windows: robot -> sorted ``(start_s, end_s)`` windows; None: always in range.
    """

    windows: dict[int, list[tuple[float, float]]] | None = None

    def in_range(self, robot: int, time_s: float) -> bool:
        """Whether ``robot`` is in range at ``time_s`` (windows are closed intervals)."""
        if self.windows is None:
            return True
        return any(start <= time_s <= end for start, end in self.windows.get(robot, ()))

    def hears(self, receiver: int, sender: int, time_s: float) -> bool:
        """The link filter: whether ``receiver`` hears a message ``sender`` sent at mission
        time ``time_s`` (both in range of the rendezvous)."""
        return self.in_range(receiver, time_s) and self.in_range(sender, time_s)

    def group(self, robots: Sequence[int], time_s: float) -> tuple[int, ...]:
        """The robots of ``robots`` in range at ``time_s``, sorted."""
        return tuple(sorted(r for r in robots if self.in_range(r, time_s)))

    def round_times(self, end_s: float, period_s: float = 0.0) -> list[float]:
        """Round times up to ``end_s``: window ends, every ``period_s`` (if > 0) and ``end_s``."""
        times = {float(end_s)}
        if self.windows is not None:
            times.update(
                end for windows in self.windows.values() for _, end in windows if end <= end_s
            )
        if period_s > 0:
            times.update(float(t) for t in np.arange(period_s, end_s, period_s))
        return sorted(times)


def read_schedule(path: str | Path) -> Schedule:
    """Parse a rendezvous file (module docstring); ``#`` starts a comment.

    Raises:
        InputError: naming the line of a malformed entry.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the rendezvous schedule ({exc})") from None
    windows: dict[int, list[tuple[float, float]]] = {}
    for line_no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p.strip() for p in text.split(",")]
        where = f"{path}:{line_no}"
        if len(parts) < 3 or len(parts) % 2 == 0:
            raise InputError(
                f"{where}: expected robot_id,start_s,end_s[,start_s,end_s...], got {text!r}"
            )
        try:
            robot = int(parts[0])
            bounds = [float(p) for p in parts[1:]]
        except ValueError:
            raise InputError(f"{where}: not a number in {text!r}") from None
        if robot < 0 or robot in windows:
            raise InputError(f"{where}: robot id {robot} is negative or listed twice")
        pairs = list(zip(bounds[0::2], bounds[1::2]))
        if not all(math.isfinite(a) and math.isfinite(b) and a <= b for a, b in pairs):
            raise InputError(f"{where}: every window needs finite start_s <= end_s")
        windows[robot] = sorted(pairs)
    return Schedule(windows)


def elect(group: Sequence[int]) -> int:
    """The robot that optimises for ``group``: the smallest id (Swarm-SLAM, F-[9])."""
    if not group:
        raise ValueError("cannot elect a robot in an empty group")
    return min(group)


def plan_rounds(
    schedule: Schedule, robots: Sequence[int], end_s: float, period_s: float = 0.0
) -> list[RoundPlan]:
    """Every round with at least two robots in range, numbered in time order."""
    plans = []
    for time_s in schedule.round_times(end_s, period_s):
        group = schedule.group(robots, time_s)
        if len(group) >= 2:
            plans.append(RoundPlan(len(plans), time_s, group))
    return plans
