"""benchmarks/team_scale.py's replay of the coordinator's backlog at the agents' measured
rates, for a coordinator of one core and of P cores (its verification spread over them),
on hand-made calls whose queue is worked out below."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from team_scale import call_seconds, cores_to_keep_up, replay  # noqa: E402

# two agents at 1 s of CPU per frame, frames at 0.1 s of input apart; agent 0's keyframes at
# its frames 0 and 2 (done at 1 s and 3 s), agent 1's at its frame 0 (done at 1 s)
FRAMES = {0: np.arange(4) * 0.1, 1: np.arange(4) * 0.1}
RATE = {0: 1.0, 1: 1.0}
# (coordinator thread CPU, keyframes, of it verified in line, pool workers' CPU)
CALLS = [
    (3.0, [(0, 0, 0.0), (1, 0, 0.0)], 2.0, 0.0),  # 1 s serial + 2 s in line, 1.5 s per kf
    (1.5, [(0, 1, 0.2)], 0.5, 2.5),  # 1 s serial, 3 s of verification in all
]


def test_one_core_serves_all_the_work_and_p_cores_spread_the_verification() -> None:
    assert call_seconds(CALLS[0], 1) == pytest.approx(3.0)
    assert call_seconds(CALLS[1], 1) == pytest.approx(4.0)  # its thread's and the pool's
    assert call_seconds(CALLS[0], 4) == pytest.approx(1.0 + 2.0 / 4)
    assert call_seconds(CALLS[1], 4) == pytest.approx(1.0 + 3.0 / 4)
    assert call_seconds((2.0, [(0, 0, 0.0)]), 8) == pytest.approx(2.0)  # older records: serial


def test_the_backlog_at_the_end_of_the_input() -> None:
    # the input ends when the agents' 4th frames are done, at 4 s. One core: keyframes
    # arrive at 1, 1 and 3 s and take 1.5, 1.5 and 4 s: done at 2.5, 4 and 8 s; at 4 s the
    # third waits (one keyframe, 0.2 s of input behind the newest handled at 0.0), 4 s to go
    # (begun at 4 s, in hand: none queued)
    waiting, behind, drain, queued = replay(CALLS, FRAMES, RATE)
    assert (waiting, behind, drain, queued) == (1, pytest.approx(0.2), pytest.approx(4.0), 0)
    # four cores: 0.75, 0.75 and 1.75 s: done at 1.75, 2.5 and 4.75 s
    waiting, behind, drain, queued = replay(CALLS, FRAMES, RATE, cores=4)
    assert (waiting, behind, drain, queued) == (1, pytest.approx(0.2), pytest.approx(0.75), 0)
    # sixteen: 0.5625, 0.5625, 1.1875: the last done at 4.1875
    assert replay(CALLS, FRAMES, RATE, cores=16)[2] == pytest.approx(0.1875)
    # an idle coordinator's catch-up (a call without keyframes) is not in the replay
    idle = (5.0, [], 5.0, 1.0)
    assert replay([*CALLS, idle], FRAMES, RATE) == replay(CALLS, FRAMES, RATE)


def test_the_cores_a_coordinator_needs_to_keep_up() -> None:
    # one agent at 1 s of CPU per frame: keyframes at its frames 0, 1 and 2 arrive at 1, 2
    # and 3 s, when the input ends; each call 2 s of CPU, 1.5 s of it verification in line
    frames = {0: np.arange(3) * 0.1}
    calls = [(2.0, [(0, k, 0.1 * k)], 1.5, 0.0) for k in range(3)]
    # one core: 2 s each, begun at 1, 3 and 5 s; at 3 s the second is in hand and the third
    # queued
    assert replay(calls, frames, {0: 1.0}) == (2, pytest.approx(0.2), pytest.approx(4.0), 1)
    # two: 0.5 + 0.75 s, the second begun at 2.25 s, the third queued until 3.5 s; four:
    # 0.875 s, each begun as it arrives, the third in hand at the end and none queued
    assert replay(calls, frames, {0: 1.0}, cores=2)[3] == 1
    assert replay(calls, frames, {0: 1.0}, cores=4)[3] == 0
    assert cores_to_keep_up(calls, frames, {0: 1.0}) == 4
    # a serial part longer than the keyframes' spacing: no number of cores keeps up
    serial = [(2.0, [(0, k, 0.1 * k)], 0.5, 0.0) for k in range(3)]
    assert cores_to_keep_up(serial, frames, {0: 1.0}) == ">256"
