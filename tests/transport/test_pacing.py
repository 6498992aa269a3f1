"""The rate limit and priorities of a sender (transport/pacing.py, the Zenoh Sender): a
token bucket that lets a put go once its debt is paid; small messages ahead of large ones,
never waiting for a large one's debt."""

from __future__ import annotations

import threading

import pytest

from como3r.transport.pacing import MBPS, Lanes, TokenBucket, bytes_per_s


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_bucket_lets_a_put_go_once_its_debt_is_paid() -> None:
    clock = _Clock()
    bucket = TokenBucket(rate=1000.0, burst=500.0, clock=clock)
    assert bucket.delay() == 0.0  # the burst: the first put goes at once
    bucket.spend(2500)  # a put larger than the burst goes whole, in debt
    assert bucket.delay() == pytest.approx(2.0)
    clock.now = 1.5
    assert bucket.delay() == pytest.approx(0.5)
    clock.now = 100.0  # idle: no more than the burst accrues
    assert bucket.delay() == 0.0 and bucket.level == 500.0
    assert bytes_per_s(0) is None and bytes_per_s(8) == 8 * MBPS == 1e6


def test_control_goes_before_bulk_and_never_waits_for_its_debt() -> None:
    clock = _Clock()
    lanes: Lanes[str] = Lanes(rate=1000.0, burst=1000.0, clock=clock)
    for name in ("kf0", "kf1", "kf2"):
        lanes.add(name, 3000, control=False)
    assert lanes.next() == ("kf0", 0.0)  # within the burst
    wait = lanes.next()  # kf1 waits for kf0's debt ...
    assert wait == (None, pytest.approx(2.0))
    lanes.add("pose update", 200, control=True)
    assert lanes.next() == ("pose update", 0.0)  # ... a pose update does not
    assert lanes.backlog_s() == pytest.approx(6.0)  # kf1, kf2 at 1000 B/s
    clock.now = 2.2  # the pose update's bytes count against the bulk too
    assert lanes.next() == ("kf1", 0.0)
    assert lanes.next()[0] is None
    assert lanes.peak_bytes == 9000


def test_the_zenoh_sender_puts_a_pose_update_before_the_queued_keyframes() -> None:
    pytest.importorskip("zenoh")
    from como3r.transport.zenoh_protocol import Sender

    class _Session:
        def __init__(self) -> None:
            self.puts: list[str] = []
            self.first = threading.Event()

        def put(self, key: str, payload: bytes, **kwargs) -> None:
            self.puts.append(key)
            self.first.set()

    session = _Session()
    # 0.8 Mbit/s: 100 kB/s; the last of six 50 kB keyframe pieces goes 2.3 s after the first
    sender = Sender(session, max_mbps=0.8, control=lambda nbytes: nbytes <= 1024)
    for k in range(6):
        sender.put(f"keyframe/{k}", bytes(50_000))
    assert session.first.wait(10.0)
    sender.put("pose_update", bytes(100))
    sender.close(timeout=30.0)
    assert sorted(session.puts) == sorted([*(f"keyframe/{k}" for k in range(6)), "pose_update"])
    assert session.puts.index("pose_update") < session.puts.index("keyframe/5"), session.puts
    assert sender.bytes_put == 300_100
