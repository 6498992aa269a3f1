"""Rendezvous, election and message routing of the decentralized mode.

Robots run as separate processes (or, for tests, as threads of one process) and exchange
only the typed messages of :mod:`como3r.decentralized.messages`. Radio range is simulated
by a rendezvous schedule: a file with one line per robot,

    robot_id,start_s,end_s[,start_s,end_s...]

listing the mission-time windows [s] in which the robot is in communication range (of the
rendezvous point; two robots can talk when both are in range). A robot without a line is
never in range; without a schedule every robot always is. Exchange rounds happen when a
window closes, every ``round_period_s`` while robots are in range, and at the end of the
mission; the group of a round is every robot in range at its time. The robot with the
smallest id in a group is elected to optimise (Swarm-SLAM, F-[9]; :func:`elect`).

All traffic goes through a :class:`Router` in the driver, which delivers a message only
when sender and recipient are both in range at the message's round time, and counts the
bytes of every delivered message per robot and per message type. The robots' messages to
the driver (progress after each round, the final report) are not radio traffic: they are
always delivered and not counted.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import queue
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.config import Config, config_from_dict, config_to_dict
from como3r.data.agent import open_agent
from como3r.decentralized.config import DecentralizedConfig
from como3r.decentralized.messages import (
    DRIVER,
    ROBOT_MESSAGES,
    RobotProgress,
    RobotReport,
    RobotTask,
)
from como3r.decentralized.place_recognition import PlaceRecognizer
from como3r.decentralized.robot import PHASES, Robot, RoundPlan
from como3r.errors import Como3rError, ConfigError, InputError
from como3r.prior.base import Prior
from como3r.transport import codec

logger = logging.getLogger(__name__)

MissionProgress = Callable[[RobotProgress | RobotReport], None]
"""What the driver calls with the robots' progress messages and final reports."""


# ------------------------------------------------------------------------------ schedule


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


# ------------------------------------------------------------------------------ router


@dataclass
class TrafficCounter:
    """Bytes and messages delivered, per robot and message type; messages dropped (out of
    range, or to a robot that is gone) per type."""

    sent: dict[int, Counter] = field(default_factory=dict)
    received: dict[int, Counter] = field(default_factory=dict)
    messages: Counter = field(default_factory=Counter)
    bytes_by_type: Counter = field(default_factory=Counter)
    dropped: Counter = field(default_factory=Counter)

    def count(self, sender: int, recipient: int, kind: str, size: int) -> None:
        self.sent.setdefault(sender, Counter())[kind] += size
        self.received.setdefault(recipient, Counter())[kind] += size
        self.messages[kind] += 1
        self.bytes_by_type[kind] += size

    def to_json(self, robots: Sequence[int]) -> dict[str, Any]:
        per_robot = {
            str(r): {
                "sent": dict(self.sent.get(r, {})),
                "received": dict(self.received.get(r, {})),
                "sent_total": sum(self.sent.get(r, Counter()).values()),
                "received_total": sum(self.received.get(r, Counter()).values()),
            }
            for r in robots
        }
        return {
            "per_robot": per_robot,
            "bytes_by_type": dict(self.bytes_by_type),
            "messages_by_type": dict(self.messages),
            "bytes_per_message": {k: v / self.messages[k] for k, v in self.bytes_by_type.items()},
            "total_bytes": sum(self.bytes_by_type.values()),
            "dropped": dict(self.dropped),
        }


class Router:
    """Delivers robot messages that the schedule allows and counts them.

    Args:
        schedule: rendezvous schedule.
        deliver: ``deliver(recipient, data)`` hands raw bytes to a robot.
        max_bytes: size cap of a message.
        robots: the robot ids; messages to any other id are dropped.
        progress: called with every :class:`RobotProgress` and :class:`RobotReport`, one at
            a time (robot threads route concurrently).
    """

    def __init__(
        self,
        schedule: Schedule,
        deliver: Any,
        max_bytes: int,
        robots: Sequence[int],
        progress: MissionProgress | None = None,
    ) -> None:
        self.robots = set(robots)
        self.schedule = schedule
        self.deliver = deliver
        self.max_bytes = max_bytes
        self.progress = progress
        self.traffic = TrafficCounter()
        self.reports: dict[int, RobotReport] = {}
        self.gone: set[int] = set()
        self._lock = threading.Lock()

    def route(self, data: bytes) -> None:
        """Validate, check range, count and forward one encoded message."""
        message = codec.decode(
            data, max_bytes=self.max_bytes, expected=(*ROBOT_MESSAGES, RobotProgress, RobotReport)
        )
        with self._lock:
            if isinstance(message, RobotReport):
                self.reports[message.sender] = message
                self.gone.add(message.sender)
            if isinstance(message, (RobotProgress, RobotReport)):
                if self.progress is not None and message.sender in self.robots:
                    self.progress(message)
                return
            kind = type(message).__name__
            sender, recipient, time_s = message.sender, message.recipient, message.time_s
            if (
                recipient not in self.robots
                or recipient in self.gone
                or not self.schedule.hears(recipient, sender, time_s)
            ):
                self.traffic.dropped[kind] += 1
                return
            self.traffic.count(sender, recipient, kind, len(data))
        self.deliver(recipient, data)


# ------------------------------------------------------------------------------ links


class ThreadLink:
    """A robot's link in single-process mode: straight into the router, a queue back."""

    def __init__(self, router: Router, max_bytes: int) -> None:
        self.router = router
        self.inbox: queue.Queue[bytes] = queue.Queue()
        self.max_bytes = max_bytes

    def send(self, message: Any) -> None:
        self.router.route(codec.encode(message, max_bytes=self.max_bytes))

    def receive(self, timeout: float) -> Any | None:
        try:
            data = self.inbox.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return None
        return codec.decode(data, max_bytes=self.max_bytes, expected=ROBOT_MESSAGES)


class PipeLink:
    """A robot process's link: raw bytes over two one-way pipes, sends from a thread so a
    full pipe never blocks computation."""

    def __init__(self, inbox: Connection, outbox: Connection, max_bytes: int) -> None:
        self.inbox = inbox
        self.outbox = outbox
        self.max_bytes = max_bytes
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._sender = threading.Thread(target=self._send_loop, daemon=True)
        self._sender.start()

    def send(self, message: Any) -> None:
        self._queue.put(codec.encode(message, max_bytes=self.max_bytes))

    def receive(self, timeout: float) -> Any | None:
        if not self.inbox.poll(max(timeout, 0.0)):
            return None
        try:
            data = self.inbox.recv_bytes(self.max_bytes)
        except (EOFError, OSError):
            return None
        return codec.decode(data, max_bytes=self.max_bytes, expected=(*ROBOT_MESSAGES, RobotTask))

    def close(self, timeout: float = 60.0) -> None:
        """Flush queued messages, then close both pipes."""
        self._queue.put(None)
        self._sender.join(timeout)
        self.inbox.close()
        self.outbox.close()

    def _send_loop(self) -> None:
        while (data := self._queue.get()) is not None:
            try:
                self.outbox.send_bytes(data)
            except OSError:
                return


# ------------------------------------------------------------------------------ robots


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
    agent_path: str,
    prior: Prior,
    codebook: np.ndarray | None,
    config: Config,
    settings: DecentralizedConfig,
    link: Any,
    leave: tuple[int, str] | None,
) -> Robot:
    """Robot ``robot`` on its input, with its place recognizer, over ``link``."""
    recognizer = PlaceRecognizer(settings.place_method, codebook, config.retrieval)
    return Robot(
        robot,
        open_agent(
            agent_path,
            fps=config.input.frame_rate_hz,
            format=config.input.format,
            topic=config.input.topic,
        ),
        prior,
        recognizer,
        config,
        settings,
        link,
        leave,
    )


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
        worker = make_robot(
            robot, task.agent_path, prior, codebook, config, settings, link, task.leave
        )
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
        progress: called with each robot's :class:`RobotProgress` after every round it took
            part in and with its :class:`RobotReport` (also the one of a robot process that
            died), one at a time.

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
            workers.append(
                make_robot(r, str(path), prior, codebook, config, settings, links[r], leave.get(r))
            )
        except Exception as exc:  # the robot's thread reports it like any other failure
            workers.append(exc)
    codec.resolve_all()
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
            rounds=[(p.round, p.time_s, list(p.group)) for p in rounds if robot in p.group],
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
