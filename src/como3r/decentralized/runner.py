"""``como3r run --mode decentralized``: FLOCC-SLAM over agent inputs, end to end.

:func:`run_decentralized` validates every input (each needs ``odometry.txt``), runs the
robots (:func:`~como3r.decentralized.protocol.run_protocol`), and writes the output folder
(manual: docs/outputs.md, "Run output"):

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
from como3r.config_decentralized import (
    FORMULATIONS,
    SOLVERS,
    DecentralizedConfig,
    check_config,
)
from como3r.decentralized.keyframes import (
    FrameOdometry,
    Keyframes,
    RobotData,
    open_robot,
    select_keyframes,
)
from como3r.decentralized.messages import RobotProgress, RobotReport
from como3r.decentralized.outputs import (
    final_loop_check,
    formulation_table,
    graph_document,
    image_shape,
    loop_statistics,
    robot_metrics,
    two_stage,
    write_trajectories,
)
from como3r.decentralized.protocol import ProtocolResult, run_protocol
from como3r.decentralized.schedule import Schedule
from como3r.errors import Como3rError, InputError
from como3r.io.output import atomic_output_dir, check_output_dir
from como3r.prior.base import Prior
from como3r.progress import AgentProgress, PhaseCallback, ProgressCallback, report_phase


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
    robots = [open_robot(path, config, settings) for path in agent_paths]
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
        robots,
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
        "robots": [
            {
                **robot_metrics(r, reports.get(r)),
                # its declared odometry start in the pose graph's units (None: undeclared)
                "odometry_start": start and dataclasses.asdict(start),
            }
            for r, start in enumerate(robot.start for robot in robots)
        ],
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
        metrics["table"], table_weights = formulation_table(robots, loops, settings)
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
