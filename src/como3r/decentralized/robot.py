"""One robot of the decentralized mode: its data, its caches and its part of every round.

A round at mission time ``t`` with the group ``G`` of robots in range (F-Sec. III, F-Fig. 1):

1. send the place descriptors of keyframes not yet sent to each peer (F-Sec. III-A);
2. with the peers' descriptors, compute the loop candidates of each pair (the same on both
   sides, :func:`~como3r.decentralized.place_recognition.candidate_pairs`) and request the
   encodings of the peer's keyframes this robot registers;
3. serve the peers' requests and receive the encodings (F-Sec. III-B), register the
   candidates, weigh them by the correspondence ratio and drop those below the threshold
   (F-Eq. 1-2);
4. the elected robot -- the smallest id of the robots present (Swarm-SLAM, F-[9]) --
   collects everyone's :class:`~.messages.PoseGraphShare`, solves the pose graph of each
   connected group (F-Sec. III-C) and sends every robot its new poses.

Every wait is bounded by ``protocol.message_timeout_s`` (twice that for the elected robot's
answer, which may itself wait one timeout for a slow peer): a peer that does not answer (it
left, or crashed) is left out of the rest of the round, and a robot whose elected robot
disappears keeps its previous estimate. A link that sees a peer's process end (a
:class:`PeerLeft` from ``como3r robot``'s Zenoh link) ends those waits at once. Requests are
served whenever the robot waits, in any phase.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from como3r.config import Config
from como3r.config_decentralized import DecentralizedConfig
from como3r.data.preprocess import make_view
from como3r.decentralized.confidence import accept_loop, correspondence_ratio, loop_probability
from como3r.decentralized.consistency import (
    Graphs,
    LoopCheck,
    SharedGraph,
    loop_key,
    solve_shares,
)
from como3r.decentralized.keyframes import RobotData, select_keyframes
from como3r.decentralized.messages import (
    DRIVER,
    EncodingReply,
    EncodingRequest,
    PlaceDescriptors,
    PoseEstimate,
    PoseGraphShare,
    RobotProgress,
    RobotReport,
)
from como3r.decentralized.place_recognition import PlaceRecognizer, candidate_pairs
from como3r.decentralized.pose_graph_problem import LoopClosure, OdometryStart
from como3r.decentralized.registration import Registrar
from como3r.decentralized.routing import Link, PeerLeft
from como3r.decentralized.schedule import RoundPlan, chain_depths
from como3r.prior.base import Prior, View

logger = logging.getLogger(__name__)

#: Phases at which a robot can be made to leave (failure injection): before sending its
#: descriptors, before registering, and before the pose-graph step (the elected robot
#: leaves after collecting the shares, i.e. in the middle of the optimisation).
PHASES = ("descriptors", "registration", "optimisation")

#: The rounds (:mod:`.schedule`) and the radio link (:mod:`.routing`) a robot runs on stay
#: importable from here.
__all__ = ["PHASES", "Link", "PeerLeft", "Robot", "RoundPlan", "chain_depths"]


@dataclass(frozen=True)
class _Task:
    """A candidate this robot registers: its keyframe and the peer's."""

    keyframe: int
    peer: int
    other: int


class _Left(Exception):
    """Raised inside a round when the robot drops out (failure injection)."""


class Robot:
    """A robot with its odometry, keyframes, prior and radio link.

    Args:
        robot: robot id.
        data: its opened input (:func:`~.keyframes.open_robot`: odometry and declared
            start read once, by whoever opened it).
        prior: the prior (shared between threads in single-process mode).
        recognizer: place recognition.
        config: main configuration (image size, calibration use).
        settings: decentralized configuration.
        link: radio link to the router.
        leave: ``(round, phase)`` at which the robot drops out, for failure injection.
    """

    def __init__(
        self,
        robot: int,
        data: RobotData,
        prior: Prior,
        recognizer: PlaceRecognizer,
        config: Config,
        settings: DecentralizedConfig,
        link: Link,
        leave: tuple[int, str] | None = None,
    ) -> None:
        self.robot = robot
        self.agent = data.agent
        self.settings = settings
        self.link = link
        self.leave = leave
        self._long_side = config.input.long_side
        self._calib = data.agent.calib if config.calibrated else None
        self.recognizer = recognizer
        self.registrar = Registrar(prior, robot, self._view, settings.registration)
        odometry = data.odometry
        self._frame_times = odometry.timestamps
        #: Path length between keyframes [odometry units]: a fraction of the scene depth.
        self.keyframe_distance = settings.keyframe_distance_ratio * self.registrar.scene_depth(
            self._frame_view(int(odometry.frames[0]))
        )
        self.keyframes = select_keyframes(odometry, self.keyframe_distance)
        self.odometry = self.keyframes.T_OC.numpy()
        #: Its odometry's unconverged start, from the kind its input declares (None:
        #: undeclared); it travels with the odometry to whoever solves the graph.
        self.start = data.start
        self.estimate = np.zeros((0, 8))
        self.frame = robot
        self.loops: list[LoopClosure] = []
        self.rejected: list[LoopClosure] = []
        self.candidates = 0
        self.timeouts = 0
        # Safeguards of the solves this robot led (:mod:`~.consistency`).
        self.scale_alarms = 0
        self.loops_held_back = 0
        self._descriptors: list[np.ndarray] = []
        self._peer_descriptors: dict[int, dict[int, np.ndarray]] = defaultdict(dict)
        self._sent: dict[int, int] = defaultdict(int)
        self._handled: dict[int, set[tuple[int, int]]] = defaultdict(set)
        self._got_descriptors: set[tuple[int, int]] = set()
        self._got_requests: set[tuple[int, int]] = set()
        self._shares: dict[int, dict[int, PoseGraphShare]] = defaultdict(dict)
        self._estimates: dict[int, PoseEstimate] = {}
        self._gone: set[int] = set()
        # The pose graph of robots met through others (odometry, loops), relayed onwards.
        self._relayed: dict[int, np.ndarray] = {}
        self._relayed_starts: dict[int, OdometryStart] = {}
        self._relayed_loops: dict[tuple[int, int, int, int], LoopClosure] = {}

    # ------------------------------------------------------------------ running

    def run(self, rounds: list[RoundPlan]) -> RobotReport:
        """Take part in ``rounds`` (those whose group holds this robot; the others tell how
        long its peers may be busy before, :func:`chain_depths`), telling the driver how far
        the mission got after each, then report."""
        left = False
        depths = chain_depths(rounds, self.robot)
        for plan in rounds:
            if self.robot not in plan.group:
                continue
            try:
                self._round(plan, depths[plan.round])
            except _Left:
                logger.info("robot %d leaves during round %d", self.robot, plan.round)
                left = True
                break
            self.link.send(
                RobotProgress(
                    sender=self.robot,
                    recipient=DRIVER,
                    round=plan.round,
                    frames_done=int(np.searchsorted(self._frame_times, plan.time_s, side="right")),
                    keyframes=self.keyframes.up_to(plan.time_s),
                )
            )
        return self.report(left)

    def report(self, left: bool = False) -> RobotReport:
        """The robot's final state for the driver."""
        stats: dict[str, float] = {
            **self.registrar.stats.to_json(),
            "keyframes": len(self.keyframes),
            "keyframe_distance": self.keyframe_distance,
            "candidates": self.candidates,
            "loops": len(self.loops),
            "rejected": len(self.rejected),
            "timeouts": self.timeouts,
            "scale_alarms": self.scale_alarms,
            "loops_held_back": self.loops_held_back,
        }
        return RobotReport(
            sender=self.robot,
            recipient=DRIVER,
            estimate=self.estimate,
            frame=self.frame,
            loops=list(self.loops),
            rejected=list(self.rejected),
            stats=stats,
            left=left,
        )

    def _round(self, plan: RoundPlan, depth: int = 1) -> None:
        r, t = plan.round, plan.time_s
        peers = [p for p in plan.group if p != self.robot]
        count = self.keyframes.up_to(t)
        self._check_leave(r, "descriptors")
        self._send_descriptors(r, t, peers, count)
        # A peer first finishes the rounds before this one that it depends on: one timeout each.
        self._wait(
            lambda: all((r, p) in self._got_descriptors or p in self._gone for p in peers),
            timeouts=depth,
        )
        present = [p for p in peers if (r, p) in self._got_descriptors and p not in self._gone]
        leader = min([self.robot, *present])
        self._check_leave(r, "registration")
        tasks = self._candidates(present, count)
        self._request_encodings(r, t, tasks, present)
        self._wait(
            lambda: (
                all((r, p) in self._got_requests or p in self._gone for p in present)
                and all(
                    self.registrar.answered(k.peer, k.other) or k.peer in self._gone for k in tasks
                )
            )
        )
        self._register(tasks, count)
        # A peer whose request never came is gone for this round: nobody waits for it again.
        present = [
            p
            for p in present
            if ((r, p) in self._got_requests or p == leader) and p not in self._gone
        ]
        participants = sorted([self.robot, *present])
        if self.robot == leader:
            self._wait(lambda: all(p in self._shares[r] or p in self._gone for p in present))
            self._check_leave(r, "optimisation")
            self._solve_and_broadcast(r, t, present, self._share(r, t, leader, participants, count))
        else:
            self._check_leave(r, "optimisation")
            self.link.send(self._share(r, t, leader, participants, count))
            # The elected robot may itself wait up to one timeout for a slower peer's share.
            self._wait(lambda: r in self._estimates or leader in self._gone, timeouts=2)
            if r in self._estimates:
                self._apply(self._estimates[r])

    def _check_leave(self, r: int, phase: str) -> None:
        if self.leave is not None and self.leave == (r, phase):
            raise _Left

    # ------------------------------------------------------------------ messages

    def _wait(self, done: Callable[[], bool], timeouts: int = 1) -> bool:
        """Handle incoming messages until ``done()`` or ``timeouts`` message timeouts have
        passed; whether it is done."""
        deadline = time.monotonic() + timeouts * self.settings.protocol.message_timeout_s
        while not done():
            remaining = deadline - time.monotonic()
            message = self.link.receive(remaining) if remaining > 0 else None
            if message is None:
                self.timeouts += 1
                logger.warning("robot %d: timed out waiting for its peers", self.robot)
                return False
            self._handle(message)
        return True

    def _handle(self, message: Any) -> None:
        if isinstance(message, PeerLeft):
            logger.warning("robot %d: robot %d is gone", self.robot, message.robot)
            self._gone.add(message.robot)
            return
        sender = message.sender
        if isinstance(message, PlaceDescriptors):
            for k, descriptor in enumerate(message.descriptors, start=message.first):
                self._peer_descriptors[sender][k] = descriptor
            self._got_descriptors.add((message.round, sender))
        elif isinstance(message, EncodingRequest):
            for keyframe in message.keyframes:
                if 0 <= keyframe < len(self.keyframes):
                    self.link.send(
                        EncodingReply(
                            sender=self.robot,
                            recipient=sender,
                            round=message.round,
                            time_s=message.time_s,
                            keyframe=keyframe,
                            **self.registrar.reply_for_peer(keyframe),
                        )
                    )
            self._got_requests.add((message.round, sender))
        elif isinstance(message, EncodingReply):
            self.registrar.add_foreign(sender, message.keyframe, message.encoding, message.colours)
        elif isinstance(message, PoseGraphShare):
            self._shares[message.round][sender] = message
        elif isinstance(message, PoseEstimate):
            self._estimates[message.round] = message

    def _view(self, keyframe: int) -> View:
        return self._frame_view(int(self.keyframes.frames[keyframe]))

    def _frame_view(self, frame: int) -> View:
        return make_view(self.agent.load_frame(frame), self.robot, self._long_side, self._calib)

    def _send_descriptors(self, r: int, t: float, peers: list[int], count: int) -> None:
        for k in range(len(self._descriptors), count):
            encoding = self.registrar.own_encoding(k)
            self._descriptors.append(
                self.recognizer.describe(*self.registrar.prior.retrieval_features(encoding))
            )
        for peer in peers:
            first = self._sent[peer]
            self.link.send(
                PlaceDescriptors(
                    sender=self.robot,
                    recipient=peer,
                    round=r,
                    time_s=t,
                    first=first,
                    descriptors=self._descriptors[first:count],
                )
            )
            self._sent[peer] = max(first, count)

    def _known_peer_descriptors(self, peer: int) -> list[np.ndarray]:
        """The peer's descriptors of keyframes 0, 1, ... without a gap."""
        known = self._peer_descriptors[peer]
        out = []
        while len(out) in known:
            out.append(known[len(out)])
        return out

    def _candidates(self, present: list[int], count: int) -> list[_Task]:
        """The candidates of every pair with a present peer that this robot registers."""
        tasks = []
        mine = self._descriptors[:count]
        for peer in present:
            theirs = self._known_peer_descriptors(peer)
            lower = self.robot < peer
            rows, cols = (mine, theirs) if lower else (theirs, mine)
            similarity = self.recognizer.similarity(rows, cols)
            found = candidate_pairs(similarity, self.settings.place_threshold, self._handled[peer])
            self._handled[peer].update((c.row, c.col) for c in found)
            for c in found:
                if c.by_row == lower:
                    keyframe, other = (c.row, c.col) if lower else (c.col, c.row)
                    tasks.append(_Task(keyframe, peer, other))
        self.candidates += len(tasks)
        return tasks

    def _request_encodings(self, r: int, t: float, tasks: list[_Task], present: list[int]) -> None:
        for peer in present:
            needed = sorted(
                {
                    k.other
                    for k in tasks
                    if k.peer == peer and not self.registrar.has_foreign(peer, k.other)
                }
            )
            self.link.send(
                EncodingRequest(
                    sender=self.robot, recipient=peer, round=r, time_s=t, keyframes=needed
                )
            )

    # ------------------------------------------------------------------ registration

    def _register(self, tasks: list[_Task], count: int) -> None:
        """Register each candidate whose encoding arrived; keep it if it passes F-Eq. 1."""
        for task in tasks:
            if not self.registrar.has_foreign(task.peer, task.other):
                continue
            registration = self.registrar.register(task.keyframe, task.peer, task.other)
            neighbour, consecutive = self.registrar.consecutive(task.keyframe, count)
            ratio = correspondence_ratio(registration.correspondences, consecutive.correspondences)
            loop = LoopClosure(
                robot_a=self.robot,
                keyframe_a=task.keyframe,
                robot_b=task.peer,
                keyframe_b=task.other,
                T_ab=(
                    np.zeros(8) if registration.T_ij is None else registration.T_ij.double().numpy()
                ),
                odometry_scale=self._odometry_scale(task.keyframe, neighbour, consecutive.T_ij),
                ratio=ratio,
                probability=loop_probability(ratio, self.settings.confidence_k),
                correspondences=registration.correspondences,
            )
            if registration.T_ij is not None and accept_loop(ratio, self.settings.ratio_threshold):
                self.loops.append(loop)
            else:
                self.rejected.append(loop)

    def _odometry_scale(self, keyframe: int, neighbour: int, T_prior: Any) -> float:
        """F-Eq. 6: odometry distance over prior distance of the odometry pair (NaN if none)."""
        if T_prior is None:
            return float("nan")
        prior_distance = float(T_prior[:3].norm())
        odometry_distance = float(
            np.linalg.norm(self.odometry[keyframe, :3] - self.odometry[neighbour, :3])
        )
        if prior_distance <= 0 or odometry_distance <= 0:
            return float("nan")
        return odometry_distance / prior_distance

    # ------------------------------------------------------------------ pose graph

    def _share(
        self, r: int, t: float, leader: int, participants: list[int], count: int
    ) -> PoseGraphShare:
        """Its odometry, estimate and loops, with the graph of the robots it relays (those
        it learnt of in earlier rounds and that are not in this one)."""
        relayed = {q: o for q, o in sorted(self._relayed.items()) if q not in participants}
        known = set(participants) | set(relayed)
        loops = {
            loop_key(loop): loop
            for loop in [*self.loops, *self._relayed_loops.values()]
            if loop.robot_a in known and loop.robot_b in known
        }
        return PoseGraphShare(
            sender=self.robot,
            recipient=leader,
            round=r,
            time_s=t,
            odometry=self.odometry[:count],
            estimate=self.estimate[:count],
            frame=self.frame,
            loops=list(loops.values()),
            relayed=relayed,
            start=self.start,
            relayed_starts={q: s for q, s in self._relayed_starts.items() if q in relayed},
        )

    def _solve_and_broadcast(
        self, r: int, t: float, present: list[int], own: PoseGraphShare
    ) -> None:
        """The elected robot's step: solve every connected group, answer every robot."""
        shares = {
            self.robot: own,
            **{p: self._shares[r][p] for p in present if p in self._shares[r]},
        }
        checks: list[LoopCheck] = []
        graphs: Graphs = {}
        updates = solve_shares(shares, self.settings, checks=checks, graphs=graphs)
        self.scale_alarms += sum(check.alarm for check in checks)
        # The last solve's count: every solve sees all loops found so far.
        self.loops_held_back = sum(check.loops - int(check.consistent.sum()) for check in checks)
        # Every robot present gets an answer, empty when it has no update, so none waits.
        for robot in sorted([self.robot, *present]):
            poses, frame = updates.get(robot, (np.zeros((0, 8)), -1))
            graph = graphs.get(robot, SharedGraph({}, []))
            estimate = PoseEstimate(
                sender=self.robot,
                recipient=robot,
                round=r,
                time_s=t,
                poses=poses,
                frame=frame,
                relayed={q: o for q, o in graph.odometry.items() if q != robot},
                loops=graph.loops,
                relayed_starts={q: s for q, s in graph.starts.items() if q != robot},
            )
            if robot == self.robot:
                self._apply(estimate)
            else:
                self.link.send(estimate)

    def _apply(self, estimate: PoseEstimate) -> None:
        if len(estimate.poses):
            self.estimate = np.asarray(estimate.poses, dtype=np.float64)
            self.frame = estimate.frame
        for robot, odometry in estimate.relayed.items():
            if robot != self.robot and len(odometry) > len(self._relayed.get(robot, ())):
                self._relayed[robot] = odometry
        for robot, start in estimate.relayed_starts.items():
            if robot != self.robot:
                self._relayed_starts[robot] = start
        for loop in estimate.loops:
            self._relayed_loops.setdefault(loop_key(loop), loop)
