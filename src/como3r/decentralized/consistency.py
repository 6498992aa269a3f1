"""Wrong loops cannot bend the map: pairwise consistency and the scale-collapse alarm.

Two safeguards around :func:`~.pose_graph.solve_pose_graph`:

* **Pairwise consistency maximisation** (PCM): the loops of each robot pair kept are the
  most confident mutually consistent set (:mod:`.pairwise_consistency`); the others are
  held back before the solve.
* **Scale-collapse alarm.** Odometry is metric (F-Sec. III), so before any loop a robot's
  scale is its odometry's. After a solve, each robot's scale change is
  ``log(path length solved / path length of its odometry)``, and the merged map's is the
  log scale of the similarity (Umeyama) from the map before the new loops (the same solve
  with only the consistent loops whose keyframes the previous estimates covered, over at
  least two robots) to the solution. A loop set that moves
  either by more than ``pose_graph.scale_alarm_log`` is held back: the robots keep their
  previous estimates and the alarm is logged and reported (``metrics.json``). The merged
  check does not compare solved loop lengths with their F-Eq. 6 measurements: on the
  aliasing scene of ``tests/decentralized/test_flocc_aliasing.py`` the true loops'
  F-Eq. 6 lengths are 1.1-2x the true ones (median log ratio -0.29 after a correct solve,
  merged ATE 8 mm), which the scale-aware formulations rightly overrule.

:func:`solve_checked` is one solve behind both; :func:`solve_shares` solves every group of
robots connected by loops with it (an elected robot's step, :mod:`.robot`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from como3r.config_decentralized import DecentralizedConfig, PoseGraphConfig
from como3r.decentralized.messages import PoseGraphShare
from como3r.decentralized.pairwise_consistency import consistent_loops
from como3r.decentralized.pose_graph import solve_pose_graph
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    OdometryStart,
    PoseGraphProblem,
    PoseGraphSolution,
    connected_components,
)
from como3r.errors import SolverError

logger = logging.getLogger(__name__)


@dataclass
class LoopCheck:
    """What the safeguards decided for one connected group of robots.

    Attributes:
        robots: the group's robot ids.
        loops: loops offered.
        consistent: ``(L,)`` bool, kept by pairwise consistency.
        robot_scale_log: robot -> log scale change of its trajectory (after the solve).
        merged_scale_log: log scale change of the merged map (NaN without a previous
            merged estimate of at least two robots).
        alarm: the solve was held back because a scale change exceeded the threshold.
    """

    robots: list[int]
    loops: int
    consistent: np.ndarray
    robot_scale_log: dict[int, float] = field(default_factory=dict)
    merged_scale_log: float = float("nan")
    alarm: bool = False

    def to_json(self) -> dict[str, Any]:
        merged = self.merged_scale_log
        return {
            "robots": list(self.robots),
            "loops": self.loops,
            "consistent": int(self.consistent.sum()),
            "held_back": int(self.loops - self.consistent.sum()),
            "robot_scale_log": {str(r): v for r, v in self.robot_scale_log.items()},
            "merged_scale_log": None if math.isnan(merged) else merged,
            "scale_alarm": self.alarm,
        }


def similarity_scale(source: np.ndarray, target: np.ndarray) -> float:
    """Scale of the least-squares similarity (Umeyama) taking points ``source (N, 3)`` onto
    ``target (N, 3)``; NaN when ``source`` has no extent."""
    src, dst = source - source.mean(0), target - target.mean(0)
    variance = float((src**2).sum(1).mean())
    if not variance > 0:
        return float("nan")
    U, D, Vt = np.linalg.svd(dst.T @ src / len(src))
    signs = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        signs[2] = -1.0
    return float((D * signs).sum() / variance)


def scale_changes(
    problem: PoseGraphProblem,
    solution: PoseGraphSolution,
    reference: dict[int, np.ndarray] | None = None,
) -> tuple[dict[int, float], float]:
    """Log scale change of every robot and of the merged map (module docstring).

    Args:
        problem: the graph that was solved.
        solution: its solution.
        reference: robot -> ``(K, 8)`` poses of the merged map before the new loops (the
            solve of the previous loop set), or None.

    Returns:
        ``(robot -> log change, merged log change)``; a robot without any odometry length
        gets 0; the merged change is NaN without a reference of at least two robots.
    """
    robots = {}
    for robot, odometry in problem.odometry.items():
        before = np.linalg.norm(np.diff(odometry[:, :3], axis=0), axis=1).sum()
        after = np.linalg.norm(np.diff(solution.poses[robot][:, :3], axis=0), axis=1).sum()
        robots[robot] = float(np.log(after / before)) if before > 0 and after > 0 else 0.0
    if not reference or len(reference) < 2:
        return robots, float("nan")
    before = np.concatenate([reference[r][:, :3] for r in sorted(reference)])
    after = np.concatenate([solution.poses[r][:, :3] for r in sorted(reference)])
    scale = similarity_scale(before, after)
    return robots, math.log(scale) if scale > 0 else float("nan")


def check_solution(
    problem: PoseGraphProblem,
    solution: PoseGraphSolution,
    consistent: np.ndarray,
    robots: list[int],
    config: PoseGraphConfig,
    reference: dict[int, np.ndarray] | None = None,
) -> LoopCheck:
    """The :class:`LoopCheck` of a solve of ``problem`` restricted to its ``consistent``
    loops (``solution`` is that solve; ``reference`` as :func:`scale_changes`); raises the
    alarm as the module docstring says."""
    robot_logs, merged = scale_changes(problem, solution, reference)
    limit = config.scale_alarm_log
    worst = max(
        [abs(v) for v in robot_logs.values()] + ([abs(merged)] if not math.isnan(merged) else [])
    )
    check = LoopCheck(
        robots, len(problem.loops), consistent, robot_logs, merged, alarm=worst > limit
    )
    if check.alarm:
        logger.warning(
            "robots %s: scale-collapse alarm: the loop set changes scale by "
            "exp(%.3f) (robots %s, merged %.3f; threshold %.3f); held back",
            robots,
            worst,
            {r: round(v, 3) for r, v in robot_logs.items()},
            merged,
            limit,
        )
    return check


def previous_loops(problem: PoseGraphProblem, loops: list[LoopClosure]) -> list[LoopClosure]:
    """The ``loops`` the previous solve could have used: both ends within the previous
    estimates (``problem.initial``) of their robots."""
    known = {r: len(e) for r, e in problem.initial.items()}
    return [
        l
        for l in loops
        if l.keyframe_a < known.get(l.robot_a, 0) and l.keyframe_b < known.get(l.robot_b, 0)
    ]


def _reference(
    problem: PoseGraphProblem,
    kept: list[LoopClosure],
    formulation: str,
    solver: str,
    config: PoseGraphConfig,
) -> dict[int, np.ndarray] | None:
    """The merged map before the new loops: the same solve with only the consistent loops
    the previous solve could have used, over the robots they connect to the anchor; None
    when that is fewer than two robots."""
    old = previous_loops(problem, kept)
    component = next(
        (c for c in connected_components(sorted(problem.odometry), old) if problem.anchor in c), []
    )
    if len(component) < 2 or len(old) == len(kept):
        return None
    before = PoseGraphProblem(
        {r: problem.odometry[r] for r in component},
        [l for l in old if l.robot_a in component],
        problem.anchor,
        problem.anchor_pose,
        {r: e for r, e in problem.initial.items() if r in component},
        {r: s for r, s in problem.starts.items() if r in component},
    )
    return solve_pose_graph(before, formulation, solver, config).poses


def solve_checked(
    problem: PoseGraphProblem, formulation: str, solver: str, config: PoseGraphConfig
) -> tuple[PoseGraphSolution, LoopCheck]:
    """Solve ``problem`` behind both safeguards.

    With ``pose_graph.consistency == "pcm"`` only the pairwise-consistent loops enter the
    solve (every loop otherwise). The merged scale is compared with the solve of the
    consistent loops the previous solve could have used (:func:`previous_loops`), not with
    the previous estimate itself: a first round on a few loops that pairwise consistency
    could not yet tell apart must not veto the round that corrects it. When ``check.alarm``
    is set the solution is held back: the caller keeps its previous estimates.

    Raises:
        ConfigError, SolverError: as :func:`~.pose_graph.solve_pose_graph`.
    """
    if config.consistency == "pcm":
        consistent = consistent_loops(problem, config)
    else:
        consistent = np.ones(len(problem.loops), dtype=bool)
    kept = replace(problem, loops=[l for l, c in zip(problem.loops, consistent) if c])
    if len(kept.loops) < len(problem.loops):
        logger.info(
            "robots %s: %d of %d loops pairwise consistent; the others held back",
            sorted(problem.odometry),
            len(kept.loops),
            len(problem.loops),
        )
    solution = solve_pose_graph(kept, formulation, solver, config)
    reference = _reference(problem, kept.loops, formulation, solver, config)
    check = check_solution(
        problem, solution, consistent, sorted(problem.odometry), config, reference
    )
    return solution, check


def loop_key(loop: LoopClosure) -> tuple[int, int, int, int]:
    """What identifies a loop closure wherever it travels: its two keyframes."""
    return loop.robot_a, loop.keyframe_a, loop.robot_b, loop.keyframe_b


@dataclass
class SharedGraph:
    """The pose graph a group of robots knows together (:func:`merged_graph`).

    Attributes:
        odometry: robot -> ``(K, 8)`` keyframe odometry.
        loops: its loop closures.
        starts: robot -> its declared odometry start (robots without one: undeclared).
    """

    odometry: dict[int, np.ndarray]
    loops: list[LoopClosure]
    starts: dict[int, OdometryStart] = field(default_factory=dict)


def merged_graph(shares: dict[int, PoseGraphShare]) -> SharedGraph:
    """The pose graph the shares know together: every participant's odometry and declared
    start, the odometry relayed for robots not in the round (the longest copy) with their
    declared starts, and every loop once (the first copy, in the order of the shares) whose
    keyframes that odometry holds."""
    odometry: dict[int, np.ndarray] = {r: share.odometry for r, share in shares.items()}
    starts = {r: share.start for r, share in shares.items() if share.start is not None}
    for share in shares.values():
        for robot, relayed in share.relayed.items():
            if robot not in shares and len(relayed) > len(odometry.get(robot, ())):
                odometry[robot] = relayed
            if robot not in shares and robot in share.relayed_starts:
                # a robot's declared start is one for its whole mission, whichever copy
                starts.setdefault(robot, share.relayed_starts[robot])
    loops: dict[tuple[int, int, int, int], LoopClosure] = {}
    for share in shares.values():
        for loop in share.loops:
            if (
                loop.robot_a in odometry
                and loop.robot_b in odometry
                and loop.keyframe_a < len(odometry[loop.robot_a])
                and loop.keyframe_b < len(odometry[loop.robot_b])
            ):
                loops.setdefault(loop_key(loop), loop)
    return SharedGraph(odometry, list(loops.values()), starts)


#: participant -> the graph of the group it was solved in.
Graphs = dict[int, SharedGraph]


def solve_shares(
    shares: dict[int, PoseGraphShare],
    settings: DecentralizedConfig,
    formulation: str | None = None,
    solver: str | None = None,
    checks: list[LoopCheck] | None = None,
    graphs: Graphs | None = None,
) -> dict[int, tuple[np.ndarray, int]]:
    """Solve the pose graph of every group of robots connected by loops.

    The graph is every participant's share with the graph they relay
    (:func:`merged_graph`): robots that met earlier and are absent now take part through
    their odometry and loops, so a team that meets in small groups still solves its whole
    map (and a chain of meetings that closes a loop corrects every robot on it). Each group
    is anchored on its smallest participating robot id, at that robot's current estimate (or
    odometry) of its first keyframe, so the group joins the anchor's frame. Only pairwise
    consistent loops enter a solve, and a group whose solve raises the scale-collapse alarm
    keeps its estimates (:func:`solve_checked`).

    Args:
        shares: every participating robot's share, by robot id.
        settings: decentralized configuration (its formulation and solver by default).
        formulation, solver: override the configured ones.
        checks: if given, receives each group's :class:`~.consistency.LoopCheck`.
        graphs: if given, receives, for every participant in a group of two or more robots
            (held back or not), the odometry, loops and declared starts of its group: what
            it relays later.

    Returns:
        robot -> (``(K, 8)`` poses, frame id) for every participant in a group of two or
        more robots whose solve was not held back.
    """
    graph_config = settings.pose_graph_config()
    known = merged_graph(shares)
    updates: dict[int, tuple[np.ndarray, int]] = {}
    for component in connected_components(sorted(known.odometry), known.loops):
        present = [r for r in component if r in shares]
        if len(component) < 2 or not present:
            continue
        graph = SharedGraph(
            {r: known.odometry[r] for r in component},
            [loop for loop in known.loops if loop.robot_a in component],
            {r: s for r, s in known.starts.items() if r in component},
        )
        if graphs is not None:
            graphs.update({r: graph for r in present})
        anchor = shares[present[0]]
        frame = anchor.frame
        anchor_pose = anchor.estimate[0] if len(anchor.estimate) else anchor.odometry[0]
        problem = PoseGraphProblem(
            odometry=graph.odometry,
            loops=graph.loops,
            anchor=present[0],
            anchor_pose=anchor_pose,
            initial={
                r: shares[r].estimate
                for r in present
                if shares[r].frame == frame and len(shares[r].estimate)
            },
            starts=graph.starts,
        )
        try:
            solution, check = solve_checked(
                problem,
                formulation or graph_config.formulation,
                solver or graph_config.solver,
                graph_config,
            )
        except SolverError as exc:
            logger.warning("robots %s: %s; estimates unchanged", component, exc)
            continue
        if checks is not None:
            checks.append(check)
        if check.alarm:
            continue
        for robot in present:
            updates[robot] = (solution.poses[robot], frame)
    return updates
