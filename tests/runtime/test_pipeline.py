"""``como3r run`` in one process: agents and coordinator end to end on synthetic scenes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.io.tum import read_tum
from como3r.runtime.pipeline import PriorSpec, run

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]

WIDTH, HEIGHT = 128, 96
# Shorter global solves keep the module fast on CPU (see tests/coordination).
# the easy simulated prior: each agent alone (without loop closure, or apart) is held to
# 0.5 % of the summed path, which the v2 prior exceeds (measured without loop closure: 1.15
# and 0.52 %; with it one gauge, merged 0.63 %, inside the 1 % of the test below). Merged
# accuracy on the v2 prior with the default configuration: test_accuracy_v2.py.
OVERRIDES = [
    f"input.long_side={WIDTH}",
    "simulated_prior.model=easy",
    "global_ba.step_tol=1e-5",
    "global_ba.trigger_interval_edges=3",
    "global_ba.max_iters_stream=10",
    "global_ba.max_iters_cleanup=30",
]


def _scene(root: Path, preset: str, frames: int) -> tuple[list[Path], float]:
    root.mkdir()
    synthesize(
        root,
        agents=2,
        seed=1,
        overlap=0.2,
        frames=frames,
        preset=preset,
        width=WIDTH,
        height=HEIGHT,
    )
    info = json.loads((root / "scene.json").read_text())
    length = sum(a["path_length_m"] for a in info["agents_info"])
    return [root / "agent_0", root / "agent_1"], length


def _run(agents: list[Path], out: Path, extra: list[str] = ()) -> dict:
    config = apply_overrides(Config(), [*OVERRIDES, *extra])
    run(agents, out, config, PriorSpec("simulated"))
    return {name: json.loads((out / f"{name}.json").read_text()) for name in ("graph", "metrics")}


@pytest.fixture(scope="module")
def meeting(tmp_path_factory):
    """Two agents that meet, run with and without loop closure."""
    root = tmp_path_factory.mktemp("meeting")
    agents, length = _scene(root / "scene", "default", frames=20)
    return (
        length,
        root / "with",
        _run(agents, root / "with"),
        _run(agents, root / "without", ["loop_closure=false"]),
    )


@pytest.fixture(scope="module")
def apart(tmp_path_factory):
    """Two agents in sealed compounds: they never see the same surface."""
    root = tmp_path_factory.mktemp("apart")
    agents, length = _scene(root / "scene", "no-meeting", frames=16)
    return length, _run(agents, root / "out")


def _agent_ates(metrics: dict) -> list[float]:
    return [a["ate"]["rmse"] for a in metrics["ate"]["agents"]]


def test_two_agents_share_one_gauge(meeting) -> None:
    length, out, result, _ = meeting
    graph, metrics = result["graph"], result["metrics"]
    assert graph["components"] == [[0, 1]] == metrics["components"]
    merged = metrics["ate"]["merged_components"]
    assert [m["agents"] for m in merged] == [[0, 1]]
    assert merged[0]["ate"]["rmse"] <= 0.01 * length, (merged, length)
    inter = [e for e in graph["edges"] if e["type"] == "inter"]
    assert inter and all(
        e["nu_i"] >= 0.1 and e["nu_j"] >= 0.1 and e["similarity"] > 0 for e in inter
    )
    coordinator = metrics["coordinator"]
    assert coordinator["gauge_syncs"] == 1 and coordinator["edges_accepted"] == len(inter)
    assert coordinator["ba_runs"] >= 1 and coordinator["cleanup_passes"] >= 1
    for agent in metrics["agents"]:
        assert agent["fps"] > 0 and agent["frames"] == 10
    # every processed frame, in the shared frame
    for a in range(2):
        assert len(read_tum(out / "trajectories" / f"agent_{a}.txt").timestamps) == 10


def test_terminal_refinement_reduces_the_map_error(meeting) -> None:
    """The simulated prior distorts every pointmap at low frequency; the terminal
    alternation (C-Sec. A.7: pose passes, then one depth step at their poses) must leave a
    more accurate map."""
    _, out, result, without_lc = meeting
    metrics = result["metrics"]
    (record,) = metrics["coordinator"]["alternation"]
    assert record["agents"] == [0, 1] and record["cleanup_passes"] >= 1
    assert record["reason"] in ("converged", "poses_frozen") and record["rounds"] == 1
    assert record["seconds"] > 0 and record["depth_parameters"] > 0
    (maps,) = metrics["map_accuracy"]
    assert maps["agents"] == [0, 1]
    before, final = maps["before_refinement"], maps["final"]
    print(f"map accuracy {before['accuracy']:.4f} -> {final['accuracy']:.4f} m")
    assert final["accuracy"] < 0.95 * before["accuracy"]
    assert final["chamfer"] < before["chamfer"]
    # apart: each agent is refined alone, at its own poses
    alone = without_lc["metrics"]["coordinator"]["alternation"]
    assert [r["agents"] for r in alone] == [[0], [1]]
    assert all(r["cleanup_passes"] == 0 and r["rounds"] == 1 for r in alone)
    assert [m["agents"] for m in without_lc["metrics"]["map_accuracy"]] == [[0], [1]]


def test_without_loop_closure_there_is_no_shared_gauge(meeting) -> None:
    # Per-agent ATE is NOT asserted to improve with loop closure (C-Tab. 4): on scenes this
    # small each agent's drift is already a few millimetres and the measured difference
    # goes either way (see the coordinator's report).
    length, _, _, without_lc = meeting
    assert without_lc["graph"]["components"] == [[0], [1]]
    assert without_lc["metrics"]["ate"]["merged_components"] == []
    assert without_lc["metrics"]["coordinator"]["cross_agent_retrieval"] is False
    assert not [e for e in without_lc["graph"]["edges"] if e["type"] == "inter"]
    assert without_lc["graph"]["candidates"] == []
    for ate in _agent_ates(without_lc["metrics"]):
        assert ate <= 0.01 * length / 2


def test_agents_that_never_meet_stay_apart(apart) -> None:
    length, result = apart
    graph, metrics = result["graph"], result["metrics"]
    assert graph["components"] == [[0], [1]] == metrics["components"]
    assert not [e for e in graph["edges"] if e["type"] == "inter"]
    assert metrics["ate"]["merged"] is None
    assert metrics["ate"]["merged_components"] == []
    assert metrics["coordinator"]["gauge_syncs"] == 0
    for ate in _agent_ates(metrics):
        assert ate <= 0.01 * length / 2


def test_metrics_give_each_agent_its_time_per_stage(meeting) -> None:
    _, _, result, _ = meeting
    for agent in result["metrics"]["agents"]:
        stages = agent["stage_seconds"]
        # prior_encode: waiting for the frame read and encoded ahead (runtime.prefetch)
        assert {
            "prior_encode",
            "prior_decode",
            "matching",
            "tracking",
            "fusion",
            "keyframe",
            "local_solve",
            "other",
        } <= set(stages)
        assert all(v >= 0.0 for v in stages.values())
        assert sum(stages.values()) == pytest.approx(agent["seconds"], rel=0.05)


def test_coordinator_time_includes_its_session_store_writes(meeting) -> None:
    _, _, result, _ = meeting
    stages = result["metrics"]["coordinator"]["stage_seconds"]
    assert {"verification", "global_ba", "cleanup", "journal"} <= set(stages)
    assert stages["journal"] > 0.0
