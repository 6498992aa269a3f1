"""Rendezvous schedules of the decentralized mode (:mod:`.protocol`): which robots are in
communication range when, the exchange rounds they imply, and who is elected to optimise in
a round's group.

A schedule file has one line per robot and rendezvous point,

    robot_id[@point],start_s,end_s[,start_s,end_s...]

listing the mission-time windows [s] in which the robot is in communication range of the
point (no ``@point``: the one unnamed point). Two robots can talk when both are in range of
one point at the same time; a robot may be in range of several points. A robot without a
line is never in range; without a schedule every robot always is (one group of the whole
team).

Exchange rounds happen, per point, when a window closes, every ``round_period_s`` while
robots are in range, and at the end of the mission; the group of a round is every robot in
range of its point at its time, so a large team meeting in small groups at several points
exchanges within each group only (a robot's bytes per round grow with its group, not with
the team). Rounds at one time are ordered by point, in the order the points first appear
(the unnamed one first): a robot in several groups at once takes part in them in that order.
The robot with the smallest id in a group is elected to optimise (Swarm-SLAM, F-[9];
:func:`elect`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from como3r.errors import InputError

Windows = dict[int, list[tuple[float, float]]]

#: A point's name: letters, digits, ``_``, ``-`` and ``.``.
_POINT = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class Schedule:
    """When each robot is in communication range of which rendezvous point.

    Attributes:
        windows: robot -> sorted ``(start_s, end_s)`` windows at the unnamed point; None
            (and no ``points``): every robot always in range.
        points: point name -> robot -> sorted windows, for the named points, in the order
            they were first listed.
    """

    windows: Windows | None = None
    points: dict[str, Windows] = field(default_factory=dict)

    @property
    def always(self) -> bool:
        """Whether every robot is always in range (no schedule)."""
        return self.windows is None and not self.points

    def _all_points(self) -> list[tuple[str, Windows]]:
        """Every point with its windows, the unnamed one (``""``) first."""
        unnamed = [("", self.windows)] if self.windows is not None else []
        return unnamed + list(self.points.items())

    @staticmethod
    def _at(windows: Windows, robot: int, time_s: float) -> bool:
        return any(start <= time_s <= end for start, end in windows.get(robot, ()))

    def in_range(self, robot: int, time_s: float) -> bool:
        """Whether ``robot`` is in range of some point at ``time_s`` (closed intervals)."""
        if self.always:
            return True
        return any(self._at(windows, robot, time_s) for _, windows in self._all_points())

    def hears(self, receiver: int, sender: int, time_s: float) -> bool:
        """The link filter: whether ``receiver`` hears a message ``sender`` sent at mission
        time ``time_s`` (both in range of one point)."""
        if self.always:
            return True
        return any(
            self._at(windows, receiver, time_s) and self._at(windows, sender, time_s)
            for _, windows in self._all_points()
        )

    def group(self, robots: Sequence[int], time_s: float) -> tuple[int, ...]:
        """The robots of ``robots`` in range of any point at ``time_s``, sorted."""
        return tuple(sorted(r for r in robots if self.in_range(r, time_s)))

    def round_times(self, end_s: float, period_s: float = 0.0) -> list[float]:
        """Round times up to ``end_s`` of all points together: window ends, every
        ``period_s`` (if > 0) and ``end_s``."""
        times: set[float] = set()
        points = self._all_points() or [("", None)]
        for _, windows in points:
            times.update(_point_times(windows, end_s, period_s))
        return sorted(times)

    def rounds(
        self, robots: Sequence[int], end_s: float, period_s: float = 0.0
    ) -> list[tuple[float, tuple[int, ...]]]:
        """``(time_s, group)`` of every round with two or more robots, in time order, then
        by point (one round per point and time)."""
        found: list[tuple[float, int, tuple[int, ...]]] = []
        if self.always:
            found = [(t, 0, tuple(sorted(robots))) for t in _point_times(None, end_s, period_s)]
        for order, (_, windows) in enumerate(self._all_points()):
            for time_s in _point_times(windows, end_s, period_s):
                group = tuple(sorted(r for r in robots if self._at(windows, r, time_s)))
                found.append((time_s, order, group))
        ordered = sorted(found, key=lambda item: (item[0], item[1]))
        return [(time_s, group) for time_s, _, group in ordered if len(group) >= 2]

    def to_json(self) -> dict[str, object] | None:
        """The windows as plain lists (what robots of one team compare); None: always."""
        if self.always:
            return None

        def plain(windows: Windows) -> dict[str, list[list[float]]]:
            return {str(r): [list(w) for w in spans] for r, spans in sorted(windows.items())}

        return {
            name: plain(windows)
            for name, windows in [("", self.windows or {}), *self.points.items()]
        }


def _point_times(windows: Windows | None, end_s: float, period_s: float) -> list[float]:
    """One point's round times up to ``end_s``: its window ends, every ``period_s`` (if
    > 0) and ``end_s``."""
    times = {float(end_s)}
    if windows is not None:
        times.update(end for spans in windows.values() for _, end in spans if end <= end_s)
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
    unnamed: Windows = {}
    points: dict[str, Windows] = {}
    for line_no, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = [p.strip() for p in text.split(",")]
        where = f"{path}:{line_no}"
        if len(parts) < 3 or len(parts) % 2 == 0:
            raise InputError(
                f"{where}: expected robot_id[@point],start_s,end_s[,start_s,end_s...], got {text!r}"
            )
        robot_text, _, point = parts[0].partition("@")
        if "@" in parts[0] and not _POINT.fullmatch(point):
            raise InputError(
                f"{where}: a point name is letters, digits, '_', '-' or '.', got {point!r}"
            )
        try:
            robot = int(robot_text)
            bounds = [float(p) for p in parts[1:]]
        except ValueError:
            raise InputError(f"{where}: not a number in {text!r}") from None
        windows = points.setdefault(point, {}) if point else unnamed
        if robot < 0 or robot in windows:
            at = f" at point {point!r}" if point else ""
            raise InputError(f"{where}: robot id {robot} is negative or listed twice{at}")
        pairs = list(zip(bounds[0::2], bounds[1::2]))
        if not all(math.isfinite(a) and math.isfinite(b) and a <= b for a, b in pairs):
            raise InputError(f"{where}: every window needs finite start_s <= end_s")
        windows[robot] = sorted(pairs)
    return Schedule(unnamed if unnamed or not points else None, points)


def write_schedule(schedule: Schedule, path: str | Path) -> None:
    """Write ``schedule`` in the file format :func:`read_schedule` reads.

    Raises:
        ValueError: the schedule is "always in range", which has no file.
    """
    if schedule.always:
        raise ValueError("an always-in-range schedule has no file: leave the schedule empty")
    lines = ["# robot_id[@point],start_s,end_s[,start_s,end_s...]"]
    for name, windows in [("", schedule.windows or {}), *schedule.points.items()]:
        for robot, spans in sorted(windows.items()):
            bounds = ",".join(f"{start!r},{end!r}" for start, end in spans)
            lines.append(f"{robot}{'@' + name if name else ''},{bounds}")
    Path(path).write_text("\n".join(lines) + "\n")


def pair_schedule(
    pairs: Sequence[tuple[int, int]], start_s: float, end_s: float, laps: int = 1
) -> Schedule:
    """A schedule where each robot pair of ``pairs`` meets at its own point, both in range
    from ``start_s`` to ``end_s``: robots exchange with the neighbours they meet, never with
    the whole team. At one time the pairs meet in the order given, ``laps`` times over
    (points ``a-b``, then ``a-b.2``, ...): along a chain of meetings each robot relays the
    graph it knows (:mod:`.robot`), so a chain that closes a loop is solved whole at its
    last meeting, and a second lap brings that solution to every robot on it."""
    points: dict[str, Windows] = {}
    for lap in range(1, laps + 1):
        for a, b in pairs:
            if a == b or a < 0 or b < 0:
                raise ValueError(f"a meeting needs two distinct robot ids, got {(a, b)}")
            name = f"{a}-{b}" if lap == 1 else f"{a}-{b}.{lap}"
            points[name] = {a: [(start_s, end_s)], b: [(start_s, end_s)]}
    return Schedule(None, points)


@dataclass(frozen=True)
class RoundPlan:
    """One exchange round: its id, mission time and the robots in range."""

    round: int
    time_s: float
    group: tuple[int, ...]


def chain_depths(rounds: list[RoundPlan], robot: int) -> dict[int, int]:
    """Round id -> how many rounds deep ``robot``'s peers may be busy before its round,
    for each of its rounds: 1 plus the longest chain of rounds without it, since its peers
    last met it, in which each round shares a robot with the next. Peers reach a round
    after such earlier rounds, which wait in turn for theirs: in a relay of pairwise
    meetings round a team of N robots, the last robot's first round is N rounds deep."""
    depths: dict[int, int] = {}
    behind: dict[int, int] = {}  # peer -> rounds it may still be in before meeting robot
    for plan in sorted(rounds, key=lambda p: p.round):
        depth = 1 + max((behind.get(q, 0) for q in plan.group if q != robot), default=0)
        if robot in plan.group:
            depths[plan.round] = depth
            behind.update({q: 0 for q in plan.group})
        else:
            behind.update({q: depth for q in plan.group})
    return depths


def elect(group: Sequence[int]) -> int:
    """The robot that optimises for ``group``: the smallest id (Swarm-SLAM, F-[9])."""
    if not group:
        raise ValueError("cannot elect a robot in an empty group")
    return min(group)


def plan_rounds(
    schedule: Schedule, robots: Sequence[int], end_s: float, period_s: float = 0.0
) -> list[RoundPlan]:
    """Every round with at least two robots in range of one point, numbered in time order
    (then by point)."""
    return [
        RoundPlan(r, time_s, group)
        for r, (time_s, group) in enumerate(schedule.rounds(robots, end_s, period_s))
    ]
