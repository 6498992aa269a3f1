"""An agent's map segments joined for the outputs: which are shown, how their keyframes are
numbered, and the coordinator's graph stated in agent ids."""

from __future__ import annotations

import torch

from como3r.frontend.agent import FrontendStats
from como3r.runtime.results import (
    AgentResult,
    EdgeView,
    KeyframeView,
    MatchFraction,
    SegmentedCoordinator,
    SegmentedResult,
    SegmentPlace,
    output_places,
)


def _result(agent: int, frames: list[int]) -> AgentResult:
    result = AgentResult(agent)
    for k, frame in enumerate(frames):
        pose = torch.zeros(8, dtype=torch.float64)
        pose[0], pose[6], pose[7] = frame, 1.0, 1.0
        result.keyframes.append(
            KeyframeView(k, frame, 0.1 * frame, pose, graph=None, agent=agent, graph_kf_id=k)
        )  # poses only
    result.edges = [
        EdgeView(k - 1, k, "sequential", MatchFraction(0.5)) for k in range(1, len(frames))
    ]
    return result


def test_an_agent_shows_its_segments_in_the_component_with_most_of_its_keyframes() -> None:
    # agent 1 ran three processes: segments 1, 2 (merged with agent 0) and 3 (alone)
    components = [[0, 1, 2], [3]]
    segments = [(0, 0, 5), (1, 1, 2), (2, 1, 4), (3, 1, 3)]
    places = output_places(components, segments)
    assert places == {0: SegmentPlace(0, 0), 1: SegmentPlace(1, 0), 2: SegmentPlace(1, 2)}
    # a tie goes to the earliest segment's component
    assert set(output_places([[0], [1]], [(0, 0, 2), (1, 0, 2)])) == {0}
    # one segment per agent: everything, as it is
    assert output_places([[0, 1]], [(0, 0, 3), (1, 1, 4)]) == {
        0: SegmentPlace(0, 0),
        1: SegmentPlace(1, 0),
    }


def test_segments_join_into_one_trajectory_with_keyframes_numbered_on() -> None:
    first, second = _result(1, [0, 2]), _result(2, [6, 8, 10])
    joined = SegmentedResult(1, [first, second], FrontendStats())
    assert [kf.kf_id for kf in joined.keyframes] == [0, 1, 2, 3, 4]
    assert [(e.i, e.j) for e in joined.edges] == [(0, 1), (2, 3), (3, 4)]
    assert [kf.kf_id for kf in second.keyframes] == [0, 1, 2]  # the segment is unchanged
    frames, stamps, poses = joined.trajectory()
    assert frames.tolist() == [0, 2, 6, 8, 10] and poses[:, 0].tolist() == [0, 2, 6, 8, 10]
    alone = SegmentedResult(0, [first], FrontendStats())
    assert alone.keyframes[0] is first.keyframes[0]  # one segment: the identity


class _Coordinator:
    """What SegmentedCoordinator reads of a coordinator whose agents are segments 0..2."""

    pre_refinement = {0: ["a"], 1: ["b"], 2: ["c"]}

    def components(self) -> list[list[int]]:
        return [[0, 1, 2], [3]]

    def graph_document(self) -> dict:
        return {
            "keyframes": [{"agent": 2, "keyframe": 0}, {"agent": 3, "keyframe": 0}],
            "edges": [
                {"type": "inter", "from": [0, 4], "to": [2, 1]},
                {"type": "sequential", "from": [3, 0], "to": [3, 1]},
            ],
            "candidates": [{"from": [1, 1], "to": [2, 0], "status": "admitted"}],
            "gauge_events": [
                {"anchor_component": 0, "moved_agents": [2], "edges": [[[0, 4], [2, 1]]]}
            ],
            "components": self.components(),
        }

    def metrics(self) -> dict:
        return {
            "components": self.components(),
            "alternation": [{"agents": [0, 1, 2]}],
            "gauge_events": [],
            "focal_lengths": {"1": 300.0, "2": 310.0, "3": 200.0},
        }


def test_the_coordinator_graph_is_stated_in_agent_ids() -> None:
    places = {0: SegmentPlace(0, 0), 1: SegmentPlace(1, 0), 2: SegmentPlace(1, 2)}
    view = SegmentedCoordinator(_Coordinator(), places)
    assert view.components() == [[0, 1]]
    document = view.graph_document()
    assert document["keyframes"] == [{"agent": 1, "keyframe": 2}]
    assert [(e["from"], e["to"]) for e in document["edges"]] == [([0, 4], [1, 3])]
    assert [(c["from"], c["to"]) for c in document["candidates"]] == [([1, 1], [1, 2])]
    assert document["gauge_events"] == [
        {"anchor_component": 0, "moved_agents": [1], "edges": [[[0, 4], [1, 3]]]}
    ]
    metrics = view.metrics()
    assert metrics["alternation"] == [{"agents": [0, 1]}]
    assert metrics["focal_lengths"] == {"1": 300.0}
    assert view.pre_refinement == {0: ["a"], 1: ["b", "c"]}
