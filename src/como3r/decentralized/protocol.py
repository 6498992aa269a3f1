"""Rendezvous, election and message routing of the decentralized mode: a mission run on one
machine (:func:`run_protocol`).

Robots run as separate processes (or, for tests, as threads of one process) and exchange
only the typed messages of :mod:`como3r.decentralized.messages`. Radio range is simulated
by a rendezvous schedule (:mod:`.schedule`: who is in range when, the exchange rounds, the
election of the robot that optimises a round's group).

All traffic goes through a :class:`~.routing.Router` in the driver, which delivers a message
only when sender and recipient are both in range at the message's round time, and counts the
bytes of every delivered message per robot and per message type (:mod:`.routing`). The
robots' messages to the driver (progress after each round, the final report) are not radio
traffic: they are always delivered and not counted.
"""

from __future__ import annotations

import atexit
import gc
import logging
import multiprocessing
import queue
import threading
import time
import traceback
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.config import Config, config_from_dict, config_to_dict
from como3r.config_decentralized import DecentralizedConfig
from como3r.data.agent import open_agent
from como3r.decentralized.keyframes import RobotData, open_robot
from como3r.decentralized.messages import (
    DRIVER,
    RobotReport,
    RobotTask,
)
from como3r.decentralized.place_recognition import PlaceRecognizer
from como3r.decentralized.robot import PHASES, Robot, RoundPlan
from como3r.decentralized.routing import (
    MissionProgress,
    PipeLink,
    Router,
    ThreadLink,
    TrafficCounter,
)
from como3r.decentralized.schedule import Schedule, plan_rounds, read_schedule
from como3r.errors import Como3rError, ConfigError, InputError
from como3r.prior.base import Prior
from como3r.transport import codec, codec_registry

logger = logging.getLogger(__name__)

"""What the driver calls with the robots' progress messages and final reports."""


@dataclass(frozen=True)
class ProtocolResult:
    """What the robots ended with.

    Attributes:
        reports: robot -> its final report.
        traffic: bytes and messages per robot and type.
        rounds: the rounds that were planned.
        seconds: wall time of the whole exchange.
    """

    reports: dict[int, RobotReport]
    traffic: TrafficCounter
    rounds: list[RoundPlan]
    seconds: float


def build_prior(
    spec: Any, config: Config, place_method: str, agent_paths: dict[int, str]
) -> tuple[Prior, np.ndarray | None]:
    """The prior of a :class:`~como3r.runtime.pipeline.PriorSpec` for the robots
    ``agent_paths`` (robot id -> agent input, where the simulated prior reads its ground
    truth) and, for ASMK place recognition, its retrieval codebook."""
    from como3r.runtime.pipeline import build_prior as build_pipeline_prior

    agents = {
        r: open_agent(
            path,
            fps=config.input.frame_rate_hz,
            format=config.input.format,
            topic=config.input.topic,
        )
        for r, path in agent_paths.items()
    }
    prior, codebook = build_pipeline_prior(spec, config, agents)
    if spec.name == "simulated":
        return prior, (codebook if place_method == "asmk" else None)
    if codebook is None:
        raise InputError(
            "the decentralized mode with --prior mast3r needs --retrieval-weights "
            "for place recognition"
        )
    return prior, codebook


def make_robot(
    robot: int,
    data: RobotData,
    prior: Prior,
    codebook: np.ndarray | None,
    config: Config,
    settings: DecentralizedConfig,
    link: Any,
    leave: tuple[int, str] | None,
) -> Robot:
    """Robot ``robot`` on its opened input (:func:`~.keyframes.open_robot`), with its place
    recognizer, over ``link``."""
    recognizer = PlaceRecognizer(settings.place_method, codebook, config.retrieval)
    return Robot(robot, data, prior, recognizer, config, settings, link, leave)


def _run_thread(
    robot: int, worker: Robot | Exception, link: ThreadLink, rounds: list[RoundPlan]
) -> None:
    try:
        if isinstance(worker, Exception):
            raise worker
        link.router.route(codec.encode(worker.run(rounds), max_bytes=link.max_bytes))
    except Exception as exc:  # reported to the driver, which decides what to do
        logger.error("robot %d failed: %s", robot, exc)
        link.router.route(codec.encode(_failure(robot, exc), max_bytes=link.max_bytes))


def _failure(robot: int, exc: Exception) -> RobotReport:
    details = "" if isinstance(exc, Como3rError) else "\n" + traceback.format_exc()
    return RobotReport(
        sender=robot,
        recipient=DRIVER,
        estimate=np.zeros((0, 8)),
        frame=robot,
        loops=[],
        rejected=[],
        error=f"{type(exc).__name__}: {exc}{details}",
    )


def _robot_process_main(robot: int, inbox: Connection, outbox: Connection) -> None:
    """Entry point of a robot process: its first message is its :class:`RobotTask`."""
    atexit.register(gc.freeze)  # a quick exit, as the command line's (como3r.cli.main)
    link = PipeLink(inbox, outbox, codec.DEFAULT_MAX_BYTES)
    try:
        task = link.receive(timeout=600.0)
        if not isinstance(task, RobotTask) or task.robot != robot:
            raise codec.MessageError(f"robot {robot}: the first message must be its RobotTask")
        torch.set_num_threads(1)
        config = config_from_dict(Config, task.config)
        settings = config_from_dict(DecentralizedConfig, task.decentralized)
        link.max_bytes = int(settings.protocol.max_message_mb * 2**20)
        from como3r.runtime.pipeline import PriorSpec

        spec = PriorSpec(
            **{
                k: (
                    Path(v)
                    if k in ("weights", "retrieval_weights", "codebook") and v is not None
                    else v
                )
                for k, v in task.prior.items()
            }
        )
        prior, codebook = build_prior(spec, config, settings.place_method, {robot: task.agent_path})
        rounds = [RoundPlan(r, t, tuple(g)) for r, t, g in task.rounds]
        # The driver read the same files in its process; nothing but messages crosses.
        data = open_robot(task.agent_path, config, settings, log=False)
        worker = make_robot(robot, data, prior, codebook, config, settings, link, task.leave)
        link.send(worker.run(rounds))
    except Exception as exc:
        link.send(_failure(robot, exc))
    finally:
        link.close()


@dataclass
class _ProcessSlot:
    process: Any
    inbox: Connection
    outbox: Connection
    queue: queue.Queue = field(default_factory=queue.Queue)
    sender: threading.Thread | None = None


def _prior_fields(spec: Any) -> dict[str, Any]:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(spec).items()}


def run_protocol(
    agent_paths: Sequence[str | Path],
    config: Config,
    settings: DecentralizedConfig,
    prior_spec: Any,
    end_s: float,
    schedule: Schedule | None = None,
    prior: Prior | None = None,
    leave: dict[int, tuple[int, str]] | None = None,
    progress: MissionProgress | None = None,
    opened: Sequence[RobotData] | None = None,
) -> ProtocolResult:
    """Run every robot over the mission and collect their reports.

    Args:
        agent_paths: one agent input per robot, robot ids in this order.
        config: main configuration.
        settings: decentralized configuration (``protocol.processes`` picks processes or
            threads).
        prior_spec: the :class:`~como3r.runtime.pipeline.PriorSpec`.
        end_s: mission end [s].
        schedule: rendezvous schedule; None reads ``protocol.schedule`` (empty: always in
            range).
        prior: a prior to share between robot threads (single-process mode only).
        leave: robot -> ``(round, phase)`` at which it drops out (failure injection; phases
            in :data:`~como3r.decentralized.robot.PHASES`).
        progress: called with each robot's :class:`~.messages.RobotProgress` after every
            round it took part in and with its :class:`RobotReport` (also the one of a robot
            process that died), one at a time.
        opened: the robots' inputs as the driver opened them (:func:`~.keyframes.open_robot`,
            in ``agent_paths``' order), which robot threads take as they are instead of
            reading the files again; None: each robot opens its own (as robot processes
            always do).

    Raises:
        ConfigError: an unknown phase in ``leave``.
    """
    if schedule is None:
        schedule = (
            read_schedule(settings.protocol.schedule) if settings.protocol.schedule else Schedule()
        )
    leave = leave or {}
    for robot, (_, phase) in leave.items():
        if phase not in PHASES:
            raise ConfigError(f"leave: robot {robot} phase {phase!r} is not one of {PHASES}")
    robots = list(range(len(agent_paths)))
    rounds = plan_rounds(schedule, robots, end_s, settings.protocol.round_period_s)
    max_bytes = int(settings.protocol.max_message_mb * 2**20)
    start = time.perf_counter()
    if settings.protocol.processes:
        router = _run_processes(
            agent_paths, config, settings, prior_spec, schedule, rounds, leave, max_bytes, progress
        )
    else:
        router = _run_threads(
            agent_paths,
            config,
            settings,
            prior_spec,
            schedule,
            rounds,
            leave,
            max_bytes,
            prior,
            progress,
            opened,
        )
    return ProtocolResult(router.reports, router.traffic, rounds, time.perf_counter() - start)


def _run_threads(
    agent_paths: Sequence[str | Path],
    config: Config,
    settings: DecentralizedConfig,
    prior_spec: Any,
    schedule: Schedule,
    rounds: list[RoundPlan],
    leave: dict[int, tuple[int, str]],
    max_bytes: int,
    prior: Prior | None,
    progress: MissionProgress | None,
    opened: Sequence[RobotData] | None,
) -> Router:
    codebook = None
    if prior is None or settings.place_method == "asmk":
        prior, codebook = build_prior(
            prior_spec,
            config,
            settings.place_method,
            {r: str(path) for r, path in enumerate(agent_paths)},
        )
    links: dict[int, ThreadLink] = {}
    router = Router(
        schedule,
        lambda robot, data: links[robot].inbox.put(data),
        max_bytes,
        range(len(agent_paths)),
        progress,
    )
    links.update({r: ThreadLink(router, max_bytes) for r in range(len(agent_paths))})
    # Robots are built (files opened, classes imported) and message types resolved here,
    # one at a time: CPython 3.11's AST constructor fails when threads compile concurrently
    # ("AST constructor recursion depth mismatch").
    workers: list[Robot | Exception] = []
    for r, path in enumerate(agent_paths):
        try:
            data = opened[r] if opened else open_robot(path, config, settings, log=False)
            workers.append(
                make_robot(r, data, prior, codebook, config, settings, links[r], leave.get(r))
            )
        except Exception as exc:  # the robot's thread reports it like any other failure
            workers.append(exc)
    codec_registry.resolve_all()
    threads = [
        threading.Thread(
            target=_run_thread,
            name=f"como3r-robot-{r}",
            daemon=True,
            args=(r, workers[r], links[r], rounds),
        )
        for r in range(len(agent_paths))
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return router


def _run_processes(
    agent_paths: Sequence[str | Path],
    config: Config,
    settings: DecentralizedConfig,
    prior_spec: Any,
    schedule: Schedule,
    rounds: list[RoundPlan],
    leave: dict[int, tuple[int, str]],
    max_bytes: int,
    progress: MissionProgress | None,
) -> Router:
    context = multiprocessing.get_context("spawn")
    slots: dict[int, _ProcessSlot] = {}

    def deliver(robot: int, data: bytes) -> None:
        slots[robot].queue.put(data)

    router = Router(schedule, deliver, max_bytes, range(len(agent_paths)), progress)
    for robot, path in enumerate(agent_paths):
        to_robot_r, to_robot_w = context.Pipe(duplex=False)
        from_robot_r, from_robot_w = context.Pipe(duplex=False)
        process = context.Process(
            target=_robot_process_main,
            name=f"como3r-robot-{robot}",
            args=(robot, to_robot_r, from_robot_w),
            daemon=True,
        )
        from como3r.transport.child_signals import children_ignore_sigint

        with children_ignore_sigint():  # Ctrl-C is the driver's to handle
            process.start()
        to_robot_r.close()
        from_robot_w.close()
        slot = _ProcessSlot(process, from_robot_r, to_robot_w)
        slot.sender = threading.Thread(target=_pipe_sender, args=(slot,), daemon=True)
        slot.sender.start()
        slots[robot] = slot
        task = RobotTask(
            robot=robot,
            agent_path=str(path),
            config=config_to_dict(config),
            decentralized=asdict(settings),
            prior=_prior_fields(prior_spec),
            rounds=[(p.round, p.time_s, list(p.group)) for p in rounds],
            leave=leave.get(robot),
        )
        slot.queue.put(codec.encode(task, max_bytes=max_bytes))
    open_inboxes = {slot.inbox: robot for robot, slot in slots.items()}
    while open_inboxes:
        for conn in wait(list(open_inboxes)):
            robot = open_inboxes[conn]
            try:
                data = conn.recv_bytes(max_bytes)
            except (EOFError, OSError):
                del open_inboxes[conn]
                router.gone.add(robot)
                continue
            try:
                router.route(data)
            except codec.MessageError as exc:
                logger.error("robot %d sent an invalid message: %s", robot, exc)
    for robot, slot in slots.items():
        slot.queue.put(None)
        slot.process.join(timeout=settings.protocol.message_timeout_s)
        if slot.process.is_alive():
            slot.process.terminate()
        if robot not in router.reports:
            router.reports[robot] = _failure(robot, RuntimeError("the robot process died"))
            if progress is not None:
                progress(router.reports[robot])
    return router


def _pipe_sender(slot: _ProcessSlot) -> None:
    """Feed one robot's inbox pipe from its queue (never blocks the router)."""
    while (data := slot.queue.get()) is not None:
        try:
            slot.outbox.send_bytes(data)
        except OSError:
            return
    slot.outbox.close()
