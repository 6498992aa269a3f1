"""``como3r run --mode decentralized``: FLOCC-SLAM over agent inputs, end to end.

:func:`run_decentralized` validates every input (each needs ``odometry.txt``), runs the
robots (:func:`~como3r.decentralized.protocol.run_protocol`), and writes the output folder
(README, "Run output"):

* ``trajectories/agent_<a>.txt`` every frame with odometry, ``keyframes/agent_<a>.txt``,
  in the frame the robot ended in (robots that met share one);
* ``graph.json``: keyframes, accepted and rejected loop closures, frame groups;
* ``metrics.json``: bytes per robot and message type, encode/decode counts and the
  two-stage saving (F-Fig. 4), loop statistics, ``loop_check`` (the loops pairwise
  consistency held back and the scale changes and scale-collapse alarm of the configured
  solve, :mod:`~.consistency`; each robot's ``scale_alarms`` and ``loops_held_back`` count
  the solves it led), ATE per robot and merged (when every agent has ground truth), and
  the table of F-Tables II-III: every formulation with LM and GNC on the final
  multi-robot graph (all loops of the mission, behind the same safeguards), with its
  merged ATE and solver time;
* ``config.yaml``, ``report.html`` and, with ground truth, ``ate.json`` and
  ``trajectories.png``.

Progress goes to an optional callback as for the centralized mode (:mod:`como3r.progress`):
per robot, its frames with odometry up to the mission time of its latest round and its
keyframes (a robot's odometry never loses track: no lost or relocalized frames), then a
phase event as each step of writing the outputs starts.
"""

from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from como3r.config import Config, config_to_dict
from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput
from como3r.data.preprocess import make_view
from como3r.decentralized.config import (
    FORMULATIONS,
    SOLVERS,
    DecentralizedConfig,
    check_config,
)
from como3r.decentralized.consistency import solve_checked
from como3r.decentralized.keyframes import (
    FrameOdometry,
    Keyframes,
    frame_odometry,
    frame_poses,
    select_keyframes,
)
from como3r.decentralized.messages import RobotProgress, RobotReport
from como3r.decentralized.pose_graph_problem import (
    LoopClosure,
    PoseGraphProblem,
    connected_components,
)
from como3r.decentralized.protocol import ProtocolResult, run_protocol
from como3r.decentralized.schedule import Schedule
from como3r.errors import Como3rError, InputError
from como3r.io.output import atomic_output_dir, check_output_dir
from como3r.io.tum import Trajectory, write_tum
from como3r.prior.base import Prior
from como3r.progress import AgentProgress, PhaseCallback, ProgressCallback, report_phase


@dataclasses.dataclass
class RobotData:
    """The driver's view of one robot: its input, odometry and (after the mission, from
    its report) keyframes."""

    agent: AgentInput
    odometry: FrameOdometry
    keyframes: Keyframes | None = None


def run_decentralized(
    agent_paths: Sequence[str | Path],
    out: str | Path,
    config: Config,
    prior_spec: Any,
    decentralized: DecentralizedConfig | None = None,
    overwrite: bool = False,
    schedule: Schedule | None = None,
    prior: Prior | None = None,
    leave: dict[int, tuple[int, str]] | None = None,
    progress: ProgressCallback | None = None,
) -> Any:
    """Run the decentralized mode and write the output folder.

    Args:
        agent_paths: one agent input per robot (robot ids in this order); each needs
            ``odometry.txt``.
        out: output folder (created atomically).
        config: main configuration (image size, simulated prior, retrieval).
        prior_spec: :class:`~como3r.runtime.pipeline.PriorSpec`.
        decentralized: mode configuration; default ``config.decentralized`` if the main
            configuration has that section, else the defaults.
        overwrite: replace an existing non-empty output folder.
        schedule: rendezvous schedule; default from ``protocol.schedule``.
        prior: a prior shared by robot threads (``protocol.processes`` false only).
        leave: robot -> ``(round, phase)`` at which it drops out (failure injection).
        progress: called with each robot's :class:`~como3r.progress.AgentProgress` as the
            mission starts, after every round it took part in and when it reports (state
            ``failed`` if it failed), and with a :class:`~como3r.progress.PhaseEvent` as each
            step of writing the outputs starts.

    Returns:
        A :class:`~como3r.runtime.pipeline.RunSummary` (output folder, per-robot rows,
        evaluation, notes).

    Raises:
        InputError: a missing or malformed input (before any work starts).
        ConfigError: an invalid decentralized setting.
    """
    from como3r.runtime.pipeline import RunSummary

    settings = decentralized or getattr(config, "decentralized", None) or DecentralizedConfig()
    check_config(settings)
    if not agent_paths:
        raise InputError("no --agent given")
    check_output_dir(out, overwrite)  # the folder is written only after the whole mission
    robots = [open_robot(path, config) for path in agent_paths]
    end_s = max(float(r.odometry.timestamps[-1]) for r in robots)
    started = time.perf_counter()
    result = run_protocol(
        [str(p) for p in agent_paths],
        config,
        settings,
        prior_spec,
        end_s,
        schedule,
        prior,
        leave,
        None if progress is None else RobotProgressAdapter(progress, dict(enumerate(robots))),
    )
    failed = {r: report.error for r, report in result.reports.items() if report.error}
    if len(failed) == len(robots):
        raise Como3rError(f"every robot failed; robot 0: {failed[0].splitlines()[0]}")
    summary = RunSummary(out=Path(out))
    if prior_spec.name == "simulated":
        from como3r.runtime.outputs import SIMULATED_NOTE

        summary.notes.append(SIMULATED_NOTE)
    summary.notes += [f"robot {r} failed: {error.splitlines()[0]}" for r, error in failed.items()]
    for r, robot in enumerate(robots):
        robot.keyframes = reported_keyframes(robot.odometry, result.reports.get(r))
    with atomic_output_dir(out, overwrite=overwrite) as staging:
        _write(
            staging,
            robots,
            result,
            config,
            settings,
            summary,
            time.perf_counter() - started,
            prior_spec.name,
            progress,
        )
    summary.out = Path(out)
    return summary


def open_robot(path: str | Path, config: Config) -> RobotData:
    agent = open_agent(
        path, fps=config.input.frame_rate_hz, format=config.input.format, topic=config.input.topic
    )
    return RobotData(agent, frame_odometry(agent))


class RobotProgressAdapter:
    """The robots' progress messages and reports as per-robot
    :class:`~como3r.progress.AgentProgress` events; the first event of every robot (no
    frames done) is sent when it is built.

    Args:
        progress: where the events go.
        robots: robot id -> its data (only ``odometry`` is read).
    """

    def __init__(self, progress: ProgressCallback, robots: dict[int, RobotData]) -> None:
        self.progress = progress
        self.latest = {
            r: AgentProgress(r, 0, len(robot.odometry), 0, 0, 0) for r, robot in robots.items()
        }
        for event in self.latest.values():
            progress(event)

    def __call__(self, message: RobotProgress | RobotReport) -> None:
        event = self.latest[message.sender]
        if isinstance(message, RobotProgress):
            event = dataclasses.replace(
                event, frames_done=message.frames_done, keyframes=message.keyframes
            )
        elif message.error:
            event = dataclasses.replace(event, state="failed")
        elif not message.left:  # the mission's end: every frame is done
            event = dataclasses.replace(
                event,
                frames_done=event.frames_total,
                keyframes=int(message.stats.get("keyframes", event.keyframes)),
            )
        if event != self.latest[message.sender]:  # the last round may have said it all
            self.latest[message.sender] = event
            self.progress(event)


def reported_keyframes(odometry: FrameOdometry, report: RobotReport | None) -> Keyframes:
    """The keyframes the robot chose: its reported keyframe distance (a fraction of the
    scene depth it measured with the prior, in odometry units) applied to its odometry;
    every frame when the robot failed before reporting one."""
    distance = report.stats.get("keyframe_distance", 0.0) if report is not None else 0.0
    return select_keyframes(odometry, float(distance))


def _frame_groups(reports: dict[int, RobotReport], count: int) -> list[list[int]]:
    """Robots grouped by the frame their final estimate is expressed in."""
    groups: dict[int, list[int]] = defaultdict(list)
    for robot in range(count):
        report = reports.get(robot)
        groups[report.frame if report is not None else robot].append(robot)
    return sorted(groups.values())


def _write(
    staging: Path,
    robots: list[RobotData],
    result: ProtocolResult,
    config: Config,
    settings: DecentralizedConfig,
    summary: Any,
    seconds: float,
    prior: str,
    progress: PhaseCallback | None = None,
) -> None:
    from como3r.runtime.outputs import bandwidth, write_json

    report_phase(progress, "outputs", "config.yaml, trajectories, graph.json")
    reports = result.reports
    document = {**config_to_dict(config), "decentralized": dataclasses.asdict(settings)}
    (staging / "config.yaml").write_text(yaml.safe_dump(document, sort_keys=False))
    estimates = [
        reports[r].estimate if r in reports else np.zeros((0, 8)) for r in range(len(robots))
    ]
    write_trajectories(staging, dict(enumerate(robots)), dict(enumerate(estimates)))
    groups = _frame_groups(reports, len(robots))
    # Loops to a robot that failed before reporting its keyframes name keyframes unknown here.
    known = {r for r, report in reports.items() if "keyframe_distance" in report.stats}
    loops = [
        loop for r in sorted(reports) for loop in reports[r].loops if set(loop.robots) <= known
    ]
    rejected = [
        loop for r in sorted(reports) for loop in reports[r].rejected if set(loop.robots) <= known
    ]
    metrics: dict[str, Any] = {
        "mode": "decentralized",
        "prior": {"name": prior},
        "seconds": seconds,
        "protocol_seconds": result.seconds,
        "rounds": [
            {"round": p.round, "time_s": p.time_s, "group": list(p.group)} for p in result.rounds
        ],
        "frame_groups": groups,
        "bytes": result.traffic.to_json(range(len(robots))),
        "robots": [robot_metrics(r, reports.get(r)) for r in range(len(robots))],
        "bandwidth": [
            {
                "robot": r,
                **bandwidth(
                    result.traffic.sent.get(r, {}), len(robot.keyframes), image_shape(robot, config)
                ),
            }
            for r, robot in enumerate(robots)
        ],
        "two_stage": two_stage(reports),
        "loops": loop_statistics(loops, rejected),
        "loop_check": final_loop_check(robots, loops, settings),
    }
    has_gt = all(r.agent.groundtruth is not None for r in robots)
    table_weights: dict[tuple, float] = {}
    if settings.table and has_gt and loops:
        report_phase(
            progress,
            "formulation table",
            f"{len(FORMULATIONS)} formulations x {len(SOLVERS)} solvers",
        )
        metrics["table"], table_weights = _formulation_table(robots, loops, settings)
    write_json(
        staging / "graph.json",
        graph_document(
            dict(enumerate(robots)),
            dict(enumerate(estimates)),
            loops,
            rejected,
            groups,
            table_weights,
        ),
    )
    for r, robot in enumerate(robots):
        stats = reports[r].stats if r in reports else {}
        summary.agents.append(
            {
                "agent": r,
                "keyframes": len(robot.keyframes),
                "loops": int(stats.get("loops", 0)),
                "rejected": int(stats.get("rejected", 0)),
                "frame": groups.index(next(g for g in groups if r in g)),
            }
        )
    if has_gt:
        from como3r.evaluation.report import evaluate_run

        report_phase(progress, "evaluation", "ATE and RPE through evo")
        evaluation = evaluate_run(
            staging,
            [r.agent.root for r in robots],
            staging,
            components=groups if len(groups) > 1 else None,
        )
        metrics["ate"] = evaluation.to_json()
        summary.evaluation = evaluation
    else:
        summary.notes.append("no ground truth for every agent: ATE not computed")
    write_json(staging / "metrics.json", metrics)
    from como3r.evaluation.html import write_report

    report_phase(progress, "report", "report.html")
    write_report(staging, summary.notes, [r.agent.groundtruth for r in robots] if has_gt else None)


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
    at its odometry origin."""
    components = [c for c in connected_components(list(range(len(robots))), loops) if len(c) > 1]
    return [
        PoseGraphProblem(
            odometry={r: robots[r].keyframes.T_OC.numpy() for r in component},
            loops=[l for l in loops if l.robot_a in component],
            anchor=component[0],
            anchor_pose=robots[component[0]].keyframes.T_OC[0].numpy(),
        )
        for component in components
    ]


def final_loop_check(
    robots: list[RobotData], loops: list[LoopClosure], settings: DecentralizedConfig
) -> list[dict[str, Any]]:
    """``metrics.json`` ``loop_check``: for every group of robots, the mission's loops
    that pairwise consistency held back and the scale changes (and alarm) of the configured
    solve of all of them (:mod:`~.consistency`); ``[{"error": ...}]`` if a solve failed."""
    graph = settings.pose_graph
    try:
        return [
            solve_checked(problem, graph.formulation, graph.solver, graph)[1].to_json()
            for problem in _component_problems(robots, loops)
        ]
    except Como3rError as exc:
        return [{"error": str(exc)}]


def _formulation_table(
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
    components = [sorted(problem.odometry) for problem in problems]
    rows, weights = [], {}
    for formulation in FORMULATIONS:
        for solver in SOLVERS:
            estimates = [np.zeros((0, 8)) for _ in robots]
            seconds, inliers, held_back, alarms = 0.0, 0, 0, 0
            try:
                for problem in problems:
                    solution, check = solve_checked(
                        problem, formulation, solver, settings.pose_graph
                    )
                    seconds += solution.seconds
                    inliers += int((solution.loop_weights > 0.5).sum())
                    held_back += int((~check.consistent).sum())
                    alarms += int(check.alarm)
                    for r in problem.odometry:
                        estimates[r] = solution.poses[r]
                    if (formulation, solver) == (settings.pose_graph.formulation, "gnc"):
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
    """``graph.json``: every keyframe of ``robots`` with its final pose, accepted and
    rejected loop closures (with their GNC weight where ``weights`` has one) and the
    groups of robots sharing a frame."""
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
            }
            if _loop_key(loop) in weights:
                edge["gnc_weight"] = weights[_loop_key(loop)]
            edges.append(edge)
    return {"keyframes": keyframes, "edges": edges, "components": groups}
