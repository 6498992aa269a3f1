"""Wrong loops cannot bend the map: pairwise consistency and the scale-collapse alarm.

Two safeguards around :func:`~.pose_graph.solve_pose_graph`:

* **Pairwise consistency maximisation** (PCM, Mangelson et al. 2018, as Kimera-Multi and
  Swarm-SLAM use it). Two loops ``i``, ``j`` between the same two robots ``a``, ``b`` (or
  within one robot) close a cycle with the odometry between their endpoints::

      E_ij = (Z_i O_b(kb_i -> kb_j))^-1 O_a(ka_i -> ka_j) Z_j   (identity if both are right)

  where ``Z`` is a loop's relative pose with the prior's translation scaled by its F-Eq. 6
  factor and ``O`` the metric odometry. ``Log(E_ij)`` is tested against a chi-square bound
  (6 dof) with a covariance built from the configured noise models (each loop's as the
  solve weighs it, :func:`~.factor_noise.loop_sigmas`, or its full covariance
  :func:`~.factor_noise.loop_covariance` carried through the cycle's adjoints where the solve
  uses that), all lengths in keyframe
  spacings (:func:`~.initial_estimate.keyframe_spacing`), so the test is scale-free. The loops of
  each robot pair kept are a set of mutually consistent ones (a clique of the consistency
  graph); the others are held back before the solve. The set is the clique of largest summed
  confidence (F-Eq. 2) rather than PCM's largest clique: loops of low confidence have wide
  tolerances and agree with almost anything. Look-alike places that register to a
  plausible pose disagree with the true loops through the odometry, and so do true places
  whose prior scale is wrong (their translation, scaled, no longer closes the cycle).
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
from dataclasses import dataclass, field
from typing import Any

import gtsam
import networkx as nx
import numpy as np
from scipy.stats import chi2

from como3r.config_decentralized import DecentralizedConfig, PoseGraphConfig
from como3r.decentralized.factor_noise import loop_covariance, loop_sigmas, start_variance
from como3r.decentralized.initial_estimate import initial_scales, keyframe_spacing
from como3r.decentralized.messages import PoseGraphShare
from como3r.decentralized.pose_graph import solve_pose_graph
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    PoseGraphProblem,
    PoseGraphSolution,
    connected_components,
    to_pose3,
)
from como3r.errors import SolverError

logger = logging.getLogger(__name__)

_DOF = 6
#: Loops of one robot pair up to which the clique is searched exactly: the exact search
#: took 0.3 s (CPU) on 100 loops and 4.7 s on 200 (a fifth of them wrong); beyond, greedy.
MAX_EXACT_LOOPS = 120


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


def _oriented(loop: LoopClosure, scale: float) -> tuple[int, int, int, int, gtsam.Pose3]:
    """``(a, ka, b, kb, Z)`` with ``a <= b`` and ``Z`` the scaled pose of ``b:kb`` in
    ``a:ka`` (the loop inverted if it was registered the other way round)."""
    pose = to_pose3(loop.T_ab)
    Z = gtsam.Pose3(pose.rotation(), scale * pose.translation())
    if loop.robot_a <= loop.robot_b:
        return loop.robot_a, loop.keyframe_a, loop.robot_b, loop.keyframe_b, Z
    return loop.robot_b, loop.keyframe_b, loop.robot_a, loop.keyframe_a, Z.inverse()


def _odometry_between(odometry: np.ndarray, i: int, j: int) -> gtsam.Pose3:
    return to_pose3(odometry[i]).between(to_pose3(odometry[j]))


def _start_between(start: dict[int, np.ndarray] | None, robot: int, i: int, j: int) -> float:
    if start is None:
        return 0.0
    return float(abs(start[robot][j] - start[robot][i]))


def pair_chi2(
    first: tuple,
    second: tuple,
    p_first: float,
    p_second: float,
    odometry: dict[int, np.ndarray],
    spacing: float,
    config: PoseGraphConfig,
    start: dict[int, np.ndarray] | None = None,
    covariances: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """Whitened squared residual of the cycle of two oriented loops (module docstring).

    Args:
        first, second: :func:`_oriented` tuples of two loops between the same robots.
        p_first, p_second: their confidences (F-Eq. 2); each loop's noise is the solve's
            (:func:`~.factor_noise.loop_sigmas`: F-Eq. 3 with the translation floor).
        odometry: robot -> ``(K, 8)`` odometry poses.
        spacing: the keyframe spacing, in odometry units.
        config: noise models; the scale scatter is ``scale_smoothing_sigma``.
        start: robot -> ``(K,)`` summed variance of its odometry's unconverged scale
            (:func:`~.factor_noise.start_variance`), counted in every direction; None: none.
        covariances: the two loops' ``(6, 6)`` covariances in their oriented frames
            (:func:`oriented_covariance`); given, they replace the loops' isotropic sigmas
            and reach the cycle's error through its adjoints (first order); None: the
            isotropic sigmas of :func:`~.factor_noise.loop_sigmas`.

    Returns:
        The chi-square statistic (6 dof) of ``Log(E_ij)``.
    """
    a, ka_i, b, kb_i, Z_i = first
    _, ka_j, _, kb_j, Z_j = second
    O_a = _odometry_between(odometry[a], ka_i, ka_j)
    O_b = _odometry_between(odometry[b], kb_i, kb_j)
    E = Z_i.compose(O_b).inverse().compose(O_a).compose(Z_j)
    e = gtsam.Pose3.Logmap(E)
    n_a, n_b = abs(ka_j - ka_i), abs(kb_j - kb_i)
    odom_rot = math.radians(config.odom_sigma_rot_deg) ** 2
    # Each loop's noise as the solve weighs it (F-Eq. 3 with the translation floor), unless
    # its full covariance is given (added below).
    if covariances is None:
        rot_i, trans_i = loop_sigmas(p_first, spacing, config)
        rot_j, trans_j = loop_sigmas(p_second, spacing, config)
    else:
        rot_i = rot_j = trans_i = trans_j = 0.0
    var_rot = (n_a + n_b) * odom_rot + rot_i**2 + rot_j**2
    length_i, length_j = np.linalg.norm(Z_i.translation()), np.linalg.norm(Z_j.translation())
    # Rotation errors turn into translation errors over their lever arms: a rotation random
    # walk along an odometry chain of length L gives n sigma^2 L^2 / 3; the cycle's rotation
    # error acts on both loops' translations.
    var_trans = (
        (n_a + n_b) * (config.odom_sigma_trans_ratio * spacing) ** 2
        + odom_rot
        * (
            n_a * np.linalg.norm(O_a.translation()) ** 2
            + n_b * np.linalg.norm(O_b.translation()) ** 2
        )
        / 3
        + trans_i**2
        + trans_j**2
        + _start_between(start, a, ka_i, ka_j)
        + _start_between(start, b, kb_i, kb_j)
        + var_rot * (length_i**2 + length_j**2)
        # The scale scatter on the shorter loop's length: a wrong scale that
        # lengthens a loop must not widen its own tolerance.
        + 2 * (config.scale_smoothing_sigma * min(length_i, length_j)) ** 2
    )
    if covariances is None:
        return float(np.dot(e[:3], e[:3]) / var_rot + np.dot(e[3:], e[3:]) / var_trans)
    # E = O_b^-1 Z_i^-1 O_a Z_j: Z_j's right perturbation is E's; Z_i's reaches E through
    # Ad((Z_i^-1 O_a Z_j)^-1).
    carry = Z_i.inverse().compose(O_a).compose(Z_j).inverse().AdjointMap()
    covariance = np.diag([var_rot] * 3 + [var_trans] * 3)
    covariance += carry @ covariances[0] @ carry.T + covariances[1]
    return float(e @ np.linalg.solve(covariance, e))


def oriented_covariance(
    loop: LoopClosure, scale: float, spacing: float, config: PoseGraphConfig
) -> np.ndarray:
    """``(6, 6)``: the loop's covariance (:func:`~.factor_noise.loop_covariance`) in the frame
    of its :func:`_oriented` pose: ``Z = M^-1`` perturbs as ``Ad(M)`` of ``M``'s error."""
    covariance = loop_covariance(loop.T_ab, scale, loop.probability, spacing, config)
    if loop.robot_a <= loop.robot_b:
        return covariance
    pose = to_pose3(loop.T_ab)
    adjoint = gtsam.Pose3(pose.rotation(), scale * pose.translation()).AdjointMap()
    return adjoint @ covariance @ adjoint.T


def consistent_loops(problem: PoseGraphProblem, config: PoseGraphConfig) -> np.ndarray:
    """``(L,)`` bool: the loops of the most confident pairwise-consistent set of each robot
    pair.

    Loops are grouped by their (unordered) pair of robots; two loops of a pair are
    consistent when :func:`pair_chi2` is below the ``consistency_probability`` quantile of
    chi-square (6 dof); the kept set is the clique of that graph with the largest summed
    confidence (F-Eq. 2): exact (networkx) up to :data:`MAX_EXACT_LOOPS` loops per pair,
    greedy beyond (:func:`_greedy_clique`).
    """
    loops = problem.loops
    keep = np.zeros(len(loops), dtype=bool)
    if not loops:
        return keep
    scales = initial_scales(loops, config.scale_init)
    spacing = keyframe_spacing(problem, scales)
    oriented = [_oriented(loop, s) for loop, s in zip(loops, scales)]
    start = {r: start_variance(o, spacing, config) for r, o in problem.odometry.items()}
    covariances = (
        [oriented_covariance(loop, s, spacing, config) for loop, s in zip(loops, scales)]
        if config.loop_scene_depth_ratio > 0
        else None
    )
    threshold = float(chi2.ppf(config.consistency_probability, _DOF))
    pairs: dict[tuple[int, int], list[int]] = {}
    for index, (a, _, b, _, _) in enumerate(oriented):
        pairs.setdefault((a, b), []).append(index)
    for members in pairs.values():
        graph = nx.Graph()
        # Weighted by confidence: loops of low confidence have wide tolerances and agree
        # with almost anything, so by count alone several of them (an aliased façade seen
        # again and again) outvote two confident true loops. Integer weights: networkx's
        # clique search sums them exactly.
        graph.add_nodes_from((i, {"w": 1 + round(1000 * loops[i].probability)}) for i in members)
        for x, i in enumerate(members):
            for j in members[x + 1 :]:
                if (
                    pair_chi2(
                        oriented[i],
                        oriented[j],
                        loops[i].probability,
                        loops[j].probability,
                        problem.odometry,
                        spacing,
                        config,
                        start,
                        None if covariances is None else (covariances[i], covariances[j]),
                    )
                    < threshold
                ):
                    graph.add_edge(i, j)
        if len(members) <= MAX_EXACT_LOOPS:
            clique, _ = nx.max_weight_clique(graph, weight="w")
        else:
            clique = _greedy_clique(graph)
        keep[list(clique)] = True
    return keep


def _greedy_clique(graph: nx.Graph) -> list[int]:
    """A heavy clique of ``graph`` (node weights ``w``): nodes by decreasing weight of their
    closed neighbourhood, each kept if it is consistent with all kept before it."""
    support = {n: graph.nodes[n]["w"] + sum(graph.nodes[m]["w"] for m in graph[n]) for n in graph}
    clique: list[int] = []
    for node in sorted(graph, key=lambda n: (-support[n], n)):
        if all(graph.has_edge(node, other) for other in clique):
            clique.append(node)
    return clique


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
    kept = PoseGraphProblem(
        problem.odometry,
        [l for l, c in zip(problem.loops, consistent) if c],
        problem.anchor,
        problem.anchor_pose,
        problem.initial,
    )
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


def merged_graph(
    shares: dict[int, PoseGraphShare],
) -> tuple[dict[int, np.ndarray], list[LoopClosure]]:
    """The pose graph the shares know together: every participant's odometry, the
    odometry relayed for robots not in the round (the longest copy), and every loop once
    (the first copy, in the order of the shares) whose keyframes that odometry holds.

    Returns:
        ``(robot -> (K, 8) odometry, loops)``.
    """
    odometry: dict[int, np.ndarray] = {r: share.odometry for r, share in shares.items()}
    for share in shares.values():
        for robot, relayed in share.relayed.items():
            if robot not in shares and len(relayed) > len(odometry.get(robot, ())):
                odometry[robot] = relayed
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
    return odometry, list(loops.values())


#: participant -> ``(robot -> odometry, loops)`` of the group it was solved in.
Graphs = dict[int, tuple[dict[int, np.ndarray], list[LoopClosure]]]


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
            (held back or not), the odometry and loops of its group: what it relays later.

    Returns:
        robot -> (``(K, 8)`` poses, frame id) for every participant in a group of two or
        more robots whose solve was not held back.
    """
    graph_config = settings.pose_graph_config()
    odometry, loops = merged_graph(shares)
    updates: dict[int, tuple[np.ndarray, int]] = {}
    for component in connected_components(sorted(odometry), loops):
        present = [r for r in component if r in shares]
        if len(component) < 2 or not present:
            continue
        group_loops = [loop for loop in loops if loop.robot_a in component]
        graph = ({r: odometry[r] for r in component}, group_loops)
        if graphs is not None:
            graphs.update({r: graph for r in present})
        anchor = shares[present[0]]
        frame = anchor.frame
        anchor_pose = anchor.estimate[0] if len(anchor.estimate) else anchor.odometry[0]
        problem = PoseGraphProblem(
            odometry=graph[0],
            loops=group_loops,
            anchor=present[0],
            anchor_pose=anchor_pose,
            initial={
                r: shares[r].estimate
                for r in present
                if shares[r].frame == frame and len(shares[r].estimate)
            },
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
