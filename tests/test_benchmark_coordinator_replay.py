"""benchmarks/coordinator_replay.py: a run's coordinator calls, recorded and replayed in one
process, give the run's own in-stream work again (its keyframes and decodes), the same on
every replay."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.runtime.pipeline import PriorSpec, run

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from coordinator_replay import calls, keyframe_ate, recording, replay, row  # noqa: E402

OVERRIDES = [
    "input.long_side=64",
    "global_ba.max_iters_stream=5",
    "global_ba.max_iters_cleanup=5",
    "global_ba.cleanup_passes=1",
    "depth.alternation_rounds=0",
]


def test_a_recorded_run_replays_its_in_stream_work(tmp_path, capsys) -> None:
    scene = tmp_path / "scene"
    scene.mkdir()
    synthesize(
        scene, agents=2, seed=0, overlap=0.5, frames=8, preset="default", width=64, height=48
    )
    config = apply_overrides(Config(), OVERRIDES)
    agents = [scene / "agent_0", scene / "agent_1"]
    with recording(tmp_path / "calls"):
        run(agents, tmp_path / "run", config, PriorSpec("simulated"), overwrite=True)
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())["coordinator"]
    recorded = list(calls(tmp_path / "calls"))
    batches = [what for kind, what, _ in recorded if kind == "batch"]
    assert sum(len(packets) for packets, _ in batches) == metrics["keyframes"]
    assert all(solve for _, solve in batches)  # batches of under 16: each solves
    first, seconds = replay(tmp_path / "calls", config)
    again, _ = replay(tmp_path / "calls", config)
    assert first.stats.keyframes == metrics["keyframes"] == sum(n for n, _ in seconds)
    assert first.stats.prior_decodes == metrics["prior_decodes"] > 0
    for g in range(len(first.graph)):
        assert torch.equal(first.graph.keyframes[g].T_WC, again.graph.keyframes[g].T_WC)
    line = row(first, seconds, scene)
    assert line["keyframes"] == metrics["keyframes"] and line["decodes"] == metrics["prior_decodes"]
    assert 0.0 <= keyframe_ate(first, scene) < 1.0  # metres, the scene is a few metres wide
    # journaled to a store (paged out as a run's coordinator is), with a census per batch
    paged, _ = replay(tmp_path / "calls", config, tmp_path / "store", counted=True)
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("census:")]
    assert len(lines) == len(seconds) and f"{metrics['keyframes']} kf" in lines[-1]
    assert (tmp_path / "store" / "session.db").is_file()
    assert paged.stats.prior_decodes == metrics["prior_decodes"]
