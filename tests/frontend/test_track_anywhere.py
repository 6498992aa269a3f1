"""One agent on the realistic simulated prior with the default configuration, at two scene
scales and two image sizes (the small in-suite subset of benchmarks/robustness.py).

The only setting chosen here is ``input.long_side``, equal to the rendered width so the
suite stays within minutes on two CPU cores; every threshold is the default. The scene
turns 20 deg per processed frame. Measured at commit time (tracked / processed frames, ATE %
of path): 0.1x 96 px 20/20, 1.39 %; 1x 96 px 19/20, 1.75 %; 0.1x 160 px 20/20, 1.36 %; 1x
160 px 19/20, 1.39 % (the paper's uncalibrated mode, ``tracking.self_calibration=false``:
8.1, 7.1, 8.6, 7.5 %). The prior's default seed happens to draw a first frame whose focal
length is nearly right; seeds 1 and 2 give 1.8-3.0 % here. The bounds are about twice the
default's; the issue's goal (<= 1 %) is met on slower motion (3.6 deg per frame: 0.4-1.35 %
over three prior seeds, frontend.calibration), not yet here.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.keyframe_linking import LOOP_MAX_ROTATION_DEG
from como3r.frontend.pairs import PairLink, directed_matches
from como3r.geometry.lie import sim3_compose
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3
from como3r.prior.simulated import SimulatedPrior

pytestmark = pytest.mark.slow

FRAMES = 40


def _track(
    root,
    process_frames,
    scale: float,
    width: int,
    overrides: tuple[str, ...] = (),
    preset: str = "default",
    scene_seed: int = 0,
    frames: int = FRAMES,
    loop_frames: int | None = None,
) -> tuple[float, list[str], AgentFrontend]:
    """One agent's run on a fresh scene: (ATE as a fraction of the path, outcomes, front-end)."""
    synthesize(
        root,
        agents=1,
        seed=scene_seed,
        overlap=0.2,
        frames=frames,
        preset=preset,
        width=width,
        height=width * 3 // 4,
        progress=None,
        scale=scale,
        loop_frames=loop_frames,
    )
    agent = open_agent(root / "agent_0")
    config = apply_overrides(Config(), [f"input.long_side={width}", *overrides])
    assert config.simulated_prior.model == "realistic"
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(
        frontend, agent, width, range(0, agent.num_frames, config.input.subsample)
    )
    indices, _, T_WC = frontend.trajectory()
    gt = agent.groundtruth.T_WC[indices, :3]
    est = T_WC[:, :3].double()
    path = float((gt[1:] - gt[:-1]).norm(dim=-1).sum())
    return umeyama_rmse(umeyama_sim3(est, gt), est, gt) / path, outcomes, frontend


@pytest.mark.parametrize("scale", [0.1, 1.0])
@pytest.mark.parametrize("width", [96, 160])
def test_default_configuration_tracks_on_the_realistic_prior(
    tmp_path, process_frames, scale: float, width: int
) -> None:
    ate, outcomes, frontend = _track(tmp_path, process_frames, scale, width)
    tracked = sum(o != "lost" for o in outcomes)
    assert tracked >= 0.95 * len(outcomes), outcomes
    assert len(frontend.keyframes) < len(outcomes)
    assert ate <= 0.035, (ate, outcomes)


def test_self_calibration_beats_the_papers_uncalibrated_mode(tmp_path, process_frames) -> None:
    paper, _, frontend = _track(
        tmp_path, process_frames, 1.0, 96, ("tracking.self_calibration=false",)
    )
    assert frontend.stats.estimated_focal is None
    # measured: 7.2 % (paper's mode) against 1.6-2.0 % (the default, previous test)
    assert paper > 0.035, paper


def test_a_frame_the_motion_outran_becomes_a_keyframe_late(tmp_path, process_frames) -> None:
    """With this draw of the prior's errors, frame 2 still overlaps keyframe 0 by 36 % (no
    keyframe due) and frame 4 by 4 %: without the late promotion of frame 2 the agent lost
    track at frame 4 and tracked 4 of 20 frames (measured)."""
    ate, outcomes, frontend = _track(tmp_path, process_frames, 1.0, 96, ("simulated_prior.seed=1",))
    assert frontend.stats.late_keyframes >= 1
    # a promoted frame is where its keyframe is (it was tracked before the camera settled:
    # its first solution, relative to the previous keyframe, must not come back)
    indices, _, T_WC = frontend.trajectory()
    row = {int(i): k for k, i in enumerate(indices)}
    for kf in frontend.keyframes:
        torch.testing.assert_close(T_WC[row[kf.frame_index]], kf.T_WC.to(T_WC))
    assert sum(o != "lost" for o in outcomes) >= 0.95 * len(outcomes), outcomes
    assert ate <= 0.02, ate  # measured 0.96 % (2.2 % while its first solution came back)


def test_a_new_keyframe_is_not_pulled_off_by_a_failed_decode_of_its_edge(
    tmp_path, process_frames
) -> None:
    """The fast family of benchmarks/robustness.py (scene and prior seed 1, 24 frames of a
    loop laid out for 100) at 160x120. Frame 22 turns 16 deg from keyframe 14 and becomes a
    keyframe; tracking puts it 0.12 deg off, but the prior's decode (14, 22), the new
    sequential edge's other direction, is 4.1 deg off and its matches agree with their own
    pose at 0.23 (good directions here 0.67-0.84). Without the test of that direction
    (AgentFrontend._checked_direction) the local solve pulled keyframe 22 off and the ATE
    was 1.99 % of the path (1.18 % at 640x480 in the benchmark); with it 0.22 % (measured)."""
    ate, outcomes, frontend = _track(
        tmp_path,
        process_frames,
        1.0,
        160,
        ("simulated_prior.seed=1",),
        preset="fast",
        scene_seed=1,
        frames=24,
        loop_frames=100,
    )
    assert "lost" not in outcomes, outcomes
    assert [kf.frame_index for kf in frontend.keyframes][-2:] == [14, 22]
    assert ate <= 0.0045, ate
    assert frontend.stats.rejected_directions == 1  # that direction alone
    dropped = [e for e in frontend.edges if (e.i, e.j) == (4, 5)]
    assert len(dropped) == 1 and not bool(dropped[0].matches.valid.any())


def _turned(pose: torch.Tensor, axis: int, degrees: float) -> torch.Tensor:
    """``pose`` ``(8,)`` turned by ``degrees`` about its camera's ``axis`` (0 x, 1 y, 2 z)."""
    half = math.radians(degrees) / 2
    turn = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.cos(half), 1.0])
    turn[3 + axis] = math.sin(half)
    return sim3_compose(pose, turn.to(pose))


def test_a_loop_whose_pose_is_far_off_the_graph_is_not_added(tmp_path, process_frames) -> None:
    """A verified loop of look-alike places has a pose of its own that disagrees with the
    graph (benchmarks/robustness.py, prior v2, aliasing: keyframes 7 -> 10 matched two
    identical facades 88 deg off, and the local solve turned the map by 60 deg; ATE 12.5 %
    of the path in the front-end alone, 1.14 % without that loop). Here the last two
    keyframes of a short run, as a loop, agree with the graph; with the graph's pose of one
    of them turned, the same matches no longer do, in either direction. Turned by 150 deg
    about the optical axis or 60 deg about the vertical one, a solve from the graph's pose
    stopped where it started (LM found no step, or its step was below the tolerance: "0
    deg off") and the loop passed, as a look-alike loop did on the aliasing family's seed 1
    (keyframes 6 -> 10, 88.8 deg off, ATE 9.54 %): the gate also solves from the identity
    and takes the pose more of the matches agree with (measured: 147.5 and 58.1 deg)."""
    _, outcomes, frontend = _track(tmp_path, process_frames, 1.0, 96, frames=12)
    assert "lost" not in outcomes, outcomes
    kf = frontend.keyframes.last
    assert kf.kf_id >= 1
    partner = frontend.keyframes[kf.kf_id - 1]
    matching, q_min = frontend.config.matching, frontend.config.tracking.q_min
    link = PairLink(
        directed_matches(frontend.prior.decode(partner.encoding, kf.encoding), matching, q_min),
        directed_matches(frontend.prior.decode(kf.encoding, partner.encoding), matching, q_min),
    )
    assert frontend._loop_agrees(link, partner, kf)
    assert frontend._direction_turn(link.ji, kf, partner) <= LOOP_MAX_ROTATION_DEG
    for axis, degrees in ((2, 60.0), (2, 150.0), (1, 60.0)):
        turned = replace(partner, T_WC=_turned(partner.T_WC, axis, degrees))
        assert not frontend._loop_agrees(link, turned, kf), (axis, degrees)
        # the direction (kf, partner) is solved with its own roles: it sees the turn too
        assert frontend._direction_turn(link.ji, kf, turned) > LOOP_MAX_ROTATION_DEG
