"""The single-agent front-end end to end on a small synthetic scene (simulated prior)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import PoseUpdate
from como3r.geometry.lie import sim3_compose, sim3_exp
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3
from como3r.prior.ground_truth import GroundTruth
from como3r.prior.retrieval import RetrievalDatabase
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.pipeline import _colors

WIDTH, HEIGHT, FRAMES = 128, 96, 24


@pytest.fixture(scope="module")
def tracked(tmp_path_factory, process_frames):
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=5,
        overlap=0.2,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
        progress=None,
    )
    agent = open_agent(root / "agent_0")
    # the easy simulated prior: the tests below check the front-end's bookkeeping (keyframe
    # count, anchors, pose updates) on a ring laid out for these 24 frames, about 30 deg per
    # processed frame, where the realistic and v2 priors make every processed frame a
    # keyframe and relocalize one (measured ATE 1.24 and 1.48 % of the path, easy 0.55 %).
    # Accuracy on the v2 prior at the benchmark's motion: test_accuracy_v2.py.
    config = apply_overrides(Config(), [f"input.long_side={WIDTH}", "simulated_prior.model=easy"])
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(
        frontend, agent, WIDTH, range(0, agent.num_frames, config.input.subsample)
    )
    return agent, frontend, outcomes


def test_single_agent_ate_below_one_percent_of_path(tracked) -> None:
    agent, frontend, outcomes = tracked
    indices, _, T_WC = frontend.trajectory()
    assert len(indices) == sum(o != "lost" for o in outcomes)
    gt = agent.groundtruth.T_WC[indices, :3]
    est = T_WC[:, :3].double()
    path_length = float((gt[1:] - gt[:-1]).norm(dim=-1).sum())
    ate = umeyama_rmse(umeyama_sim3(est, gt), est, gt)
    assert ate <= 0.01 * path_length, (ate, path_length)


def test_keyframe_count_is_sensible(tracked) -> None:
    _, frontend, outcomes = tracked
    assert "lost" not in outcomes
    assert 2 <= len(frontend.keyframes) <= len(outcomes) // 2 + 1
    assert frontend.stats.keyframes == len(frontend.keyframes)
    kinds = {e.kind for e in frontend.edges}
    assert "sequential" in kinds


def test_frames_follow_their_anchor_keyframe(tracked) -> None:
    _, frontend, _ = tracked
    _, _, before = frontend.trajectory()
    packets = list(frontend.drain_new_keyframes())
    assert [p.kf_id for p in packets] == list(range(len(frontend.keyframes)))
    assert list(frontend.drain_new_keyframes()) == []
    shift = sim3_exp(torch.tensor([0.5, -0.2, 0.1, 0.0, 0.05, 0.0, 0.1]))
    last = len(frontend.keyframes) - 1
    moved = sim3_compose(shift[None], frontend.keyframes.poses()[:last])
    frontend.apply_pose_update(PoseUpdate(0, torch.arange(last), moved, "global_ba"))
    _, _, after = frontend.trajectory()
    expected = sim3_compose(shift[None].to(before), before)
    # every frame, those anchored on the keyframe missing from the update included, moved
    # with the update's correction
    assert torch.allclose(after, expected, atol=1e-4)


class _SkyAtFrame:
    """Ground truth in which the camera shows only sky at one frame (never seen before)."""

    def __init__(self, index: int, source: AgentFolderTruth) -> None:
        self.index, self.source = index, source

    def truth(self, agent: int, index: int) -> GroundTruth:
        truth = self.source.truth(agent, index)
        if index != self.index:
            return truth
        return replace(
            truth, depth=torch.zeros_like(truth.depth), surface=torch.full_like(truth.surface, -1.0)
        )


@pytest.fixture(scope="module")
def long_agent(tmp_path_factory):
    """A 60-frame agent of the default scene (every test below reads its first frames)."""
    root = tmp_path_factory.mktemp("long")
    synthesize(
        root,
        agents=1,
        seed=5,
        overlap=0.2,
        frames=60,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
        progress=None,
    )
    return open_agent(root / "agent_0")


def _run_first_frames(
    agent,
    count: int,
    overrides: list[str] = (),
    sky_at: int | None = None,
    patch_decode=None,
    patch_track=None,
) -> tuple[AgentFrontend, dict[int, str]]:
    """Every other one of the first ``count`` frames through a front-end on the easy
    simulated prior (these tests need its precision: which frame is lost, relocalized or a
    keyframe, and exact counts; accuracy on the v2 prior is test_accuracy_v2.py's),
    optionally with only sky at frame
    ``sky_at``, the prior's decode wrapped by ``patch_decode(decode)`` and the tracker's
    ``track`` by ``patch_track(track)``."""
    config = apply_overrides(
        Config(), [f"input.long_side={WIDTH}", "simulated_prior.model=easy", *overrides]
    )
    truth = AgentFolderTruth({0: agent}, config.input.long_side)
    prior = SimulatedPrior(
        config.simulated_prior, truth if sky_at is None else _SkyAtFrame(sky_at, truth)
    )
    if patch_decode is not None:
        prior.decode = patch_decode(prior.decode)
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    if patch_track is not None:
        frontend.tracker.track = patch_track(frontend.tracker.track)
    outcomes = {}
    for i in range(0, count, 2):
        frame = agent.load_frame(i)
        view = make_view(frame, 0, WIDTH)
        outcomes[i] = frontend.process(view, frame.timestamp, _colors(view))
    return frontend, outcomes


def test_a_keyframe_is_quantised_once(long_agent, monkeypatch) -> None:
    """A keyframe's loop query and its indexing share one nearest-centroid search: at the
    released codebook's size that search is the bulk of both (0.35 s of a CPU core)."""
    searched = []
    assign = RetrievalDatabase._assign

    def counted(self, descriptors, multiple_assignment, *device):
        searched.append(multiple_assignment)
        return assign(self, descriptors, multiple_assignment, *device)

    monkeypatch.setattr(RetrievalDatabase, "_assign", counted)
    frontend, outcomes = _run_first_frames(long_agent, 16)
    assert "lost" not in outcomes.values() and frontend.config.loop_closure
    assert len(frontend.keyframes) >= 3
    packets = list(frontend.drain_new_keyframes())
    # one search each (two before), none again for the packets: their retrieval travels
    # to the coordinator aggregated from the words of that search
    assert len(searched) == len(frontend.keyframes)
    database = frontend.database
    for packet in packets:
        assert packet.retrieval_words is None
        expected = database.aggregate(frontend.keyframes[packet.kf_id].retrieval[0])
        assert packet.retrieval.codebook_id == expected.codebook_id == database.codebook_id
        for name in ("query_words", "query_bits", "build_words", "build_bits"):
            np.testing.assert_array_equal(getattr(packet.retrieval, name), getattr(expected, name))


def test_lost_frame_is_reported_and_tracking_relocalizes(long_agent) -> None:
    frontend, outcomes = _run_first_frames(long_agent, 8, sky_at=2)
    assert outcomes[2] == "lost"
    assert frontend.stats.lost_frames == [2]
    assert outcomes[4] == "relocalized"
    assert outcomes[6] in ("tracked", "keyframe")
    indices, _, _ = frontend.trajectory()
    assert indices.tolist() == [0, 4, 6]


def test_tracking_resumes_on_the_current_keyframe_under_the_relocalization_bar(long_agent) -> None:
    # the relocalization bar out of reach: only the current keyframe, on tracking's own
    # tests, can take the frame after the loss (before, the agent stayed lost)
    frontend, outcomes = _run_first_frames(
        long_agent, 8, ["tracking.reloc_match_fraction=1.0"], sky_at=2
    )
    assert outcomes[2] == "lost"
    assert outcomes[4] == "relocalized"
    assert frontend.stats.relocalized == 1
    assert outcomes[6] in ("tracked", "keyframe")
    assert "loop" not in {e.kind for e in frontend.edges}
    assert frontend.trajectory()[0].tolist() == [0, 4, 6]


def test_a_frame_the_prior_fails_on_with_the_current_keyframe_takes_a_recent_one(
    long_agent,
) -> None:
    """The prior fails grossly on one pair (frame 8, current keyframe frame 6: a confident
    prediction with a wrong pose); frame 8 still matches keyframe frame 0 on tracking's own
    tests, which a recent keyframe needs, not the relocalization bar (out of reach here).
    Before, the frame was lost (a 640x480 room of benchmarks/robustness.py: 11/12)."""

    def fail_frame_8_with_frame_6(decode):
        def patched(enc_i, enc_j):
            pred = decode(enc_i, enc_j)
            if {enc_i.index, enc_j.index} != {8, 6}:
                return pred
            return replace(pred, X_ji=pred.X_ji.flip(0))

        return patched

    frontend, outcomes = _run_first_frames(
        long_agent,
        12,
        ["tracking.reloc_match_fraction=1.0"],
        patch_decode=fail_frame_8_with_frame_6,
    )
    assert [kf.frame_index for kf in frontend.keyframes][:2] == [0, 6]
    assert outcomes[8] == "relocalized" and outcomes[10] in ("tracked", "keyframe")
    assert frontend.stats.lost_frames == []
    assert "loop" in {e.kind for e in frontend.edges}
    assert frontend.trajectory()[0].tolist() == [0, 2, 4, 6, 8, 10]


def test_a_first_frame_without_geometry_is_lost_and_the_next_starts_the_map(long_agent) -> None:
    def behind_the_camera_at_frame_0(decode):
        # a prediction with nothing in front of the camera: self-calibration cannot start
        def patched(enc_i, enc_j):
            pred = decode(enc_i, enc_j)
            if enc_i.index != 0:
                return pred
            return replace(pred, X_ii=pred.X_ii * torch.tensor([1.0, 1.0, -1.0]))

        return patched

    frontend, outcomes = _run_first_frames(long_agent, 6, patch_decode=behind_the_camera_at_frame_0)
    assert outcomes[0] == "lost" and outcomes[2] == "keyframe"
    assert outcomes[4] in ("tracked", "keyframe")
    assert frontend.stats.lost_frames == [0]
    assert frontend.keyframes[0].frame_index == 2


def _turned_relocalizations(frames: set[int]):
    """A ``patch_track`` under which every relocalization attempt (an unfused track) of
    ``frames`` gives the frame's pose turned by 150 deg about its optical axis: a look-alike
    place, self-consistent, that tracking's own tests pass."""
    turn = torch.tensor(
        [0.0, 0.0, 0.0, 0.0, 0.0, math.sin(math.radians(75)), math.cos(math.radians(75)), 1.0]
    )

    def patch(track):
        def patched(enc, keyframe, T_init, fuse=True):
            result = track(enc, keyframe, T_init, fuse)
            if fuse or enc.index not in frames or not result.ok:
                return result
            return replace(result, T_kf=sim3_compose(result.T_kf, turn.to(result.T_kf)))

        return patched

    return patch


def test_a_relocalization_the_motion_does_not_allow_is_held_back(long_agent) -> None:
    """Lost at frame 8 (only sky), frame 10 relocalizes 150 deg off the last tracked frame's
    pose, 4 frames earlier, which the camera's turn rate does not allow (benchmarks/
    robustness.py, prior v2, aliasing at long side 512: a look-alike facade 44 deg off, ATE
    5.51 % of the path): it is held back and lost; frame 12, whose relocalization the motion
    allows, refutes it."""
    frontend, outcomes = _run_first_frames(
        long_agent, 14, sky_at=8, patch_track=_turned_relocalizations({10})
    )
    assert [outcomes[i] for i in (8, 10, 12)] == ["lost", "lost", "relocalized"]
    assert frontend.stats.lost_frames == [8, 10]
    indices, _, T_WC = frontend.trajectory()
    assert 10 not in indices.tolist()
    gt = long_agent.groundtruth.T_WC
    est = T_WC[:, :3].double()
    truth = gt[indices, :3]
    ate = umeyama_rmse(umeyama_sim3(est, truth), est, truth)
    path_length = float((truth[1:] - truth[:-1]).norm(dim=-1).sum())
    assert ate <= 0.01 * path_length, (ate, path_length)


def test_a_held_relocalization_confirmed_by_the_next_frame_is_taken(long_agent) -> None:
    """As above, but frame 12 relocalizes where frame 10's held pose and the motion since
    allow (a camera carried to a mapped place; benchmarks/robustness.py, prior v2, revisit:
    the path jumps 108 deg): frame 10, lost when processed, is placed as it relocalized after
    all, and frame 12 follows it."""
    frontend, outcomes = _run_first_frames(
        long_agent, 14, sky_at=8, patch_track=_turned_relocalizations({10, 12})
    )
    assert [outcomes[i] for i in (8, 10)] == ["lost", "lost"]
    assert outcomes[12] != "lost"
    assert frontend.stats.lost_frames == [8] and frontend.stats.lost == 1
    indices = frontend.trajectory()[0].tolist()
    assert indices[-2:] == [10, 12]
    assert frontend.stats.tracked == len(indices)


def test_the_motion_test_allows_what_the_turn_rate_and_the_time_allow(long_agent) -> None:
    """A pose at the last tracked frame's passes; turned by 150 deg one frame later it does
    not (a relocalization there is held back); given a minute it does."""
    frontend, outcomes = _run_first_frames(long_agent, 8)
    assert "lost" not in outcomes.values()
    last = frontend.records[-1]
    pose = frontend._record_pose(last)
    turn = torch.tensor(
        [0.0, 0.0, 0.0, 0.0, 0.0, math.sin(math.radians(75)), math.cos(math.radians(75)), 1.0]
    )
    turned = sim3_compose(pose, turn.to(pose))
    step = last.timestamp - frontend.records[-2].timestamp
    assert frontend._turn_allowed(pose, last.timestamp + step)
    assert not frontend._turn_allowed(turned, last.timestamp + step)
    assert frontend._turn_allowed(turned, last.timestamp + 60.0)
