"""What a decentralized run writes besides its trajectories' frames (:mod:`.runner` writes the
folder): each robot's trajectory and keyframe files, its metrics, the two-stage saving
(F-Fig. 4), loop statistics and the final loop check, the table of formulations and solvers
on the final graph (F-Tables II-III), and ``graph.json``. The network robots
(``como3r robot``) write theirs with the same functions.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from como3r.config import Config
from como3r.config_decentralized import (
    FORMULATIONS,
    SOLVERS,
    DecentralizedConfig,
)
from como3r.data.preprocess import make_view
from como3r.decentralized.consistency import solve_checked
from como3r.decentralized.keyframes import (
    RobotData,
    frame_poses,
)
from como3r.decentralized.messages import RobotReport
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    PoseGraphProblem,
    connected_components,
)
from como3r.errors import Como3rError
from como3r.io.tum import Trajectory, write_tum


def write_trajectories(
    staging: Path, robots: dict[int, RobotData], estimates: dict[int, np.ndarray]
) -> None:
    """``trajectories/agent_<r>.txt`` (every frame with odometry) and
    ``keyframes/agent_<r>.txt`` of each robot ``r``, from its ``(K', 8)`` keyframe estimate
    (its odometry beyond it)."""
    for r, robot in robots.items():
        poses = frame_poses(robot.odometry, robot.keyframes, estimates[r])
        write_tum(staging / "trajectories" / f"agent_{r}.txt", robot.odometry.timestamps, poses)
        write_tum(
            staging / "keyframes" / f"agent_{r}.txt",
            robot.keyframes.timestamps,
            poses[robot.keyframes.rows],
        )


def image_shape(robot: RobotData, config: Config) -> tuple[int, int]:
    """``(H, W)`` of the robot's images at network resolution (``input.long_side``)."""
    frame = robot.agent.load_frame(int(robot.odometry.frames[0]))
    height, width = make_view(frame, 0, config.input.long_side).image.shape[-2:]
    return int(height), int(width)


def robot_metrics(robot: int, report: RobotReport | None) -> dict[str, Any]:
    if report is None:
        return {"robot": robot, "error": "no report"}
    return {
        "robot": robot,
        **report.stats,
        "frame": report.frame,
        "left": report.left,
        "error": report.error,
    }


def two_stage(reports: dict[int, RobotReport]) -> dict[str, float]:
    """F-Fig. 4: encodes of the two-stage scheme versus encoding both images of every pair."""
    naive = sum(r.stats.get("naive_encodes", 0) for r in reports.values())
    used = sum(r.stats.get("registration_encodes", 0) for r in reports.values())
    encodes = sum(r.stats.get("encodes", 0) for r in reports.values())
    encode_seconds = sum(r.stats.get("encode_seconds", 0.0) for r in reports.values())
    mean = encode_seconds / encodes if encodes else 0.0
    return {
        "naive_encodes": naive,
        "two_stage_encodes": used,
        "saved_encodes": naive - used,
        "saved_fraction": (naive - used) / naive if naive else 0.0,
        "mean_encode_seconds": mean,
        "saved_seconds_estimate": (naive - used) * mean,
        "all_encodes_including_place_descriptors": encodes,
    }


def loop_statistics(loops: list[LoopClosure], rejected: list[LoopClosure]) -> dict[str, Any]:
    ratios = np.array([loop.ratio for loop in loops]) if loops else np.zeros(0)
    return {
        "accepted": len(loops),
        "rejected": len(rejected),
        "ratio_median": float(np.median(ratios)) if loops else None,
        "probability_mean": float(np.mean([l.probability for l in loops])) if loops else None,
    }


def _component_problems(
    robots: list[RobotData], loops: list[LoopClosure]
) -> list[PoseGraphProblem]:
    """One pose graph per group of robots connected by loops, anchored on its smallest id
    at its odometry origin, with the robots' declared odometry starts."""
    components = [c for c in connected_components(list(range(len(robots))), loops) if len(c) > 1]
    return [
        PoseGraphProblem(
            odometry={r: robots[r].keyframes.T_OC.numpy() for r in component},
            loops=[l for l in loops if l.robot_a in component],
            anchor=component[0],
            anchor_pose=robots[component[0]].keyframes.T_OC[0].numpy(),
            starts={r: start for r in component if (start := robots[r].start) is not None},
        )
        for component in components
    ]


def final_loop_check(
    robots: list[RobotData], loops: list[LoopClosure], settings: DecentralizedConfig
) -> list[dict[str, Any]]:
    """``metrics.json`` ``loop_check``: for every group of robots, the mission's loops
    that pairwise consistency held back and the scale changes (and alarm) of the configured
    solve of all of them (:mod:`~.consistency`); ``[{"error": ...}]`` if a solve failed."""
    graph = settings.pose_graph_config()
    try:
        return [
            solve_checked(problem, graph.formulation, graph.solver, graph)[1].to_json()
            for problem in _component_problems(robots, loops)
        ]
    except Como3rError as exc:
        return [{"error": str(exc)}]


def formulation_table(
    robots: list[RobotData], loops: list[LoopClosure], settings: DecentralizedConfig
) -> tuple[list[dict[str, Any]], dict]:
    """Every formulation x solver on the mission's full graph (F-Tables II-III).

    Each group of robots connected by loops is anchored on its smallest id at its odometry
    origin; the merged ATE (one Sim(3) per group) is computed against ground truth, which
    the solve never sees.

    Returns:
        The table rows and the GNC weight of every loop for the configured formulation,
        keyed by ``(robot_a, keyframe_a, robot_b, keyframe_b)``.
    """
    from como3r.evaluation.trajectory import associate, merged_errors_by_component

    problems = _component_problems(robots, loops)
    graph = settings.pose_graph_config()
    components = [sorted(problem.odometry) for problem in problems]
    rows, weights = [], {}
    for formulation in FORMULATIONS:
        for solver in SOLVERS:
            estimates = [np.zeros((0, 8)) for _ in robots]
            seconds, inliers, held_back, alarms = 0.0, 0, 0, 0
            try:
                for problem in problems:
                    solution, check = solve_checked(problem, formulation, solver, graph)
                    seconds += solution.seconds
                    inliers += int((solution.loop_weights > 0.5).sum())
                    held_back += int((~check.consistent).sum())
                    alarms += int(check.alarm)
                    for r in problem.odometry:
                        estimates[r] = solution.poses[r]
                    if (formulation, solver) == (graph.formulation, "gnc"):
                        kept = iter(solution.loop_weights)
                        # A loop pairwise consistency held back has weight 0.
                        weights.update(
                            {
                                _loop_key(l): float(next(kept)) if c else 0.0
                                for l, c in zip(problem.loops, check.consistent)
                            }
                        )
            except Como3rError as exc:
                rows.append({"formulation": formulation, "solver": solver, "error": str(exc)})
                continue
            pairs = [
                associate(
                    Trajectory(r.odometry.timestamps, frame_poses(r.odometry, r.keyframes, e)),
                    r.agent.groundtruth,
                    f"agent_{k}",
                    str(r.agent.root),
                )
                for k, (r, e) in enumerate(zip(robots, estimates))
            ]
            merged = merged_errors_by_component(pairs, components)
            rows.append(
                {
                    "formulation": formulation,
                    "solver": solver,
                    "merged_ate_rmse": [m.ate.rmse for m in merged],
                    "merged_ate_mean": [m.ate.mean for m in merged],
                    "merged_ate_std": [m.ate.std for m in merged],
                    "groups": [list(m.agents) for m in merged],
                    "seconds": seconds,
                    "loops": len(loops),
                    "inlier_loops": inliers,
                    "held_back_loops": held_back,
                    "scale_alarms": alarms,
                }
            )
    return rows, weights


def _loop_key(loop: LoopClosure) -> tuple[int, int, int, int]:
    return loop.robot_a, loop.keyframe_a, loop.robot_b, loop.keyframe_b


def graph_document(
    robots: dict[int, RobotData],
    estimates: dict[int, np.ndarray],
    loops: list[LoopClosure],
    rejected: list[LoopClosure],
    groups: list[list[int]],
    weights: dict,
) -> dict[str, Any]:
    """``graph.json``: every keyframe of ``robots`` with its final pose and its odometry
    pose ``T_OC``, accepted and rejected loop closures (with the prior's relative pose
    ``T_ab`` and their GNC weight where ``weights`` has one) and the groups of robots
    sharing a frame: the final pose graph, which ``benchmarks/resolve_decentralized.py``
    solves again."""
    keyframes = []
    for r, robot in robots.items():
        poses = frame_poses(robot.odometry, robot.keyframes, estimates[r])[robot.keyframes.rows]
        for k in range(len(robot.keyframes)):
            keyframes.append(
                {
                    "agent": r,
                    "keyframe": k,
                    "frame": int(robot.keyframes.frames[k]),
                    "timestamp": float(robot.keyframes.timestamps[k]),
                    "T_WC": poses[k].tolist(),
                    "T_OC": robot.keyframes.T_OC[k].tolist(),
                }
            )
    edges = []
    for accepted, group in ((True, loops), (False, rejected)):
        for loop in group:
            edge = {
                "type": "inter",
                "from": [loop.robot_a, loop.keyframe_a],
                "to": [loop.robot_b, loop.keyframe_b],
                "accepted": accepted,
                "ratio": loop.ratio,
                "probability": loop.probability,
                "correspondences": loop.correspondences,
                "odometry_scale": loop.odometry_scale,
                "T_ab": np.asarray(loop.T_ab, dtype=np.float64).tolist(),
            }
            if _loop_key(loop) in weights:
                edge["gnc_weight"] = weights[_loop_key(loop)]
            edges.append(edge)
    return {"keyframes": keyframes, "edges": edges, "components": groups}
