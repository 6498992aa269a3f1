"""A robot's Zenoh link (decentralized/zenoh_robot.py) on loopback TCP, in this process: the team
handshake, the link filter at the receiver, invalid messages dropped."""

from __future__ import annotations

import socket
import threading
import uuid

import numpy as np
import pytest

from como3r.decentralized.messages import DRIVER, EncodingRequest, RobotHello, RobotProgress
from como3r.decentralized.robot import PeerLeft
from como3r.decentralized.schedule import Schedule
from como3r.decentralized.zenoh_robot import RobotKeys, ZenohRobotLink
from como3r.errors import InputError
from como3r.transport import codec
from como3r.transport.zenoh_protocol import ZenohOptions, open_session

zenoh = pytest.importorskip("zenoh")

#: robot 0 is in range until 1 s, robot 1 until 2 s
SCHEDULE = Schedule({0: [(0.0, 1.0)], 1: [(0.0, 2.0)]})
MAX_BYTES = 2**16


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def network():
    """Two sessions of one Zenoh network (the second connects to the first) and its keys."""
    endpoint, name = f"tcp/127.0.0.1:{_free_port()}", f"t{uuid.uuid4().hex[:12]}"
    sessions = [
        open_session(ZenohOptions(listen=(endpoint,), session=name)),
        open_session(ZenohOptions(connect=(endpoint,), session=name)),
    ]
    yield sessions, RobotKeys(name)
    for session in sessions:
        session.close()


def _link(session, keys, robot, plan="plan", progress=None) -> ZenohRobotLink:
    hello = RobotHello(robot=robot, end_s=2.0 + robot, plan=plan)
    return ZenohRobotLink(session, keys, robot, 2, hello, SCHEDULE.hears, MAX_BYTES, progress)


def _each(links: list[ZenohRobotLink], call) -> list:
    """``call(link)`` for every link, concurrently; what each returned or raised."""
    results: list = [None] * len(links)

    def run(k: int) -> None:
        try:
            results[k] = call(links[k])
        except InputError as exc:
            results[k] = exc

    threads = [threading.Thread(target=run, args=(k,)) for k in range(len(links))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    return results


def _meet(links: list[ZenohRobotLink]) -> list:
    return _each(links, lambda link: link.meet_team(wait_log_s=5.0))


def _finish(links: list[ZenohRobotLink], peers: list[int]) -> None:
    _each(links, lambda link: link.finish(peers, timeout=30.0))


def _request(sender: int, recipient: int, time_s: float) -> EncodingRequest:
    return EncodingRequest(
        sender=sender, recipient=recipient, round=0, time_s=time_s, keyframes=[3]
    )


def test_the_receiver_drops_what_it_could_not_hear_and_counts_the_rest(network):
    (first, second), keys = network
    progress: list = []
    links = [_link(first, keys, 0, progress=progress.append), _link(second, keys, 1)]
    hellos = _meet(links)
    assert [sorted(h) for h in hellos] == [[0, 1], [0, 1]]
    assert hellos[0][1].end_s == 3.0
    in_range, out_of_range = _request(1, 0, 0.5), _request(1, 0, 1.5)  # robot 0 left at 1 s
    links[1].send(out_of_range)
    links[1].send(in_range)
    assert links[0].receive(30.0) == in_range
    assert links[0].receive(0.5) is None
    size = len(codec.encode(in_range))
    assert links[0].traffic.to_json()["received"] == {"EncodingRequest": size}
    assert links[0].traffic.filtered == {"EncodingRequest": 1}
    sent = links[1].traffic.to_json()
    assert sent["sent"] == {"EncodingRequest": 2 * size}
    assert sent["by_peer"] == {"0": {"sent": {"EncodingRequest": 2 * size}, "received": {}}}
    # messages to the driver stay in the process: the progress callback
    note = RobotProgress(sender=0, recipient=DRIVER, round=0, frames_done=3, keyframes=1)
    links[0].send(note)
    assert progress == [note] and links[0].traffic.messages_sent == {}
    _finish(links, [0, 1])


def test_invalid_messages_are_logged_and_dropped(network, caplog):
    (first, second), keys = network
    links = [_link(first, keys, 0), _link(second, keys, 1)]
    _meet(links)
    to_robot_0 = keys.messages(0, 1)
    for key, payload in [
        (to_robot_0, b"\x80\x04not msgpack"),
        (to_robot_0, codec.encode(_request(0, 0, 0.5))),  # names robot 0 as sender
        (keys.messages(0, 5), codec.encode(_request(5, 0, 0.5))),  # no robot 5
        (to_robot_0, np.zeros(MAX_BYTES + 1, np.uint8).tobytes()),
        (to_robot_0, codec.encode(_request(1, 0, 0.5))),
    ]:
        # BLOCK as the transport does: the default (DROP) loses puts behind the large one
        # when the machine is busy
        second.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
    assert links[0].receive(30.0) == _request(1, 0, 0.5)
    assert links[0].traffic.invalid == 4
    assert "exceeds the cap" in caplog.text and "malformed msgpack" in caplog.text
    _finish(links, [0, 1])


def test_a_peer_whose_process_ends_is_reported_gone(network):
    (first, second), keys = network
    links = [_link(first, keys, 0), _link(second, keys, 1)]
    _meet(links)
    second.close()  # robot 1's process ends: its liveliness token goes with its session
    assert links[0].receive(30.0) == PeerLeft(1)
    links[0].finish([0, 1], timeout=30.0)  # robot 1 is gone: nobody to wait for


def test_robots_with_different_plans_refuse_each_other(network):
    (first, second), keys = network
    links = [_link(first, keys, 0, plan="a"), _link(second, keys, 1, plan="b")]
    results = _meet(links)
    assert all(isinstance(r, InputError) for r in results)
    assert "robot 1 runs another mission plan" in str(results[0])
    _finish(links, [])
