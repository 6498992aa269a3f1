"""``como3r coordinator --resume`` (runtime/runtime_state.py; issue 14 item 2 across
machines): a coordinator killed with SIGKILL at several points while its agents track on
(early, mid-stream, and after the agents have left while it runs the terminal refinement) and
started again with ``--resume`` each time ends with the outputs of an uninterrupted run; the
agents lose nothing and leave only once the store holds everything they sent."""

from __future__ import annotations

import json
import math
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from como3r.config import Config, apply_overrides
from como3r.errors import StoreError
from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.pipeline import PriorSpec
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME
from como3r.transport.links import Joined, Received
from como3r.transport.messages import KeyframeMessage

zenoh = pytest.importorskip("zenoh")

LIMIT_S = 240
RESUMED = "coordinator resumed from"


def _stored(store: Path) -> int:
    """Keyframes the store holds (0 before it exists). Read paged: polled every 50 ms while
    the team works, a full read (every pointmap) takes 3.5 times the CPU (70 against 20 ms
    for 14 keyframes)."""
    try:
        return len(read_session(store, paged=True).graph)
    except StoreError:
        return 0


def _until(condition, what: str) -> None:
    deadline = time.monotonic() + LIMIT_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _start(team, out: Path, agents: list[Path]) -> list:
    """Coordinator and agents; returns the processes, the coordinator's first."""
    args = [a for path in agents for a in ("--gt", str(path))]
    return [team.coordinator(out, 2, *args)] + [
        team.agent(a, path) for a, path in enumerate(agents)
    ]


def _wait(team) -> None:
    for name in ("agent0", "agent1", "coordinator"):
        team.wait(name)


def _run(team, out: Path, agents: list[Path], kills: list[int | str]) -> list[float]:
    """Coordinator and agents; at each kill point (keyframes stored, or ``"left"``: both
    agents have left) kill -9 the coordinator and start it again with ``--resume``.
    Returns the seconds from each restart until the coordinator had restored its state."""
    args = [a for path in agents for a in ("--gt", str(path))]
    coordinator, *processes = _start(team, out, agents)
    store = out.with_name(out.name + ".partial") / STORE_NAME
    seconds = []
    for kill in kills:
        if kill == "left":
            _until(lambda: all(p.poll() is not None for p in processes), "agents never left")
        else:
            _until(lambda: _stored(store) >= kill, f"{kill} keyframes never stored")
        assert coordinator.poll() is None, team.log("coordinator")  # still at work
        coordinator.send_signal(signal.SIGKILL)
        coordinator.wait()
        restarted, count = time.monotonic(), team.log("coordinator").count(RESUMED)
        coordinator = team.coordinator(out, 2, *args, "--resume")
        _until(
            lambda: team.log("coordinator").count(RESUMED) > count,
            "the coordinator never resumed: " + team.log("coordinator"),
        )
        seconds.append(time.monotonic() - restarted)
    _wait(team)
    return seconds


@pytest.mark.slow
def test_a_coordinator_killed_at_several_points_resumes_to_the_uninterrupted_result(
    tiny_scene, free_running, new_team, tmp_path
) -> None:
    """The uninterrupted run is the session's ``free_running`` one (conftest.py): the same
    team, commands and scene."""
    scene = tiny_scene(frames=12, seed=0, overlap=0.5)  # 6 processed frames per agent
    agents = [scene / "agent_0", scene / "agent_1"]
    team = new_team("killed")
    seconds = _run(team, tmp_path / "killed.out", agents, [2, 5, "left"])
    reference, metrics = (
        json.loads((out / "metrics.json").read_text())
        for out in (free_running.out, tmp_path / "killed.out")
    )
    assert team.log("coordinator").count(RESUMED) == 3
    assert metrics["components"] == reference["components"] == [[0, 1]]
    for entry, own in zip(metrics["runtime"]["agents"], metrics["agents"]):
        assert entry["status"] == "finished" and entry["restarts"] == 0, entry
        assert entry["frames_done"] == entry["frames_expected"] == 6  # none counted twice
        assert entry["keyframes_received"] == own["keyframes"]  # every keyframe it made
    assert "re-sending" in team.log("agent0") + team.log("agent1")
    assert metrics["coordinator"]["keyframes"] == sum(a["keyframes"] for a in metrics["agents"])
    ate, expected = (m["ate"]["merged"]["ate"]["rmse"] for m in (metrics, reference))
    print(
        f"merged ATE {ate * 1e3:.3f} mm after 3 kills, {expected * 1e3:.3f} mm uninterrupted; "
        f"restart to state restored {', '.join(f'{s:.1f}' for s in seconds)} s"
    )
    # both runs are free-running: their batches, and so when the in-stream BA runs, differ
    # (test_network's tcp test, the same run), which the terminal alternation absorbs;
    # which candidates are verified does not: keyframes go by (timestamp, agent), a batch
    # is verified in that order, and after each restart the order waits for the agents
    # that were present, while they re-send by the latest keyframe each re-sent (ordered
    # by the stored clocks, infinite for an agent that had finished, one agent's later
    # keyframes went ahead of the other's re-sent ones in 3 of 6 runs: 14.92 and 15.44 mm;
    # CI at b60fb32 13.85). Measured killed 15.304 mm in 19 runs (kills at 2/5/left and
    # 1/3/8/left: after a restart the rest came as one batch, one in-stream BA),
    # uninterrupted 15.297-15.411 in 14 (by where the batch that merges ends), load 7-33
    # on 2 shared cores, 6 of the runs with one or two more cores' worth burnt: 0.70 %
    # apart at most. The counts above, which a lossy resume would break, are exact
    assert ate == pytest.approx(expected, rel=0.015)
    session = read_session(tmp_path / "killed.out" / STORE_NAME)
    assert session.finished and set(session.reports) == {0, 1}


def test_keyframes_re_sent_after_a_restart_keep_the_order_of_an_uninterrupted_run(
    scripted_hub,
) -> None:
    """Both agents had finished when the coordinator was killed, their last keyframes not
    taken yet (their stored clocks are infinite): the resumed coordinator orders by what
    each agent has re-sent so far, so agent 1, all of whose keyframes are back, does not
    go ahead of agent 0's still on their way (in a killed run of the test above, agent 1's
    keyframes 4 and 5 were taken before agent 0's keyframe 4 and retrieved another
    database)."""
    from como3r.runtime.processes import _Runtime

    hub = scripted_hub
    config = apply_overrides(Config(), ["input.long_side=64"])
    options = RuntimeOptions()
    runtime = _Runtime(hub, [0, 0], config, PriorSpec("simulated"), options, None)
    runtime.start([None, None], PriorSpec("simulated"))
    batches: list = []

    def taken(batch, solve=True) -> None:  # what the coordinator takes, its segments' keyframes
        batches.append([(w.message()[0].packet.agent, w.message()[0].packet.kf_id) for w in batch])
        for waiting in batch:
            waiting.segment.result.keyframes.append(waiting.message()[0].packet)

    runtime._add_keyframes = taken
    for slot in runtime.slots:  # as restore_runtime leaves a store that holds no keyframe
        slot.status, slot.clock, slot.handled_seq = "finished", math.inf, 5
        slot.resend_until, slot.away_since, slot.awaited = 5, time.monotonic(), True

    def keyframe(agent: int, kf_id: int, seq: int) -> Received:
        packet = SimpleNamespace(
            agent=agent, kf_id=kf_id, timestamp=2 * kf_id / 30, frame_index=2 * kf_id
        )
        return Received(agent, KeyframeMessage(packet, 0, None), seq)

    def pump(*events) -> None:
        hub.script = list(events)
        runtime._pump(0.0)
        runtime._process_pending()

    finished = [SimpleNamespace(agent=a) for a in (0, 1)]  # its AgentFinished, stored
    pump(Joined(0), Joined(1))
    assert [s.order_clock() for s in runtime.slots] == [-math.inf, -math.inf]
    pump(*(keyframe(1, k, 1 + k) for k in range(3)), Received(1, finished[1], 5))
    pump(keyframe(0, 0, 1))  # agent 0's keyframes 1 and 2 are still on their way
    assert runtime.slots[0].order_clock() == 0.0 and runtime.slots[1].order_clock() == math.inf
    pump(keyframe(0, 1, 2))
    pump(keyframe(0, 2, 3), Received(0, finished[0], 5))
    assert batches == [[(0, 0)], [(1, 0), (0, 1)], [(1, 1), (0, 2), (1, 2)]]
