"""Pairwise consistency maximisation of loops (PCM, Mangelson et al. 2018, as Kimera-Multi
and Swarm-SLAM use it): the first safeguard of :mod:`.consistency`.

Two loops ``i``, ``j`` between the same two robots ``a``, ``b`` (or within one robot) close a
cycle with the odometry between their endpoints::

    E_ij = (Z_i O_b(kb_i -> kb_j))^-1 O_a(ka_i -> ka_j) Z_j   (identity if both are right)

where ``Z`` is a loop's relative pose with the prior's translation scaled by its F-Eq. 6
factor and ``O`` the metric odometry. ``Log(E_ij)`` is tested against a chi-square bound (6
dof) with a covariance built from the configured noise models (each loop's as the solve
weighs it, :func:`~.factor_noise.loop_sigmas`, or its full covariance
:func:`~.factor_noise.loop_covariance` carried through the cycle's adjoints where the solve
uses that), all lengths in keyframe spacings (:func:`~.initial_estimate.keyframe_spacing`),
so the test is scale-free. The loops of each robot pair kept are a set of mutually
consistent ones (a clique of the consistency graph); the others are held back before the
solve. The set is the clique of largest summed confidence (F-Eq. 2) rather than PCM's
largest clique: loops of low confidence have wide tolerances and agree with almost
anything. Look-alike places that register to a plausible pose disagree with the true loops
through the odometry, and so do true places whose prior scale is wrong (their translation,
scaled, no longer closes the cycle).
"""

from __future__ import annotations

import math

import gtsam
import networkx as nx
import numpy as np
from scipy.stats import chi2

from como3r.config_decentralized import PoseGraphConfig
from como3r.decentralized.factor_noise import (
    loop_covariance,
    loop_sigmas,
    robot_start,
    start_variance,
)
from como3r.decentralized.initial_estimate import initial_scales, keyframe_spacing
from como3r.decentralized.pose_graph_problem import LoopClosure, PoseGraphProblem, to_pose3

_DOF = 6
#: Loops of one robot pair up to which the clique is searched exactly: the exact search
#: took 0.3 s (CPU) on 100 loops and 4.7 s on 200 (a fifth of them wrong); beyond, greedy.
MAX_EXACT_LOOPS = 120


def oriented_loop(loop: LoopClosure, scale: float) -> tuple[int, int, int, int, gtsam.Pose3]:
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
        first, second: :func:`oriented_loop` tuples of two loops between the same robots.
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
    of its :func:`oriented_loop` pose: ``Z = M^-1`` perturbs as ``Ad(M)`` of ``M``'s error."""
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
    oriented = [oriented_loop(loop, s) for loop, s in zip(loops, scales)]
    start = {
        r: start_variance(o, spacing, robot_start(problem, r, config))
        for r, o in problem.odometry.items()
    }
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
