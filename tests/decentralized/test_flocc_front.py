"""Place recognition, registration and ratio confidence (decentralized/place_recognition.py,
registration.py, confidence.py; F-Sec. III-A, III-B, F-Eq. 1-2)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from como3r.config import RetrievalConfig
from como3r.config_decentralized import DecentralizedConfig, RegistrationConfig, check_config
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.decentralized.confidence import accept_loop, correspondence_ratio, loop_probability
from como3r.decentralized.keyframes import frame_odometry, select_keyframes
from como3r.decentralized.matching import reciprocal_matches
from como3r.decentralized.place_recognition import PlaceRecognizer, candidate_pairs
from como3r.decentralized.registration import (
    Registrar,
    odometry_neighbour,
    ransac_similarity,
)
from como3r.errors import ConfigError
from como3r.geometry.lie import quat_to_matrix, sim3_act, sim3_compose, sim3_inverse, so3_exp
from como3r.prior.base import EncodingRecord
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.prior.retrieval import RetrievalDatabase
from como3r.prior.simulated import SimulatedPrior
from como3r.prior.simulated_keys import generator

# ----------------------------------------------------------------------------- confidence


def test_ratio_and_logistic_confidence():
    assert correspondence_ratio(150, 300) == 0.5
    assert correspondence_ratio(10, 0) == 0.0
    with pytest.raises(ValueError):
        correspondence_ratio(-1, 3)
    assert loop_probability(1.0, 5.0) == pytest.approx(0.5)
    assert loop_probability(1.4, 5.0) == pytest.approx(1 / (1 + math.exp(-2.0)))
    assert loop_probability(0.0, 1e4) == pytest.approx(0.0, abs=1e-300)
    assert loop_probability(5.0, 1e4) == pytest.approx(1.0)
    assert accept_loop(0.3, 0.3) and not accept_loop(0.29, 0.3)


# ----------------------------------------------------------------------------- place recognition


def test_cosine_descriptor_is_the_attention_weighted_mean():
    features = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    recognizer = PlaceRecognizer("cosine")
    descriptor = recognizer.describe(features, torch.tensor([3.0, 1.0]))
    np.testing.assert_allclose(descriptor, np.array([3.0, 1.0]) / math.sqrt(10), rtol=1e-6)
    similarity = recognizer.similarity([descriptor], [descriptor, np.array([0.0, 1.0])])
    np.testing.assert_allclose(similarity, [[1.0, 1 / math.sqrt(10)]], rtol=1e-6)


def test_place_method_is_checked():
    with pytest.raises(ConfigError, match="place_method"):
        PlaceRecognizer("netvlad")
    with pytest.raises(ConfigError, match="codebook"):
        PlaceRecognizer("asmk")


def test_asmk_similarity_ranks_the_same_place_first():
    rng = np.random.default_rng(0)
    codebook = rng.normal(size=(64, 32)).astype(np.float32)
    places = [rng.normal(size=(40, 32)).astype(np.float32) for _ in range(3)]
    noisy = [p + 0.05 * rng.normal(size=p.shape).astype(np.float32) for p in places]
    recognizer = PlaceRecognizer("asmk", codebook, RetrievalConfig())
    similarity = recognizer.similarity(noisy, places)
    assert similarity.shape == (3, 3)
    np.testing.assert_array_equal(np.argmax(similarity, axis=1), [0, 1, 2])


def test_asmk_searches_each_keyframe_once_over_rounds(monkeypatch):
    """Every round compares all keyframes again; their codebook search is made once."""
    rng = np.random.default_rng(1)
    codebook = rng.normal(size=(64, 32)).astype(np.float32)
    places = [rng.normal(size=(40, 32)).astype(np.float32) for _ in range(4)]

    def searched_per_call(rows, cols):
        database = RetrievalDatabase(codebook, RetrievalConfig())
        for k, descriptors in enumerate(cols):
            database.add(1, k, descriptors)
        return np.stack([database.scores(descriptors) for descriptors in rows])

    expected = [
        searched_per_call(places[:2], places[2:3]),
        searched_per_call(places[:2], places[2:]),
    ]
    searches = []
    assign = RetrievalDatabase._assign
    monkeypatch.setattr(
        RetrievalDatabase, "_assign", lambda *a, **k: searches.append(1) or assign(*a, **k)
    )
    recognizer = PlaceRecognizer("asmk", codebook, RetrievalConfig())
    np.testing.assert_array_equal(recognizer.similarity(places[:2], places[2:3]), expected[0])
    np.testing.assert_array_equal(recognizer.similarity(places[:2], places[2:]), expected[1])
    assert len(searches) == 4  # 3 keyframes, then the new one (7 before)


def test_candidates_are_best_matches_above_threshold_from_both_sides():
    similarity = np.array([[0.9, 0.2, 0.0], [0.8, 0.3, 0.05], [0.0, 0.05, 0.08]])
    found = candidate_pairs(similarity, 0.1)
    assert [(c.row, c.col, c.by_row, c.by_col) for c in found] == [
        (0, 0, True, True),
        (1, 0, True, False),
        (1, 1, False, True),
    ]
    # Column 2's best (row 1, 0.05) and row 2's best (col 2, 0.08) are below the threshold.
    assert [(c.row, c.col) for c in candidate_pairs(similarity, 0.1, {(0, 0)})] == [(1, 0), (1, 1)]


# ----------------------------------------------------------------------------- registration


def test_ransac_similarity_recovers_the_transform_despite_outliers(dtype):
    gen = torch.Generator().manual_seed(0)
    src = torch.randn(200, 3, generator=gen, dtype=dtype) * 2 + torch.tensor(
        [0, 0, 6.0], dtype=dtype
    )
    T = torch.cat(
        [
            torch.tensor([0.3, -0.2, 0.5]),
            so3_exp(torch.tensor([0.1, 0.2, -0.1])),
            torch.tensor([1.3]),
        ]
    ).to(dtype)
    dst = sim3_act(T, src)
    dst[:60] += torch.randn(60, 3, generator=gen, dtype=dtype) * 3  # 30 % outliers
    fit = ransac_similarity(src, dst, RegistrationConfig(), generator(0, "test"))
    assert fit is not None
    estimate, inliers = fit
    assert estimate.dtype == torch.float64
    torch.testing.assert_close(estimate, T.double(), atol=1e-5, rtol=1e-5)
    assert int(inliers[60:].sum()) == 140 and int(inliers[:60].sum()) < 5


def test_ransac_similarity_gives_up_without_support():
    src = torch.randn(8, 3)
    assert ransac_similarity(src, src, RegistrationConfig(min_inliers=12), generator(0)) is None


def _room_points(count: int, gen: torch.Generator) -> torch.Tensor:
    """``(count, 3)`` points a camera sees in a room: back wall at depth 6, side walls at
    x = -3, 3 (depth 4-8), 4 high."""
    u = torch.rand(count, 2, generator=gen) * 2 - 1
    wall = torch.randint(0, 3, (count,), generator=gen)
    x = torch.where(wall == 0, 3 * u[:, 0], torch.where(wall == 1, -3.0, 3.0))
    z = torch.where(wall == 0, 6.0, 6 + 2 * u[:, 0])
    return torch.stack([x, 2 * u[:, 1], z], dim=-1)


def test_ransac_similarity_refuses_unrelated_matches_whatever_their_number():
    # Chance support grows with the number of matches: the best of 256 hypotheses explains
    # 16-38 of 3000 unrelated matches (44-48 of a real unrelated 512x384 pair's ~3000),
    # above min_inliers, so the consensus test is also a fraction of the matches.
    config = RegistrationConfig()
    for count in (300, 3000):
        gen = torch.Generator().manual_seed(count)
        src, dst = _room_points(count, gen), _room_points(count, gen)
        assert ransac_similarity(src, dst, config, generator(0, count)) is None
    # The same 3000 matches with 40 % of them true are registered.
    T = torch.cat(
        [
            torch.tensor([0.4, 0.1, -0.3]),
            so3_exp(torch.tensor([0.05, 0.3, 0.0])),
            torch.tensor([0.8]),
        ]
    ).double()
    dst[:1200] = sim3_act(T, src[:1200].double()).float()
    fit = ransac_similarity(src, dst, config, generator(0, "true"))
    assert fit is not None
    torch.testing.assert_close(fit[0], T, atol=1e-4, rtol=1e-4)
    assert int(fit[1][:1200].sum()) == 1200 and int(fit[1][1200:].sum()) < 60


def test_min_inlier_fraction_is_checked():
    with pytest.raises(ConfigError, match="min_inlier_fraction"):
        check_config(DecentralizedConfig(registration=RegistrationConfig(min_inlier_fraction=1.0)))


def test_reciprocal_matches_find_the_permutation():
    gen = torch.Generator().manual_seed(1)
    H, W, d = 12, 16, 24
    D_i = torch.nn.functional.normalize(torch.randn(H, W, d, generator=gen), dim=-1)
    permutation = torch.randperm(H * W, generator=gen)
    D_j = D_i.reshape(-1, d)[permutation].reshape(H, W, d)
    Q = torch.full((H, W), 5.0)
    Q_low = Q.clone()
    Q_low[:6] = 1.0  # the top half of view i is not confident
    # a permutation has no spatial order for a coarse level to follow: a one-pixel grid
    # makes the coarse level every pixel, an exact search
    config = RegistrationConfig(match_stride_ratio=1 / 16)
    p_i, p_j = reciprocal_matches(D_i, D_j, Q, Q, config)
    assert p_i.numel() == H * W
    torch.testing.assert_close(permutation[p_j], p_i)
    p_i, _ = reciprocal_matches(D_i, D_j, Q_low, Q, config)
    assert p_i.numel() == (H // 2) * W and bool((p_i >= 6 * W).all())


def test_odometry_neighbour():
    assert odometry_neighbour(3, 10) == 2
    assert odometry_neighbour(0, 10) == 1
    assert odometry_neighbour(0, 1) == 0


@pytest.fixture(scope="module")
def registrars(scene, main_config):
    """Registrars of robots 0 and 1 of the scene, with their keyframes (2 m apart)."""
    prior = SimulatedPrior(
        main_config.simulated_prior,
        AgentFolderTruth(
            {robot: open_agent(scene[robot]) for robot in (0, 1)}, main_config.input.long_side
        ),
    )
    out = []
    for robot in (0, 1):
        agent = open_agent(scene[robot])
        keyframes = select_keyframes(frame_odometry(agent), 2.0)

        def view_of(k, agent=agent, keyframes=keyframes, robot=robot):
            frame = agent.load_frame(int(keyframes.frames[k]))
            return make_view(frame, robot, main_config.input.long_side)

        out.append((Registrar(prior, robot, view_of, RegistrationConfig()), keyframes, agent))
    return out


def _true_relative(agent_a, frame_a, agent_b, frame_b):
    return sim3_compose(
        sim3_inverse(agent_a.groundtruth.T_WC[frame_a]), agent_b.groundtruth.T_WC[frame_b]
    )


def _nearest_keyframe(agent_a, frame_a, agent_b, keyframes_b) -> int:
    """Keyframe of robot b whose true camera centre is nearest to robot a's frame."""
    centre = agent_a.groundtruth.T_WC[frame_a, :3]
    distances = (agent_b.groundtruth.T_WC[torch.from_numpy(keyframes_b.frames), :3] - centre).norm(
        dim=1
    )
    return int(torch.argmin(distances))


def test_registration_of_an_overlapping_pair_and_ratio_rejection_of_a_distant_one(registrars):
    """Robot 0's last keyframes share the road with robot 1's first ones (ring plan)."""
    (reg_a, kf_a, agent_a), (reg_b, kf_b, agent_b) = registrars
    mine = len(kf_a) - 3
    near = _nearest_keyframe(agent_a, kf_a.frames[mine], agent_b, kf_b)
    far = len(kf_b) - 1
    for other in (near, far):
        reg_a.add_foreign(1, other, **reg_b.reply_for_peer(other))
    overlap = reg_a.register(mine, 1, near)
    _, odometry_pair = reg_a.consecutive(mine, len(kf_a))
    truth = _true_relative(agent_a, kf_a.frames[mine], agent_b, kf_b.frames[near])
    assert overlap.T_ij is not None
    R_error = quat_to_matrix(overlap.T_ij[3:7]).T @ quat_to_matrix(truth[3:7]).double()
    angle = math.degrees(math.acos(min(1.0, (float(torch.trace(R_error)) - 1) / 2)))
    assert angle < 3.0
    direction = overlap.T_ij[:3] / overlap.T_ij[:3].norm()
    assert float(direction @ (truth[:3] / truth[:3].norm()).double()) > 0.9
    ratio = correspondence_ratio(overlap.correspondences, odometry_pair.correspondences)
    assert accept_loop(ratio, 0.3)
    # Robot 1's last keyframe is 20 m further along the ring road: the prior still returns
    # a pair prediction, but with few correspondences -- a failed registration.
    distant = reg_a.register(mine, 1, far)
    ratio = correspondence_ratio(distant.correspondences, odometry_pair.correspondences)
    assert not accept_loop(ratio, 0.3)


def test_two_stage_encoding_encodes_each_keyframe_once(registrars):
    (reg_a, kf_a, _), (reg_b, _, _) = registrars
    last = len(kf_a) - 1
    reg_a.add_foreign(1, 1, **reg_b.reply_for_peer(1))
    reg_a.register(last, 1, 1)
    encodes, naive, sent = reg_a.stats.encodes, reg_a.stats.naive_encodes, reg_b.stats.encodes
    decodes = reg_a.stats.decodes
    again = reg_a.register(last, 1, 1)
    reg_a.add_foreign(1, 1, **reg_b.reply_for_peer(1))
    assert reg_a.stats.encodes == encodes and reg_b.stats.encodes == sent
    assert reg_a.stats.decodes == decodes + 1
    assert reg_a.stats.naive_encodes == naive + 2  # a naive pipeline encodes both again
    assert again.correspondences > 0
    assert reg_b.stats.registration_encodes <= reg_b.stats.encodes


def test_the_simulated_prior_sends_its_record_and_colours_in_place_of_its_encoding(registrars):
    """A peer makes the encoding again from the image and the ground-truth record (13 MB
    against about 1 MB at 512x384) and registers the pair as with the encoding itself."""
    (reg_a, kf_a, _), (reg_b, _, _) = registrars
    reply = reg_b.reply_for_peer(3)
    assert isinstance(reply["encoding"], EncodingRecord) and reply["colours"].dtype == np.uint8
    made = reg_a.stats.foreign_encodes
    reg_a.add_foreign(1, 3, **reply)
    assert reg_a.stats.foreign_encodes == made + 1 and reg_a.has_foreign(1, 3)
    by_record = reg_a.register(len(kf_a) - 1, 1, 3)
    reg_a.add_foreign(1, 3, reg_b.own_encoding(3).for_decoding())
    by_encoding = reg_a.register(len(kf_a) - 1, 1, 3)
    assert by_record.correspondences == by_encoding.correspondences > 0
    assert by_record.inliers == by_encoding.inliers


def test_an_encoding_this_prior_cannot_decode_is_refused(registrars, caplog):
    (reg_a, _, _), (reg_b, _, _) = registrars
    theirs = reg_b.own_encoding(2).for_decoding()  # an encoding as such, not its record
    foreign = MASt3REncoding(
        agent=1,
        index=0,
        shape=(16, 16),
        tokens=torch.zeros(1, 8),
        pos=torch.zeros(1, 2, dtype=torch.int64),
        grid=(1, 1),
    )
    reg_a.add_foreign(1, 5, foreign)
    reg_a.add_foreign(1, 6, dataclasses.replace(theirs, ranges=theirs.ranges[None]))
    for keyframe in (5, 6):
        assert reg_a.answered(1, keyframe) and not reg_a.has_foreign(1, keyframe)
    assert "a MASt3REncoding, where this prior makes SimulatedEncoding" in caplog.text
    assert "ranges is not a 2-d torch.float32 tensor" in caplog.text
    reg_a.add_foreign(1, 2, theirs)
    assert reg_a.has_foreign(1, 2) and reg_a.answered(1, 2)
