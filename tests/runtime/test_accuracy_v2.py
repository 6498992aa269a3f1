"""Two agents merged into one map on the hardest simulated prior (``v2``, issue 37) with the
default configuration: the centralized cell of benchmarks/robustness.py in small.

The scene and configuration are tests/conftest.py's ``v2_case``: the ``room`` family at
160x120, ``input.long_side`` 160, every threshold the default; each agent runs 24 frames
(12 processed) of a path laid out for 100, and they meet on the shared stretch. The
easy-prior end-to-end tests (test_pipeline.py, test_processes.py) check the runtime, which
needs exact, repeatable values; test_meeting_realistic.py checks the realistic prior's
focal lengths. The accuracy bound on the hardest prior is here.

Measured at commit time (scene seed 1, ATE % of an agent's mean path of ``scene.json``,
every frame tracked, one map): merged, prior seed 0 / 1 / 2: 0.48 / 0.39 / 0.58 %; per
agent 0.28 and 0.29 / 0.31 and 0.24 / 0.50 and 0.34 %. The bounds are about twice seed 0's.
"""

from __future__ import annotations

import json

import pytest

from como3r.runtime.pipeline import PriorSpec, run

# no test here reads a figure of its run's report.html (tests/conftest.py)
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("undrawn_report_figures")]


@pytest.fixture(scope="module")
def merged(v2_case, tmp_path_factory) -> tuple[dict, float]:
    """``metrics.json`` of the run and the mean ground-truth path of an agent [m]."""
    agents, path, config = v2_case(agents=2, frames=24, scene_seed=1, prior_seed=0)
    out = tmp_path_factory.mktemp("v2_centralized") / "out"
    run(agents, out, config, PriorSpec("simulated"))
    return json.loads((out / "metrics.json").read_text()), path


def test_two_agents_track_their_frames_on_the_v2_prior(merged) -> None:
    metrics, _ = merged
    assert metrics["prior"]["model"] == "v2"
    for agent in metrics["agents"]:
        assert agent["frames"] == 12
        assert agent["tracked_fraction"] >= 0.95, agent


def test_two_agents_share_one_map_within_one_percent_of_the_path(merged) -> None:
    metrics, path = merged
    assert metrics["components"] == [[0, 1]]
    assert metrics["coordinator"]["gauge_syncs"] == 1
    (map_,) = metrics["ate"]["merged_components"]
    assert map_["agents"] == [0, 1]
    assert map_["ate"]["rmse"] <= 0.010 * path, (map_["ate"]["rmse"], path)
    for agent in metrics["ate"]["agents"]:
        assert agent["ate"]["rmse"] <= 0.006 * path, agent["ate"]
