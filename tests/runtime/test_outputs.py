"""Run outputs (runtime/outputs.py): loud tracking loss, bandwidth per keyframe."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from como3r.config import Config
from como3r.frontend.agent import FrontendStats
from como3r.runtime.outputs import tracking_warnings


def _agent(agent: int, frames: int, lost: list[int], relocalized: int = 0) -> SimpleNamespace:
    stats = FrontendStats(
        frames=frames,
        tracked=frames - len(lost),
        lost=len(lost),
        relocalized=relocalized,
        lost_frames=lost,
    )
    return SimpleNamespace(agent=agent, stats=stats)


def test_an_agent_tracked_on_fewer_than_95_percent_of_frames_is_named(caplog) -> None:
    agents = [_agent(0, 40, [12]), _agent(1, 40, [10, 12, 14], relocalized=1)]
    with caplog.at_level(logging.WARNING):
        warnings = tracking_warnings(agents)
    assert len(warnings) == 1  # 39 of 40 is 97.5 %, 37 of 40 is 92.5 %
    assert "agent 1" in warnings[0] and "37 of 40" in warnings[0]
    assert "10, 12, 14" in warnings[0] and "1 relocalized" in warnings[0]
    assert "agent 1 was tracked on 37 of 40" in caplog.text


def test_long_lists_of_lost_frames_are_shortened() -> None:
    [warning] = tracking_warnings([_agent(2, 100, list(range(50, 100)))])
    assert "50 of 100" in warning and warning.endswith("69, ...")
    assert tracking_warnings([_agent(3, 0, [])]) == []


def test_notes_name_the_final_folder_not_the_staging_one(tmp_path) -> None:
    from como3r.runtime.outputs import in_final_folder

    staging = tmp_path / "run.partial"
    text = f"{staging / 'trajectories' / 'agent_0.txt'}: 1 pose, at least 3 needed"
    assert in_final_folder(text, staging) == (
        f"{tmp_path / 'run' / 'trajectories' / 'agent_0.txt'}: 1 pose, at least 3 needed"
    )


def test_bandwidth_is_per_keyframe_against_the_raw_image() -> None:
    from como3r.runtime.outputs import bandwidth

    row = bandwidth({"KeyframeMessage": 9000, "FrameDone": 600}, 3, (40, 50))
    assert row["image_bytes"] == 6000 and row["bytes_sent"] == 9600
    assert row["bytes_per_keyframe"] == 3200 and row["per_keyframe_over_image"] == 3200 / 6000
    assert row["bytes_per_keyframe_by_type"] == {"FrameDone": 200, "KeyframeMessage": 3000}
    assert row["keyframe_message_bytes_by_part"] is None  # not measured
    parts = bandwidth({"KeyframeMessage": 9000}, 3, (40, 50), {"tokens": 2000.0})
    assert parts["keyframe_message_bytes_by_part"] == {"tokens": 2000.0}
    empty = bandwidth({}, 0, (40, 50))
    assert empty["bytes_per_keyframe"] is None and empty["per_keyframe_over_image"] is None


def test_keyframe_bandwidth_reads_what_each_agent_sent_the_coordinator() -> None:
    from como3r.runtime.outputs import keyframe_bandwidth

    keyframe = SimpleNamespace(colors=np.zeros((6, 8, 3), np.uint8))
    runtime = {
        "agents": [
            {"agent": 0, "bytes_from_agent": {"KeyframeMessage": 1440}, "keyframes_received": 2},
            {"agent": 1, "bytes_from_agent": {"AgentFailed": 50}, "keyframes_received": 0},
        ]
    }
    results = [
        SimpleNamespace(agent=0, keyframes=[keyframe, keyframe]),
        SimpleNamespace(agent=0, keyframes=[]),  # a later map segment of agent 0
        SimpleNamespace(agent=1, keyframes=[]),
    ]
    rows = keyframe_bandwidth(runtime, results)
    assert [r["agent"] for r in rows] == [0, 1]
    assert rows[0]["per_keyframe_over_image"] == 720 / 144
    assert rows[1]["bytes_per_keyframe"] is None
    assert keyframe_bandwidth(None, results) is None


def _keyframes(count: int, seed: int) -> list[SimpleNamespace]:
    """Keyframes of 6x8 random pointmaps near the origin (overlapping voxels), a few
    pixels under the confidence threshold."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    keyframes = []
    for _ in range(count):
        confidence = 1.0 + 2.0 * torch.rand(6, 8, generator=gen)
        keyframes.append(
            SimpleNamespace(
                T_WC=torch.tensor([0.1, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0, 1.0]),
                X_hat=torch.rand(6, 8, 3, generator=gen),
                colors=np.full((6, 8, 3), seed, np.uint8),
                mean_confidence=lambda c=confidence: c,
            )
        )
    return keyframes


def test_the_map_is_written_a_keyframe_at_a_time_as_it_was_whole(tmp_path) -> None:
    """fused_map yields a keyframe at a time and write_ply_pieces streams them (bounded
    memory): with a voxel size, the first point of each voxel over all keyframes is kept,
    as one pass over the whole map did."""
    from como3r.io.ply import read_ply, write_ply_pieces
    from como3r.runtime.outputs import fused_map

    keyframes = {0: _keyframes(5, 0), 1: _keyframes(4, 1)}
    whole = [np.concatenate(parts) for parts in zip(*fused_map(keyframes, 1.5))]
    assert whole[0].shape[0] < 9 * 48 and set(whole[2]) == {0, 1}
    _, first = np.unique(np.floor(whole[0] / 0.25).astype(np.int64), axis=0, return_index=True)
    first.sort()
    assert 0 < len(first) < whole[0].shape[0] // 3  # most voxels are met again
    count = write_ply_pieces(tmp_path / "map.ply", fused_map(keyframes, 1.5, voxel_size=0.25))
    vertices = read_ply(tmp_path / "map.ply")
    assert count == len(vertices) == len(first)
    np.testing.assert_array_equal(np.stack([vertices[k] for k in "xyz"], 1), whole[0][first])
    np.testing.assert_array_equal(vertices["agent_id"], whole[2][first])
    assert not (tmp_path / "map.ply.body").exists()


def test_first_point_per_voxel_over_pieces_of_any_extent() -> None:
    """_FirstPerVoxel over pieces (some empty, cells millions of voxels from the origin)
    keeps exactly the first point of every voxel of the whole cloud."""
    from como3r.runtime.map_points import _FirstPerVoxel

    rng = np.random.default_rng(1)
    pieces = [
        rng.normal(size=(int(rng.integers(0, 300)), 3)) * [1.0, 1.0, 1e6 if k % 3 else 1]
        for k in range(30)
    ]
    pieces.insert(5, np.zeros((0, 3)))
    voxels, kept, offset = _FirstPerVoxel(0.25), [], 0
    for piece in pieces:
        kept.append(voxels.new_points(piece) + offset)
        offset += len(piece)
    cloud = np.concatenate(pieces)
    _, first = np.unique(np.floor(cloud / 0.25).astype(np.int64), axis=0, return_index=True)
    np.testing.assert_array_equal(np.concatenate(kept), np.sort(first))
    assert 0 < len(first) < len(cloud)


def test_the_map_is_thinned_by_a_voxel_relative_to_its_depth_and_says_so(tmp_path) -> None:
    """write_map: visualization.map_voxel times the median of the keyframes' median ranges
    (scaled by their poses' s), the same map at any scale; 0 keeps every confident point;
    voxel_size_m, where set, wins; metrics' map counts both."""
    from como3r.config import apply_overrides
    from como3r.geometry.units import median_range
    from como3r.io.ply import read_ply
    from como3r.runtime.outputs import write_map

    def frontends(scale: float) -> list[SimpleNamespace]:
        agents = [SimpleNamespace(agent=a, keyframes=_keyframes(4, a)) for a in (0, 1)]
        for agent in agents:
            for kf in agent.keyframes:
                kf.X_hat = kf.X_hat / scale  # the same world points at another pose scale
                kf.T_WC = kf.T_WC.clone()
                kf.T_WC[7] = scale
        return agents

    config = apply_overrides(Config(), ["visualization.map_voxel=0.4"])
    agents = frontends(1.0)
    confident = sum(int((kf.mean_confidence() > 1.5).sum()) for a in agents for kf in a.keyframes)
    ranges = [
        float(median_range(kf.X_hat, kf.mean_confidence() > 1.5))
        for a in agents
        for kf in a.keyframes
    ]
    written = write_map(tmp_path, agents, config)
    assert written["confident_points"] == confident
    assert written["voxel"] == pytest.approx(0.4 * float(np.median(ranges)), rel=1e-6)
    assert 0 < written["points"] < confident // 2
    assert len(read_ply(tmp_path / "map.ply")) == written["points"]
    twice = write_map(tmp_path, frontends(2.0), config)
    assert twice["points"] == written["points"]
    assert twice["voxel"] == pytest.approx(written["voxel"], rel=1e-5)
    every = write_map(tmp_path, agents, apply_overrides(config, ["visualization.map_voxel=0"]))
    assert every == {"points": confident, "confident_points": confident, "voxel": 0.0}
    metres = apply_overrides(config, ["visualization.voxel_size_m=0.01"])
    assert write_map(tmp_path, agents, metres)["voxel"] == 0.01
