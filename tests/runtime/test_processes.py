"""The multi-process runtime against the single-process runner, and under agent failures."""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import shutil
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.errors import InputError
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import PoseUpdate
from como3r.geometry.lie import sim3_exp
from como3r.io.tum import read_tum
from como3r.live import FrameEvent
from como3r.prior.simulated import SimulatedPrior
from como3r.progress import AgentProgress, PhaseEvent, ProgressEvent
from como3r.runtime.agent_events import RuntimeOptions
from como3r.runtime.multiprocess import run_multiprocess
from como3r.runtime.pipeline import PriorSpec, RunSummary, run
from como3r.runtime.results import AgentResult, KeyframeView
from como3r.transport.messages import FrameDone, Step
from como3r.transport.pipes import Channel

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

WIDTH, HEIGHT, FRAMES, SHORT = 64, 48, 12, 8
# small global solves keep the test fast; they do not change what is compared
# the easy simulated prior: under the realistic default the free-running trajectories differ
# from the single-process run by 0.23 % (bound 0.1 %)
OVERRIDES = [
    f"input.long_side={WIDTH}",
    "simulated_prior.model=easy",
    "global_ba.max_iters_stream=5",
    "global_ba.max_iters_cleanup=10",
    "global_ba.cleanup_passes=1",
]


#: torch threads of the process that starts the free-running run (the suite uses one)
FINISH_THREADS = 2

#: the phase that shows the coordinator's backlog while agents stream
BACKLOG = "backlog"

#: the slow-reader test's hung-agent timeout at its first check after its coordinator was
#: busy [s], and how long the coordinator is busy at least (longer: the agent's messages
#: wait unread past the timeout)
HUNG_S, BUSY_S = 1.0, 2.0

#: its timeout at every other check: it covers the agent's start-up (interpreter, torch,
#: prior), which took over 8 s once in four runs at a load of 10-15 and in a CI run at a
#: load of about 20 ("no message for 8 s (hung)"), and the agent's frames under load
START_S = 60.0


def _truncate(agent_dir: Path, frames: int) -> None:
    """Keep the first ``frames`` frames of a synthetic agent input."""
    for sub in ("rgb", "depth", "surface"):
        for path in sorted((agent_dir / sub).iterdir())[frames:]:
            path.unlink()
    stamps = (agent_dir / "timestamps.txt").read_text().splitlines()[:frames]
    (agent_dir / "timestamps.txt").write_text("\n".join(stamps) + "\n")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """Two agents that meet; agent 1's stream is shorter (its process ends first)."""
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.5,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
    )
    _truncate(root / "agent_1", SHORT)
    return root


@pytest.fixture(scope="module")
def config() -> Config:
    return apply_overrides(Config(), OVERRIDES)


def _agents(scene: Path) -> list[Path]:
    return [scene / "agent_0", scene / "agent_1"]


@pytest.fixture(scope="module")
def heard() -> dict[str, list[object]]:
    """What the module's runs told their ``progress`` and ``live`` callbacks, by run."""
    return {}


@pytest.fixture(scope="module")
def single(scene, config, tmp_path_factory, heard) -> Path:
    out = tmp_path_factory.mktemp("runs") / "single"
    events = heard.setdefault("single", [])
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in every process of the multi-process run
    try:
        run(
            _agents(scene),
            out,
            config,
            PriorSpec("simulated"),
            progress=events.append,
            live=events.append,
        )
    finally:
        torch.set_num_threads(threads)
    return out


@pytest.fixture(scope="module")
def lockstep(scene, config, tmp_path_factory, heard) -> tuple[Path, RunSummary]:
    out = tmp_path_factory.mktemp("runs") / "lockstep"
    events = heard.setdefault("lockstep", [])
    summary = run_multiprocess(
        _agents(scene),
        out,
        config,
        PriorSpec("simulated"),
        progress=events.append,
        live=events.append,
        options=RuntimeOptions(lockstep=True),
    )
    return out, summary


@pytest.fixture(scope="module")
def free(scene, config, tmp_path_factory) -> tuple[Path, RunSummary]:
    out = tmp_path_factory.mktemp("runs") / "free"
    progress: list[ProgressEvent] = []
    threads = torch.get_num_threads()
    torch.set_num_threads(FINISH_THREADS)  # the caller's threads, for the terminal work
    try:
        # keyframes one at a time, as the single-process run takes them: whether a busy
        # coordinator batches them depends on the machine's timing (batches: test_coordinator)
        one_by_one = apply_overrides(config, ["global_ba.max_batch_keyframes=1"])
        summary = run_multiprocess(
            _agents(scene), out, one_by_one, PriorSpec("simulated"), progress=progress.append
        )
    finally:
        torch.set_num_threads(threads)
    # every FrameDone is one AgentProgress, counted per agent; the terminal phases follow
    frames = [e for e in progress if isinstance(e, AgentProgress)]
    for agent, total in enumerate((FRAMES // 2, SHORT // 2)):
        mine = [e for e in frames if e.agent == agent]
        assert [e.frames_done for e in mine] == list(range(1, total + 1))
        assert {e.frames_total for e in mine} == {total}
        assert mine[-1].keyframes == summary.agents[agent]["keyframes"]
        assert mine[-1].lost == summary.agents[agent]["lost"]
    # the agents' events with the coordinator's backlog among them, then the terminal work's
    streaming = [e for e in progress if not (isinstance(e, PhaseEvent) and e.name == BACKLOG)]
    assert streaming[: len(frames)] == frames
    phases = streaming[len(frames) :]
    assert all(isinstance(e, PhaseEvent) for e in phases)
    backlog = [e for e in progress if isinstance(e, PhaseEvent) and e.name == BACKLOG]
    assert all(e.done < e.total and "behind" in e.detail for e in backlog)
    assert {"alternation round", "outputs", "report"} <= {e.name for e in phases}
    return out, summary


def _metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def _max_relative_difference(a: Path, b: Path, kind: str, agent: int) -> float:
    """Largest pose difference between two runs' TUM files, relative to the path extent."""
    ta, tb = read_tum(a / kind / f"agent_{agent}.txt"), read_tum(b / kind / f"agent_{agent}.txt")
    assert np.array_equal(np.asarray(ta.timestamps), np.asarray(tb.timestamps))
    Ta, Tb = np.asarray(ta.T_WC), np.asarray(tb.T_WC)
    extent = max(np.ptp(Ta[:, :3], axis=0).max(), 1e-6)
    dq = np.minimum(np.abs(Ta[:, 3:7] - Tb[:, 3:7]), np.abs(Ta[:, 3:7] + Tb[:, 3:7])).max()
    return max(np.abs(Ta[:, :3] - Tb[:, :3]).max() / extent, dq)


def _assert_same_run(reference: Path, other: Path, tolerance: float) -> None:
    ref, oth = _metrics(reference), _metrics(other)
    assert ref["components"] == oth["components"] == [[0, 1]]  # the agents met
    for key in ("keyframes", "edges_accepted", "gauge_syncs"):
        assert ref["coordinator"][key] == oth["coordinator"][key], key
    # keyframes that waited for a busy coordinator share a batch and its one global BA
    shared = oth["coordinator"]["keyframes"] - oth["coordinator"]["batches"]
    runs = ref["coordinator"]["ba_runs"]
    assert runs - shared <= oth["coordinator"]["ba_runs"] <= runs
    for agent in (0, 1):
        for key in ("frames", "tracked", "lost", "keyframes"):
            assert ref["agents"][agent][key] == oth["agents"][agent][key], (agent, key)
        for kind in ("trajectories", "keyframes"):
            assert _max_relative_difference(reference, other, kind, agent) <= tolerance
    assert ref["map"]["confident_points"] == oth["map"]["confident_points"]
    # map.ply keeps a voxel's first point: one moved within the tolerance may cross a voxel
    assert abs(ref["map_points"] - oth["map_points"]) <= tolerance * ref["map_points"]
    rounds = [[r["rounds"] for r in m["coordinator"]["alternation"]] for m in (ref, oth)]
    assert rounds[0] == rounds[1] and rounds[0][0] >= 1  # the refined pointmaps came back
    graph_ref = json.loads((reference / "graph.json").read_text())
    graph_oth = json.loads((other / "graph.json").read_text())
    assert len(graph_ref["edges"]) == len(graph_oth["edges"])


@pytest.mark.slow
def test_lockstep_reproduces_the_single_process_run(single, lockstep) -> None:
    out, summary = lockstep
    _assert_same_run(single, out, tolerance=1e-6)
    # each keyframe alone, as in one process (the first ones wait for the camera to settle)
    coordinator = _metrics(out)["coordinator"]
    assert (
        coordinator["batches"]
        == coordinator["keyframes"]
        == _metrics(single)["coordinator"]["keyframes"]
    )
    assert [a["status"] for a in summary.agents] == ["finished", "finished"]


@pytest.mark.slow
def test_lockstep_agents_report_each_frame_as_in_one_process(single, lockstep, heard) -> None:
    """Both runtimes run an agent's frames through one loop (``AgentLoop``): on the same
    schedule, every frame's progress (outcome, keyframes made) and live event (pose, image)
    are the same and come in the same order."""
    one, many = (
        [e for e in heard[name] if isinstance(e, (AgentProgress, FrameEvent))]
        for name in ("single", "lockstep")
    )
    assert len(one) == 2 * (FRAMES // 2 + SHORT // 2)  # a live event and a progress a frame
    assert sum(isinstance(e, FrameEvent) and e.T_WC is not None for e in one) > FRAMES // 2
    for a, b in zip(one, many, strict=True):
        assert type(a) is type(b)
        if isinstance(a, AgentProgress):
            assert a == b
            continue
        assert (a.agent, a.frame_index, a.timestamp, a.state) == (
            b.agent,
            b.frame_index,
            b.timestamp,
            b.state,
        )
        assert np.array_equal(a.image, b.image)
        for mine, theirs in ((a.T_WC, b.T_WC), (a.K, b.K)):
            assert (mine is None) == (theirs is None)
            if mine is not None:
                np.testing.assert_allclose(mine, theirs, rtol=1e-6, atol=1e-6)


@pytest.mark.slow
def test_the_coordinator_finishes_on_the_cores_the_agents_freed(lockstep, free) -> None:
    """Free-running, the terminal refinement gets the caller's threads (it ran on one of
    two cores); lockstep keeps the serial schedule's single thread."""
    assert _metrics(free[0])["runtime"]["finish_torch_threads"] == FINISH_THREADS
    assert _metrics(lockstep[0])["runtime"]["finish_torch_threads"] == 1


@pytest.mark.slow
def test_agent_processes_report_their_time_per_stage(lockstep) -> None:
    out, _ = lockstep
    for agent in _metrics(out)["agents"]:
        stages = agent["stage_seconds"]
        assert {"prior_encode", "prior_decode", "matching", "tracking", "other"} <= set(stages)
        assert all(v >= 0.0 for v in stages.values())
        assert sum(stages.values()) == pytest.approx(agent["seconds"], rel=0.05)


@pytest.mark.slow
def test_free_running_agents_match_the_single_process_run(single, free) -> None:
    """Keyframes reach the coordinator in the same order; only the moment an agent applies a
    pose update differs, which the final global solve absorbs."""
    out, summary = free
    _assert_same_run(single, out, tolerance=1e-3)
    runtime = _metrics(out)["runtime"]
    assert runtime["lockstep"] is False and runtime["failed_agents"] == []
    assert [a["frames_done"] for a in runtime["agents"]] == [FRAMES // 2, SHORT // 2]
    # the coordinator's backlog: sampled when the input ended, and none left after it
    backlog, keyframes = runtime["backlog"], _metrics(out)["coordinator"]["keyframes"]
    assert backlog["keyframes_handled"] == keyframes
    assert keyframes >= backlog["max_keyframes"] >= backlog["end_keyframes"] >= 0
    assert backlog["max_seconds"] >= backlog["end_seconds"] >= 0.0
    assert backlog["drain_seconds"] >= 0.0


@pytest.mark.slow
@pytest.mark.parametrize("schedule", ["free", "lockstep"])
def test_bytes_are_counted_per_message_type_and_agent(schedule, request) -> None:
    out, _ = request.getfixturevalue(schedule)
    metrics = _metrics(out)
    runtime = metrics["runtime"]
    for agent, entry in enumerate(runtime["agents"]):
        assert entry["status"] == "finished" and entry["exitcode"] == 0
        sent, received = entry["messages_from_agent"], entry["bytes_from_agent"]
        assert sent["FrameDone"] == entry["frames_done"]
        assert sent["KeyframeMessage"] == metrics["agents"][agent]["keyframes"]
        assert sent["AgentStarted"] == sent["AgentFinished"] == 1
        # a keyframe carries pointmaps, colours, an encoding and matches: kilobytes
        assert received["KeyframeMessage"] > 1000 * sent["KeyframeMessage"] > 0
        assert entry["bytes_to_agent"]["AgentTask"] > 0
        assert entry["pose_updates_sent"] >= entry["messages_to_agent"].get("PoseUpdateMessage", 0)
        # the parts of the keyframe messages (the lossy codings, as across machines) add up to
        # nearly their bytes
        parts = metrics["bandwidth"][agent]["keyframe_message_bytes_by_part"]
        per_message = received["KeyframeMessage"] / sent["KeyframeMessage"]
        assert parts["pointmap"] > 0 and parts["colours"] > 0 and parts["encoding_rest"] > 0
        assert 0 < per_message - sum(parts.values()) < 1000
    total = sum(runtime["bytes_by_type"].values())
    assert (
        total
        == runtime["bytes_total"]
        == sum(
            sum(e["bytes_to_agent"].values()) + sum(e["bytes_from_agent"].values())
            for e in runtime["agents"]
        )
    )
    if schedule == "lockstep":  # the agents met while both ran (free-running, a busy
        # machine can delay the meeting past the agents' end: then no update is sent)
        assert runtime["bytes_by_type"]["PoseUpdateMessage"] > 0


@pytest.mark.slow
def test_killed_and_crashing_agents_leave_the_others_running(scene, config, tmp_path) -> None:
    """Agent 1 is SIGKILLed after its first frame, agent 2 fails on a truncated image; the
    coordinator and agent 0 finish and every output is written."""
    broken = tmp_path / "broken"
    shutil.copytree(scene / "agent_1", broken)
    image = broken / "rgb" / "000002.png"
    image.write_bytes(image.read_bytes()[:100])

    def kill_agent_1(event: ProgressEvent) -> None:
        if isinstance(event, AgentProgress) and event.agent == 1:
            for child in multiprocessing.active_children():
                if child.name == "como3r-agent-1" and child.is_alive():
                    os.kill(child.pid, signal.SIGKILL)

    out = tmp_path / "out"
    summary = run_multiprocess(
        [*_agents(scene), broken], out, config, PriorSpec("simulated"), progress=kill_agent_1
    )
    runtime = _metrics(out)["runtime"]
    assert [a["status"] for a in runtime["agents"]] == ["finished", "failed", "failed"]
    assert runtime["failed_agents"] == [1, 2]
    assert "signal 9" in runtime["agents"][1]["error"]
    assert "InputError" in runtime["agents"][2]["error"]
    assert "000002" in runtime["agents"][2]["error"]
    assert any(n.startswith("agent 1 failed") and "signal 9" in n for n in summary.notes)
    assert any(n.startswith("agent 2 failed") and "truncated" in n for n in summary.notes)
    for agent in range(3):
        assert (out / "trajectories" / f"agent_{agent}.txt").exists()
    agent_0 = summary.agents[0]
    assert agent_0["frames"] == FRAMES // 2
    trajectory = read_tum(out / "trajectories" / "agent_0.txt")
    assert len(trajectory.timestamps) == agent_0["frames"] - agent_0["lost"]
    assert (out / "map.ply").exists() and (out / "graph.json").exists()
    assert not multiprocessing.active_children()


@pytest.mark.slow
def test_a_silent_agent_is_terminated_as_hung(scene, config, tmp_path) -> None:
    options = RuntimeOptions(agent_timeout_s=0.2, shutdown_grace_s=2.0)
    with pytest.raises(InputError, match="every agent failed: agent 0: no message for"):
        run_multiprocess(
            [scene / "agent_0"], tmp_path / "out", config, PriorSpec("simulated"), options=options
        )
    assert not (tmp_path / "out").exists()
    assert not multiprocessing.active_children()


@pytest.mark.slow
@pytest.mark.usefixtures("lockstep")  # its agent processes fill numba's cache (below)
def test_a_coordinator_slow_to_read_costs_no_message_and_no_agent(
    scene, config, tmp_path, monkeypatch
) -> None:
    """The coordinator is busy (a global BA) for longer than the hung-agent timeout while
    the agent keeps sending: its messages wait, and once the coordinator reads again the
    agent counts as talking, not as hung (it used to be terminated as hung with its
    messages unread). The timeout is that short only at the first check after the busy
    keyframe: the test is of the coordinator's reading, not of the agent's start-up."""
    from como3r.runtime.processes import _Runtime

    add_keyframes, check_timeouts = _Runtime._add_keyframes, _Runtime._check_timeouts
    busy: list[int] = []
    # at the first check after the busy keyframe: how long the coordinator had not read the
    # agent, and whether it still waited for it
    seen: list[tuple[float, bool]] = []

    def busy_coordinator(self, batch, solve=True) -> None:
        if not busy:
            busy.append(batch[0].message()[0].packet.kf_id)
            time.sleep(BUSY_S)
            deadline = time.monotonic() + START_S
            while not self.hub.readers[0].ready():  # until the agent has sent more, unread
                assert time.monotonic() < deadline, "the agent sent nothing more"
                time.sleep(0.01)
        add_keyframes(self, batch, solve)

    def check_after_busy(self, watched) -> None:
        if not busy or seen:
            check_timeouts(self, watched)
            return
        slot, options = self.slots[0], self.options
        seen.append((time.monotonic() - slot.last_heard, slot in watched))
        self.options = replace(options, agent_timeout_s=HUNG_S)
        check_timeouts(self, watched)
        self.options = options

    # A run of agent processes on this configuration first (``lockstep``, the module's own,
    # made once), so that the agent's compiled loops are in numba's cache on disk: in a
    # fresh checkout the timed agent compiles them in its first frames and stays silent
    # for long (measured at a timeout of 8 s: "no message for 8 s (hung)" every time). The
    # module's run serves as well as a run of this agent alone, which it replaced.
    monkeypatch.setattr(_Runtime, "_add_keyframes", busy_coordinator)
    monkeypatch.setattr(_Runtime, "_check_timeouts", check_after_busy)
    options = RuntimeOptions(agent_timeout_s=START_S)
    summary = run_multiprocess(
        [scene / "agent_0"], tmp_path / "out", config, PriorSpec("simulated"), options=options
    )
    runtime = _metrics(tmp_path / "out")["runtime"]
    assert busy and runtime["failed_agents"] == [], runtime["agents"][0]["error"]
    [(silence, waited)] = seen
    assert waited and silence > HUNG_S  # its messages waited unread past the timeout
    assert summary.agents[0]["frames"] == FRAMES // 2
    assert runtime["agents"][0]["keyframes_received"] == summary.agents[0]["keyframes"]


def test_bad_input_fails_before_any_process_starts(scene, config, tmp_path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        run_multiprocess(
            [scene / "agent_0", tmp_path / "missing"],
            tmp_path / "out",
            config,
            PriorSpec("simulated"),
        )
    assert not multiprocessing.active_children()


# ---------------------------------------------------------------------- pieces


def test_channel_counts_bytes_and_enforces_the_cap() -> None:
    reader, writer = multiprocessing.Pipe(duplex=False)
    sender = Channel(None, writer, max_bytes=10_000, accepts=(Step,))
    receiver = Channel(reader, None, max_bytes=200, accepts=(Step, FrameDone))
    sender.send(Step(frame_index=4))
    assert receiver.poll(5.0) and receiver.receive() == Step(frame_index=4)
    assert sender.traffic.bytes_sent == receiver.traffic.bytes_received
    assert sender.traffic.bytes_sent["Step"] > 0
    sender.send(
        FrameDone(
            agent=0, frame_index=1, timestamp=0.0, outcome="x" * 500, seconds=0, keyframes_waiting=0
        )
    )
    assert receiver.poll(5.0)
    with pytest.raises(OSError, match="bad message length"):  # over the cap: unread
        receiver.receive()
    sender.close()
    receiver.close()


def test_close_waits_until_a_late_reader_has_the_whole_message() -> None:
    """An agent's last message outlives a busy coordinator: close() returns only once the
    reader took all of it (it used to give up after 30 s and cut the pipe mid-message)."""
    reader, writer = multiprocessing.Pipe(duplex=False)
    sender = Channel(None, writer, max_bytes=10_000_000, accepts=(FrameDone,))
    receiver = Channel(reader, None, max_bytes=10_000_000, accepts=(FrameDone,))
    big = FrameDone(
        agent=0,
        frame_index=1,
        timestamp=0.0,
        outcome="x" * 2_000_000,
        seconds=0,
        keyframes_waiting=0,
    )
    sender.send(big)  # far beyond the pipe's buffer: the sender thread blocks on it
    received: list[FrameDone] = []
    late_reader = threading.Timer(1.0, lambda: received.append(receiver.receive()))
    late_reader.start()
    started = time.monotonic()
    sender.close()
    waited = time.monotonic() - started
    late_reader.join()
    receiver.close()
    assert waited >= 0.9 and received == [big]


def test_agent_result_applies_updates_like_the_frontend() -> None:
    """Updates an agent never saw are applied for it with the front-end's own semantics."""
    generator = torch.Generator().manual_seed(0)
    poses = sim3_exp(0.3 * torch.randn(5, 7, dtype=torch.float64, generator=generator))
    frontend = AgentFrontend(SimulatedPrior(Config().simulated_prior), Config(), 0, None)
    result = AgentResult(agent=0)
    for k, pose in enumerate(poses):
        frontend.keyframes.add(
            Keyframe(
                k,
                2 * k,
                0.1 * k,
                None,
                pose.clone(),
                torch.zeros(1, 1, 3),
                torch.ones(1, 1),
                torch.zeros(1, 1, 3),
                torch.ones(1, 1),
                np.zeros((1, 1, 3), np.uint8),
            )
        )
        result.keyframes.append(
            KeyframeView(k, 2 * k, 0.1 * k, pose.clone(), graph=None, agent=0, graph_kf_id=k)
        )  # poses only
    for count in (3, 5, 1):
        new = sim3_exp(0.3 * torch.randn(count, 7, dtype=torch.float64, generator=generator))
        update = PoseUpdate(agent=0, kf_ids=torch.arange(count), T_WC=new, reason="global_ba")
        frontend.apply_pose_update(update)
        result.apply_pose_update(update)
        assert torch.allclose(
            frontend.keyframes.poses(), result.keyframe_trajectory()[2], atol=1e-12
        )
    assert not torch.allclose(poses[3:], frontend.keyframes.poses()[3:])


# ---------------------------------------------------------------------- away, back, rejoin


def _scripted_runtime(hub, away_timeout_s: float, states: list) -> tuple:
    from como3r.runtime.processes import _Runtime

    runtime = _Runtime(
        hub,
        [0, 0],
        apply_overrides(Config(), OVERRIDES),
        PriorSpec("simulated"),
        RuntimeOptions(away_timeout_s=away_timeout_s),
        lambda e: states.append((e.agent, e.state)),
    )
    runtime.start([None, None], PriorSpec("simulated"))
    return hub, runtime


def _pump(hub, runtime, *events) -> None:
    hub.script = list(events)
    runtime._pump(0.0)


def test_an_agent_whose_link_is_lost_is_away_then_back_or_failed(scripted_hub) -> None:
    from como3r.transport.links import Joined, Left, Received
    from como3r.transport.messages import AgentStarted, PoseUpdateMessage

    states: list = []
    hub, runtime = _scripted_runtime(scripted_hub, 0.3, states)
    slot = runtime.slots[0]
    _pump(
        hub,
        runtime,
        Received(0, AgentStarted(agent=0, pid=1, frames=6)),
        Left(0, "left (link lost)", may_return=True),
    )
    assert slot.status == "running" and slot.away_since is not None
    assert states[-1] == (0, "away")
    runtime._send_update(
        PoseUpdate(
            agent=0,
            kf_ids=torch.zeros(0, dtype=torch.int64),
            T_WC=torch.zeros(0, 8),
            reason="global_ba",
        )
    )
    assert hub.sent == []  # nobody to send it to: kept for its return
    _pump(hub, runtime, Joined(0))
    assert slot.away_since is None and slot.absences == 1
    [(agent, message)] = hub.sent
    assert agent == 0 and isinstance(message, PoseUpdateMessage) and message.seq == 1
    _pump(hub, runtime, Left(0, "left (link lost)", may_return=True))
    runtime._check_timeouts(runtime.slots)
    assert slot.status == "running"  # not yet
    time.sleep(0.35)
    runtime._check_timeouts(runtime.slots)
    assert slot.status == "failed" and "did not come back within 0.3 s" in slot.error
    assert hub.dropped == [0] and states[-1] == (0, "failed")


def test_a_process_ending_fails_its_agent_at_once(scripted_hub) -> None:
    from como3r.transport.links import Left

    hub, runtime = _scripted_runtime(scripted_hub, 120.0, [])
    _pump(hub, runtime, Left(1, "process died (exit code 1)"))  # pipes: it cannot return
    assert runtime.slots[1].status == "failed" and hub.dropped == [1]


def test_a_new_process_taking_over_an_id_starts_a_map_segment_after_the_last_frame(
    scripted_hub,
) -> None:
    from como3r.runtime.results import KeyframeView
    from como3r.transport.links import Left

    hub, runtime = _scripted_runtime(scripted_hub, 120.0, [])
    slot = runtime.slots[1]
    slot.status, slot.last_frame = "running", 6
    runtime.segments[1].result.keyframes.append(
        KeyframeView(0, 4, 0.1, torch.zeros(8), graph=None, agent=1, graph_kf_id=0)
    )  # frames only
    _pump(hub, runtime, Left(1, "left", may_return=True))
    task = runtime.rejoin(1)
    assert task.agent == 1 and task.resume_after == 6
    assert slot.segment.index == 2 == runtime.coordinator.num_agents - 1
    assert slot.segment.after_frame == 6 and slot.restarts == 1 and slot.away_since is None
    assert [s.index for s in runtime.segments] == [0, 1, 2]
    again = runtime.rejoin(1)  # a process that left before making a keyframe: same segment
    assert again.resume_after == 6 and len(runtime.segments) == 3
    runtime.slots[0].status = "finished"
    assert "has finished" in runtime.rejoin(0)
    runtime._fail(slot, "boom")
    assert "failed in this run (boom)" in runtime.rejoin(1)


def test_keyframes_an_agent_still_holds_keep_its_ordering_clock_back(scripted_hub) -> None:
    """A self-calibrated agent holds its first keyframes until its camera settles (each
    FrameDone counts them): its clock stays at the frame that made the oldest, so another
    agent's keyframe of that time waits for them, as the ``(timestamp, agent)`` order wants
    (it was taken first when the clock followed the frames)."""
    from types import SimpleNamespace

    from como3r.transport.links import Received
    from como3r.transport.messages import AgentStarted, FrameDone

    hub, runtime = _scripted_runtime(scripted_hub, 120.0, [])
    runtime.progress = None
    batches: list = []
    runtime._add_keyframes = lambda batch, solve=True: batches.append(
        [(w.message()[0].packet.agent, w.message()[0].packet.kf_id) for w in batch]
    )

    def done(agent: int, frame: int, waiting: int) -> Received:
        return Received(agent, FrameDone(agent, frame, frame / 30, "keyframe", 0.0, waiting))

    def keyframe(agent: int, kf_id: int, frame: int) -> None:  # as a KeyframeMessage queues
        packet = SimpleNamespace(agent=agent, kf_id=kf_id, timestamp=frame / 30, frame_index=frame)
        runtime._queue(runtime.segments[agent], SimpleNamespace(packet=packet), None)

    _pump(
        hub,
        runtime,
        *(Received(a, AgentStarted(agent=a, pid=1, frames=6)) for a in (0, 1)),
        done(0, 0, 1),
        done(0, 1, 2),  # agent 0 holds keyframes 0 and 1
    )
    keyframe(1, 0, 0)
    _pump(hub, runtime, done(1, 0, 0), done(1, 1, 0))
    assert runtime.slots[0].order_clock() == 0.0  # not frame 1's
    runtime._process_pending()
    assert batches == []  # (0, 0) may still come before agent 1's keyframe 0
    keyframe(0, 0, 0)
    keyframe(0, 1, 1)
    _pump(hub, runtime, done(0, 2, 0))
    assert runtime.slots[0].order_clock() == 2 / 30
    runtime._process_pending()
    assert batches == [[(0, 0), (1, 0), (0, 1)]]


def test_a_long_backlog_goes_to_the_coordinator_in_parts_solved_after_each_batch(
    scripted_hub,
) -> None:
    """Issue 41: a batch (``global_ba.max_batch_keyframes``, 32) is handed over in parts of
    ``HANDOVER_KEYFRAMES`` (16), each a transaction and a page-out of its own (the batch's
    keyframes are not all in memory at once), the global BA allowed after the last part only,
    so a trailing coordinator solves as often as with whole batches."""
    from types import SimpleNamespace

    from como3r.runtime.processes import HANDOVER_KEYFRAMES

    hub, runtime = _scripted_runtime(scripted_hub, 120.0, [])
    runtime.progress = None
    parts: list = []
    runtime._add_keyframes = lambda batch, solve=True: parts.append(
        ([w.message()[0].packet.kf_id for w in batch], solve)
    )
    for kf_id in range(40):  # agent 0 alone, both finished: everything's turn has come
        packet = SimpleNamespace(agent=0, kf_id=kf_id, timestamp=kf_id / 30, frame_index=kf_id)
        runtime._queue(runtime.segments[0], SimpleNamespace(packet=packet), None)
    for slot in runtime.slots:
        slot.status, slot.clock = "finished", math.inf
    runtime._process_pending()
    assert HANDOVER_KEYFRAMES == 16 == runtime.config.global_ba.max_batch_keyframes // 2
    assert parts == [
        (list(range(0, 16)), False),
        (list(range(16, 32)), True),
        (list(range(32, 40)), True),
    ]


def test_an_agent_away_since_the_coordinator_restarted_still_orders_the_keyframes(
    scripted_hub,
) -> None:
    """Restored from its store (runtime_state.restore_runtime), a coordinator waits for the
    agents that were present: their stored clocks order the keyframes until they are back,
    so which reconnects first does not decide the order; once back, an agent whose link
    is lost holds nothing back."""
    from como3r.transport.links import Joined, Left

    hub, runtime = _scripted_runtime(scripted_hub, 120.0, [])
    slot = runtime.slots[0]
    slot.status, slot.clock = "running", 0.2
    slot.away_since, slot.awaited = time.monotonic(), True  # as restore_runtime leaves it
    assert slot.order_clock() == 0.2
    _pump(hub, runtime, Joined(0))
    assert slot.away_since is None and not slot.awaited and slot.order_clock() == 0.2
    _pump(hub, runtime, Left(0, "left (link lost)", may_return=True))
    assert slot.order_clock() == float("inf")
