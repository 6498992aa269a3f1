"""A finished two-agent run of the real pipeline on a tiny synthetic scene: what the export
tests read."""

from __future__ import annotations

from pathlib import Path

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.runtime.pipeline import PriorSpec, run

WIDTH, HEIGHT, FRAMES = 64, 48, 12
# short global solves keep the run fast (as tests/runtime/test_processes.py); the easy
# simulated prior makes the two agents meet, so the graph has inter-agent edges
OVERRIDES = [
    f"input.long_side={WIDTH}",
    "simulated_prior.model=easy",
    "global_ba.max_iters_stream=5",
    "global_ba.max_iters_cleanup=10",
    "global_ba.cleanup_passes=1",
]


def tiny_run(root: Path, overrides: list[str]) -> Path:
    """Synthesize the scene under ``root/scene`` and run it into ``root/run``."""
    (root / "scene").mkdir()
    synthesize(
        root / "scene",
        agents=2,
        seed=0,
        overlap=0.5,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
    )
    run(
        [root / "scene" / "agent_0", root / "scene" / "agent_1"],
        root / "run",
        apply_overrides(Config(), overrides),
        PriorSpec("simulated"),
    )
    return root / "run"
