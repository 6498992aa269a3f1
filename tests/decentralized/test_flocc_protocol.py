"""Rendezvous, election, routing and robot dropouts (decentralized/protocol.py, robot.py,
messages.py), without a network: robots are threads (and once, processes) of this machine."""

from __future__ import annotations

import math

import numpy as np
import pytest

from como3r.decentralized.keyframes import open_robot
from como3r.decentralized.messages import (
    DRIVER,
    EncodingReply,
    EncodingRequest,
    PlaceDescriptors,
    PoseEstimate,
    PoseGraphShare,
    RobotReport,
    RobotTask,
)
from como3r.decentralized.pose_graph_problem import LoopClosure
from como3r.decentralized.protocol import build_prior, make_robot, run_protocol
from como3r.decentralized.robot import PeerLeft, RoundPlan
from como3r.decentralized.routing import Router
from como3r.decentralized.schedule import Schedule, elect, plan_rounds, read_schedule
from como3r.errors import ConfigError, InputError
from como3r.runtime.pipeline import PriorSpec
from como3r.transport import codec

MISSION_END_S = 2.0  # the scene's 60 frames at 30 Hz end at 1.97 s

# ----------------------------------------------------------------------------- schedule


def test_read_schedule(tmp_path):
    path = tmp_path / "rendezvous.csv"
    path.write_text("# robot,start,end,...\n0,0.0,1.0,2.0,3.0\n1, 0.5, 2.5\n\n2,5,6\n")
    schedule = read_schedule(path)
    assert schedule.windows == {0: [(0.0, 1.0), (2.0, 3.0)], 1: [(0.5, 2.5)], 2: [(5.0, 6.0)]}
    assert schedule.in_range(0, 1.0) and not schedule.in_range(0, 1.5)
    assert not schedule.in_range(3, 0.5)  # a robot without a line is never in range
    assert schedule.group(range(4), 2.2) == (0, 1)
    assert schedule.round_times(4.0) == [1.0, 2.5, 3.0, 4.0]
    assert schedule.round_times(4.0, period_s=1.5) == [1.0, 1.5, 2.5, 3.0, 4.0]
    assert Schedule().in_range(7, 1e9)


@pytest.mark.parametrize(
    "text, message",
    [
        ("0,1.0\n", "expected robot_id"),
        ("0,1.0,2.0,3.0\n", "expected robot_id"),
        ("x,1,2\n", "not a number"),
        ("0,2,1\n", "start_s <= end_s"),
        ("0,1,2\n0,3,4\n", "listed twice"),
    ],
)
def test_bad_schedules_name_the_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=rf"bad.csv:\d+: .*{message}"):
        read_schedule(path)


def test_rounds_need_two_robots_in_range_and_election_takes_the_smallest_id():
    schedule = Schedule({0: [(0.0, 1.0)], 1: [(0.5, 3.0)], 2: [(2.0, 3.0)]})
    rounds = plan_rounds(schedule, [0, 1, 2], end_s=3.0)
    assert [(p.round, p.time_s, p.group) for p in rounds] == [(0, 1.0, (0, 1)), (1, 3.0, (1, 2))]
    assert [elect(p.group) for p in rounds] == [0, 1]
    with pytest.raises(ValueError):
        elect([])


# ----------------------------------------------------------------------------- router


def test_router_delivers_only_in_range_and_counts_bytes():
    schedule = Schedule({0: [(0.0, 1.0)], 1: [(0.0, 2.0)]})
    delivered = []
    router = Router(
        schedule, lambda robot, data: delivered.append((robot, data)), 2**20, robots=[0, 1]
    )
    inside = codec.encode(
        EncodingRequest(sender=0, recipient=1, round=0, time_s=0.5, keyframes=[1, 2])
    )
    outside = codec.encode(
        EncodingRequest(sender=1, recipient=0, round=1, time_s=1.5, keyframes=[])
    )
    router.route(inside)
    router.route(outside)
    router.route(
        codec.encode(EncodingRequest(sender=0, recipient=7, round=0, time_s=0.5, keyframes=[]))
    )  # no such robot
    assert delivered == [(1, inside)]
    traffic = router.traffic.to_json([0, 1])
    assert traffic["per_robot"]["0"]["sent"] == {"EncodingRequest": len(inside)}
    assert traffic["per_robot"]["1"]["received_total"] == len(inside)
    assert traffic["per_robot"]["1"]["sent_total"] == 0
    assert traffic["dropped"] == {"EncodingRequest": 2}
    report = RobotReport(
        sender=1, recipient=DRIVER, estimate=np.zeros((0, 8)), frame=1, loops=[], rejected=[]
    )
    router.route(codec.encode(report))
    assert 1 in router.reports and 1 in router.gone
    router.route(
        codec.encode(EncodingRequest(sender=0, recipient=1, round=0, time_s=0.5, keyframes=[]))
    )
    assert len(delivered) == 1  # robot 1 is gone
    with pytest.raises(codec.MessageError):
        router.route(b"\x80\x04not msgpack")  # e.g. pickle bytes


def test_messages_round_trip_through_the_codec():
    loop = LoopClosure(0, 3, 1, 4, np.arange(8, dtype=np.float64), math.nan, 0.7, 0.2, 120)
    task = RobotTask(
        robot=1,
        agent_path="/x",
        config={"seed": 0},
        decentralized={},
        prior={"name": "simulated", "weights": None},
        rounds=[(0, 1.5, [0, 1])],
        leave=(0, "optimisation"),
    )
    descriptors = PlaceDescriptors(
        sender=0, recipient=1, round=2, time_s=1.0, first=3, descriptors=[np.ones(4, np.float32)]
    )
    for message in (loop, task, descriptors):
        decoded = codec.decode(codec.encode(message))
        assert type(decoded) is type(message)
    decoded = codec.decode(codec.encode(loop))
    assert math.isnan(decoded.odometry_scale) and np.array_equal(decoded.T_ab, loop.T_ab)
    assert codec.decode(codec.encode(task)).rounds == [(0, 1.5, [0, 1])]


def _share(**changes) -> PoseGraphShare:
    loop = LoopClosure(0, 3, 1, 4, np.arange(8, dtype=np.float64), math.nan, 0.7, 0.2, 120)
    fields = dict(
        sender=1,
        recipient=0,
        round=0,
        time_s=1.0,
        odometry=np.zeros((3, 8)),
        estimate=np.zeros((0, 8)),
        frame=1,
        loops=[loop],
    )
    return PoseGraphShare(**{**fields, **changes})


@pytest.mark.parametrize(
    "message, match",
    [
        (_share(odometry=np.full((3, 8), np.nan)), "odometry must be finite float64"),
        (_share(odometry=np.zeros((3, 7))), "odometry has shape"),
        (_share(estimate=np.zeros((4, 8))), "estimate must not outnumber odometry"),
        (
            _share(loops=[LoopClosure(0, 3, 1, 4, np.zeros(8), 1.0, 0.7, 2.0, 120)]),
            "probability in \\[0, 1\\]",
        ),
        (_share(time_s=math.inf), "time_s finite"),
        (
            PoseEstimate(
                sender=0,
                recipient=1,
                round=0,
                time_s=1.0,
                poses=np.zeros((2, 8), np.float32),
                frame=0,
            ),
            "poses must be finite float64",
        ),
        (EncodingRequest(sender=0, recipient=1, round=0, time_s=0.5, keyframes=[2, 2]), "distinct"),
        (
            EncodingReply(sender=0, recipient=1, round=0, time_s=0.5, keyframe=1, encoding=[1.0]),
            "encoding must be a prior's Encoding",
        ),
        (
            PlaceDescriptors(
                sender=0,
                recipient=1,
                round=0,
                time_s=0.5,
                first=0,
                descriptors=[np.ones(4, np.float32), np.ones(5, np.float32)],
            ),
            "share one shape kind and width",
        ),
    ],
)
def test_malformed_robot_messages_are_refused_on_decode(message, match):
    with pytest.raises(codec.MessageError, match=match):
        codec.decode(codec.encode(message))


# ----------------------------------------------------------------------------- robots


def _run(scene, main_config, settings_factory, schedule=None, leave=None, robots=3, **settings):
    return run_protocol(
        [str(p) for p in scene[:robots]],
        main_config,
        settings_factory(**settings),
        PriorSpec("simulated"),
        MISSION_END_S,
        schedule or Schedule(),
        leave=leave,
    )


def _sent(result, robot, kind=None):
    sent = result.traffic.sent.get(robot, {})
    return sum(sent.values()) if kind is None else sent.get(kind, 0)


def test_robots_out_of_range_exchange_nothing(scene, main_config, settings_factory):
    schedule = Schedule({0: [(0.0, 10.0)], 1: [(0.0, 10.0)]})  # robot 2 is never in range
    result = _run(scene, main_config, settings_factory, schedule, keyframe_distance_ratio=0.45)
    assert _sent(result, 2) == 0 and sum(result.traffic.received.get(2, {}).values()) == 0
    assert result.traffic.dropped == {}
    assert len(result.reports[2].estimate) == 0 and result.reports[2].frame == 2
    assert result.reports[2].stats["candidates"] == 0
    # Robots 0 and 1 met: robot 0 was elected, optimised and sent robot 1 its poses.
    assert [p.group for p in result.rounds] == [(0, 1)]
    assert _sent(result, 0, "PoseEstimate") > 0 and _sent(result, 1, "PoseEstimate") == 0
    assert _sent(result, 1, "PoseGraphShare") > 0 and _sent(result, 0, "PoseGraphShare") == 0
    assert result.reports[1].frame == 0 and len(result.reports[1].estimate) > 0
    assert _sent(result, 0, "EncodingReply") + _sent(result, 1, "EncodingReply") > 0


@pytest.mark.slow
def test_the_smallest_id_in_range_is_elected(scene, main_config, settings_factory):
    schedule = Schedule({1: [(0.0, 10.0)], 2: [(0.0, 10.0)]})  # robot 0 is never in range
    result = _run(scene, main_config, settings_factory, schedule, keyframe_distance_ratio=0.45)
    assert _sent(result, 1, "PoseEstimate") > 0
    assert _sent(result, 2, "PoseEstimate") == 0 and _sent(result, 0) == 0
    assert result.reports[2].frame == 1 and result.reports[1].frame == 1
    assert result.reports[0].frame == 0 and len(result.reports[0].estimate) == 0


@pytest.mark.slow
def test_frames_propagate_over_successive_rendezvous(scene, main_config, settings_factory):
    """Robots 0 and 1 meet first, then 1 and 2: robot 2 joins robot 0's frame through 1."""
    schedule = Schedule({0: [(0.0, 1.9)], 1: [(0.0, 1.9), (1.95, 3.0)], 2: [(1.95, 3.0)]})
    result = _run(scene, main_config, settings_factory, schedule, keyframe_distance_ratio=0.45)
    assert [(p.time_s, p.group) for p in result.rounds] == [(1.9, (0, 1)), (2.0, (1, 2))]
    assert [result.reports[r].frame for r in range(3)] == [0, 0, 0]
    assert _sent(result, 1, "PoseEstimate") > 0  # elected in the second round
    assert (
        result.traffic.sent[0]["PlaceDescriptors"] > 0
        and "PoseGraphShare" not in result.traffic.sent[0]
    )


@pytest.mark.slow
def test_a_leader_leaving_mid_optimisation_does_not_hang_the_others(
    scene, main_config, settings_factory
):
    result = _run(
        scene,
        main_config,
        settings_factory,
        leave={0: (0, "optimisation")},
        keyframe_distance_ratio=0.45,
        timeout_s=5.0,
    )
    assert set(result.reports) == {0, 1, 2}
    assert result.reports[0].left
    for robot in (1, 2):
        report = result.reports[robot]
        assert not report.left and report.error == ""
        assert report.stats["timeouts"] >= 1  # waited for the elected robot's answer
        assert len(report.estimate) == 0  # and kept its previous (odometry) estimate
    assert _sent(result, 0, "PoseEstimate") == 0
    assert _sent(result, 1, "PoseGraphShare") > 0


@pytest.mark.slow
def test_a_robot_leaving_before_registration_is_left_out(scene, main_config, settings_factory):
    result = _run(
        scene,
        main_config,
        settings_factory,
        leave={2: (0, "registration")},
        keyframe_distance_ratio=0.45,
        timeout_s=5.0,
    )
    assert result.reports[2].left and result.reports[2].stats["loops"] == 0
    assert result.reports[2].stats["decodes"] == 0
    # The others go on without it: robot 0 is elected and aligns robot 1.
    assert result.reports[1].frame == 0 and len(result.reports[1].estimate) > 0
    assert _sent(result, 2, "PoseGraphShare") == 0


class _PeerLeaves:
    """A link on which robot 1 is heard leaving as soon as robot 0 first sends it anything
    (as ``como3r robot``'s link reports a peer whose process ended)."""

    def __init__(self) -> None:
        self.sent: list = []
        self.inbox: list = []

    def send(self, message) -> None:
        if message.recipient == 1 and not self.sent:
            self.inbox.append(PeerLeft(1))
        self.sent.append(message)

    def receive(self, timeout: float):
        return self.inbox.pop(0) if self.inbox else None


def test_a_robot_stops_waiting_for_a_peer_reported_gone(scene, main_config, settings_factory):
    settings = settings_factory(keyframe_distance_ratio=0.45, timeout_s=600.0)
    prior, codebook = build_prior(
        PriorSpec("simulated"), main_config, settings.place_method, {0: str(scene[0])}
    )
    link = _PeerLeaves()
    data = open_robot(scene[0], main_config, settings)
    robot = make_robot(0, data, prior, codebook, main_config, settings, link, None)
    report = robot.run([RoundPlan(0, MISSION_END_S, (0, 1))])
    assert report.error == "" and report.stats["timeouts"] == 0  # no 600 s wait for robot 1
    assert report.stats["candidates"] == 0 and len(report.estimate) == 0
    assert [type(m).__name__ for m in link.sent] == ["PlaceDescriptors", "RobotProgress"]


def test_unknown_leave_phase_is_rejected(scene, main_config, settings_factory):
    with pytest.raises(ConfigError, match="phase"):
        _run(scene, main_config, settings_factory, leave={0: (0, "lunch")})


@pytest.mark.slow
def test_robot_processes_match_robot_threads(scene, main_config, settings_factory):
    threads = _run(scene, main_config, settings_factory, robots=2, keyframe_distance_ratio=0.45)
    processes = _run(
        scene, main_config, settings_factory, robots=2, keyframe_distance_ratio=0.45, processes=True
    )
    for robot in (0, 1):
        a, b = threads.reports[robot], processes.reports[robot]
        assert b.error == "" and a.frame == b.frame == 0
        assert [(l.keyframe_a, l.keyframe_b) for l in a.loops] == [
            (l.keyframe_a, l.keyframe_b) for l in b.loops
        ]
        np.testing.assert_allclose(a.estimate, b.estimate, atol=1e-4)
    assert threads.traffic.bytes_by_type == processes.traffic.bytes_by_type
    assert isinstance(processes.reports[1], RobotReport)
