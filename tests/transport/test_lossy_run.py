"""A small centralized run whose keyframes and refreshes cross the lossy wire (the compact
codings of :mod:`como3r.transport.codec_compact`, as between machines, and as every runtime
hands them to its coordinator: :mod:`como3r.runtime.ingest`) against the same run with that
coding taken out: the merged ATE within 2 %."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from como3r.config import Config, apply_overrides
from como3r.data.synth import synthesize
from como3r.frontend.packets import KeyframePacket
from como3r.runtime import pipeline
from como3r.runtime.pipeline import PriorSpec, run
from como3r.transport import codec

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]

# the settings of tests/runtime/test_pipeline.py: a fast, deterministic single-process run
OVERRIDES = [
    "input.long_side=128",
    "simulated_prior.model=easy",
    "global_ba.step_tol=1e-5",
    "global_ba.trigger_interval_edges=3",
    "global_ba.max_iters_stream=10",
    "global_ba.max_iters_cleanup=30",
]


def _merged_ate(out: Path) -> float:
    ate = json.loads((out / "metrics.json").read_text())["ate"]
    return float(ate["merged"]["ate"]["rmse"])


@pytest.mark.parametrize("calibration", ["self-calibrated", "uncalibrated"])
def test_merged_ate_across_the_lossy_wire_is_within_two_percent(
    tmp_path, monkeypatch, calibration
) -> None:
    """Uncalibrated (the paper's rays, not a pinhole camera's), the pointmaps' directions
    travel in full (:data:`~como3r.transport.codec_compact.OCT_BITS`)."""
    scene = tmp_path / "scene"
    scene.mkdir()
    synthesize(
        scene, agents=2, seed=1, overlap=0.2, frames=12, preset="default", width=128, height=96
    )
    agents = [scene / "agent_0", scene / "agent_1"]
    self_calibration = f"tracking.self_calibration={calibration == 'self-calibrated'}"
    config = apply_overrides(Config(), [*OVERRIDES, self_calibration])
    with monkeypatch.context() as exact_path:
        exact_path.setattr(pipeline, "received", lambda message, coordinator=None: message)
        run(agents, tmp_path / "exact", config, PriorSpec("simulated"))

    add, sent = pipeline.received, []

    def received_lossy(message: Any, coordinator: Any = None) -> Any:
        if isinstance(message, KeyframePacket):
            sent.append(len(codec.encode(message, lossy=True)))
        return add(message, coordinator)

    monkeypatch.setattr(pipeline, "received", received_lossy)
    run(agents, tmp_path / "lossy", config, PriorSpec("simulated"))
    assert len(sent) > 4  # every keyframe crossed the lossy wire
    exact, lossy = _merged_ate(tmp_path / "exact"), _merged_ate(tmp_path / "lossy")
    print(f"merged ATE exact {exact:.6f} lossy {lossy:.6f} ({(lossy - exact) / exact:+.3%})")
    assert abs(lossy - exact) <= 0.02 * exact, (lossy, exact)
