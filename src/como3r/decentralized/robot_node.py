"""``como3r robot``: one robot of the decentralized mode (FLOCC-SLAM) as its own process,
talking to its peers over Zenoh (manual: docs/commands/robot.md).

:func:`run_robot` is the robot of :mod:`como3r.decentralized.robot` -- the same keyframes,
place recognition, two-stage registration, election and pose graph as ``como3r run --mode
decentralized`` -- over a :class:`~como3r.decentralized.zenoh_robot.ZenohRobotLink` instead of
the one-process router. Every robot reads the same rendezvous schedule; each plans the
same rounds from it (:func:`~como3r.decentralized.schedule.plan_rounds`, the team's mission
ending at the latest robot's last frame, learnt at start-up) and filters what it hears by
it, so range limits hold without a central router.

A robot writes its own output folder: ``config.yaml``, ``trajectories/agent_<r>.txt`` and
``keyframes/agent_<r>.txt`` in the frame it ended in (the id of the robot whose frame it
joined, ``frame`` in ``metrics.json``), ``graph.json`` (its keyframes and the loop closures
it registered) and ``metrics.json`` (bytes per message type and peer, link-filter drops,
bytes per keyframe, loop and two-stage statistics).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

import yaml

from como3r.config import Config, config_to_dict
from como3r.config_decentralized import check_config
from como3r.decentralized.keyframes import RobotData, open_robot
from como3r.decentralized.messages import RobotHello, RobotReport
from como3r.decentralized.outputs import (
    graph_document,
    image_shape,
    loop_statistics,
    robot_metrics,
    two_stage,
    write_trajectories,
)
from como3r.decentralized.protocol import build_prior, make_robot
from como3r.decentralized.robot import RoundPlan
from como3r.decentralized.runner import RobotProgressAdapter, reported_keyframes
from como3r.decentralized.schedule import Schedule, plan_rounds, read_schedule
from como3r.decentralized.zenoh_robot import (
    RobotKeys,
    RobotTraffic,
    ZenohRobotLink,
    by_type,
    finish_timeout,
)
from como3r.errors import InputError
from como3r.io.output import atomic_output_dir, check_output_dir
from como3r.progress import ProgressCallback
from como3r.runtime.outputs import SIMULATED_NOTE, bandwidth, write_json
from como3r.runtime.pipeline import PriorSpec, RunSummary
from como3r.transport.zenoh_protocol import ZenohOptions, open_session

logger = logging.getLogger(__name__)


def plan_digest(config: Config, schedule: Schedule, team: int, prior: str) -> str:
    """What robots of one team must agree on, as a short digest: the configuration (with
    the schedule's windows in place of its file name), the team size and the prior."""
    document = config_to_dict(config)
    document["decentralized"]["protocol"]["schedule"] = schedule.to_json()
    document["team"], document["prior"] = team, prior
    text = json.dumps(document, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def run_robot(
    network: ZenohOptions,
    robot: int,
    team: int,
    path: Path,
    out: Path,
    config: Config,
    prior_spec: PriorSpec,
    schedule: Schedule | None = None,
    overwrite: bool = False,
    progress: ProgressCallback | None = None,
) -> RunSummary:
    """Run robot ``robot`` of a team of ``team`` on ``path``; write its output folder.

    Args:
        network: where to listen and whom to connect to.
        path: the robot's agent input (with ``odometry.txt``).
        out: its output folder (created atomically).
        config: the run's configuration (``config.decentralized`` is the mode's); the same
            on every robot.
        prior_spec: this robot's prior (its name must be the team's).
        schedule: the rendezvous schedule (the link filter); None: the one named by
            ``decentralized.protocol.schedule``, or always in range.
        overwrite: replace an existing non-empty output folder.
        progress: this robot's :class:`~como3r.progress.AgentProgress` events.

    Raises:
        InputError: a bad input, id or schedule, a network error, or a peer running
            another plan.
    """
    settings = config.decentralized
    check_config(settings)
    if not 0 <= robot < team:
        raise InputError(f"--id {robot}: a team of {team} robots has ids 0 to {team - 1}")
    check_output_dir(out, overwrite)
    if schedule is None:
        schedule = (
            read_schedule(settings.protocol.schedule) if settings.protocol.schedule else Schedule()
        )
    data = open_robot(path, config, settings)
    prior, codebook = build_prior(prior_spec, config, settings.place_method, {robot: str(path)})
    hello = RobotHello(
        robot=robot,
        end_s=float(data.odometry.timestamps[-1]),
        plan=plan_digest(config, schedule, team, prior_spec.name),
    )
    adapter = None if progress is None else RobotProgressAdapter(progress, {robot: data})
    started = time.perf_counter()
    session = open_session(network)
    try:
        link = ZenohRobotLink(
            session,
            RobotKeys(network.session, network.member),
            robot,
            team,
            hello,
            schedule.hears,
            int(settings.protocol.max_message_mb * 2**20),
            adapter,
            certified=network.member is not None,
            max_mbps=network.max_mbps,
        )
        worker = make_robot(robot, data, prior, codebook, config, settings, link, None)
        end_s = max(h.end_s for h in link.meet_team().values())
        mission = plan_rounds(schedule, range(team), end_s, settings.protocol.round_period_s)
        rounds = [plan for plan in mission if robot in plan.group]
        logger.info("robot %d: the team has met; %d round(s) ahead", robot, len(rounds))
        report = worker.run(mission)
        if adapter is not None:
            adapter(report)
        link.finish(
            {p for plan in rounds for p in plan.group},
            finish_timeout(settings.protocol.message_timeout_s),
        )
    finally:
        session.close()
    data.keyframes = reported_keyframes(data.odometry, report)
    summary = RunSummary(out=Path(out))
    if prior_spec.name == "simulated":
        summary.notes.append(SIMULATED_NOTE)
    summary.agents.append(
        {
            "agent": robot,
            "keyframes": len(data.keyframes),
            "loops": len(report.loops),
            "rejected": len(report.rejected),
            "frame": report.frame,
            "sent [B]": sum(by_type(link.traffic.sent).values()),
            "received [B]": sum(by_type(link.traffic.received).values()),
        }
    )
    with atomic_output_dir(out, overwrite=overwrite) as staging:
        _write(
            staging,
            robot,
            data,
            report,
            link.traffic,
            rounds,
            config,
            time.perf_counter() - started,
            prior_spec.name,
        )
    return summary


def _write(
    staging: Path,
    robot: int,
    data: RobotData,
    report: RobotReport,
    traffic: RobotTraffic,
    rounds: list[RoundPlan],
    config: Config,
    seconds: float,
    prior: str,
) -> None:
    (staging / "config.yaml").write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))
    write_trajectories(staging, {robot: data}, {robot: report.estimate})
    graph = graph_document(
        {robot: data}, {robot: report.estimate}, report.loops, report.rejected, [], {}
    )
    write_json(staging / "graph.json", {**graph, "frame": report.frame})
    metrics: dict[str, Any] = {
        "mode": "decentralized",
        "runtime": "robot",
        "transport": "zenoh",
        "robot": robot,
        "prior": {"name": prior},
        "seconds": seconds,
        "frame": report.frame,
        "rounds": [{"round": p.round, "time_s": p.time_s, "group": list(p.group)} for p in rounds],
        "bytes": traffic.to_json(),
        "bandwidth": [
            {
                "robot": robot,
                **bandwidth(by_type(traffic.sent), len(data.keyframes), image_shape(data, config)),
            }
        ],
        "robots": [robot_metrics(robot, report)],
        "two_stage": two_stage({robot: report}),
        "loops": loop_statistics(report.loops, report.rejected),
    }
    write_json(staging / "metrics.json", metrics)
