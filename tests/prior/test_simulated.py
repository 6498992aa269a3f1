"""The simulated prior's easy model (DESIGN.md, "Simulated prior") on tiny synthetic scenes.

These tests pin the precise behaviour of the ``easy`` near-oracle; the realistic default is
tested in ``test_simulated_realistic.py``. Scenes are rendered once per module with
:func:`como3r.data.synth.synthesize` at 96x72 (network input 96x64). Error statistics are
measured against the ground truth of the scene, with the other error sources switched off
where a statistic must be isolated.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from como3r.config import RetrievalConfig, SimulatedPriorConfig
from como3r.data.agent import open_agent
from como3r.data.preprocess import frame_ground_truth, make_view
from como3r.data.synth import synthesize
from como3r.errors import ConfigError, PriorError
from como3r.frontend.matching import refine_with_descriptors
from como3r.geometry.camera import project, unproject_depth
from como3r.geometry.lie import (
    matrix_to_quat,
    quat_to_matrix,
    sim3_act,
    sim3_compose,
    sim3_inverse,
    so3_log,
)
from como3r.geometry.umeyama import umeyama_sim3
from como3r.prior.base import Encoding, PairPrediction, View
from como3r.prior.ground_truth import GroundTruth, InMemoryTruth
from como3r.prior.retrieval import RetrievalDatabase
from como3r.prior.simulated import SimulatedPrior
from como3r.prior.simulated_encoding import fill_depth_holes

WIDTH, HEIGHT, FRAMES = 96, 72, 40
LONG_SIDE = 96
#: The easy model with its default parameters.
EASY = SimulatedPriorConfig(model="easy")
#: Only the pose noise: every other error source off.
POSE_NOISE_ONLY = dataclasses.replace(
    EASY, scale_sigma=0.0, depth_distortion_amplitude=0.0, range_noise=0.0
)
NOISE_FREE = dataclasses.replace(POSE_NOISE_ONLY, rotation_noise_deg=0.0, translation_noise=0.0)


# ---------------------------------------------------------------------------------- fixtures


#: ground truth of every view the fixtures load (the simulated priors' source); scenes use
#: disjoint agent ids
TRUTH = InMemoryTruth()


def _load_views(root: Path, agents: int, first_agent: int = 0) -> list[list[View]]:
    """Views of every frame of every agent, at network resolution, with intrinsics; their
    ground truth goes to :data:`TRUTH`."""
    out = []
    for a in range(agents):
        agent = open_agent(root / f"agent_{a}")
        views = []
        for i in range(len(agent)):
            frame = agent.load_frame(i)
            views.append(make_view(frame, first_agent + a, LONG_SIDE, calib=agent.calib))
            TRUTH.add(first_agent + a, i, frame_ground_truth(frame, LONG_SIDE, agent.calib))
        out.append(views)
    return out


def gt(view: View) -> GroundTruth:
    """The ground truth of a fixture's view."""
    return TRUTH.truth(view.agent, view.index)


class _ChangedTruth:
    """:data:`TRUTH` with ``changes`` to the frames of ``views`` (None: every frame)."""

    def __init__(self, views: list[View] | None, **changes: object) -> None:
        self.frames = None if views is None else {(v.agent, v.index) for v in views}
        self.changes = changes

    def truth(self, agent: int, index: int) -> GroundTruth:
        truth = TRUTH.truth(agent, index)
        if self.frames is None or (agent, index) in self.frames:
            return dataclasses.replace(truth, **self.changes)
        return truth


@pytest.fixture(scope="module")
def default_views(tmp_path_factory) -> list[list[View]]:
    root = tmp_path_factory.mktemp("default")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.3,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
    )
    return _load_views(root, 2)


@pytest.fixture(scope="module")
def aliasing_scene(tmp_path_factory) -> tuple[list[View], list[int]]:
    """All views of the three agents of an aliasing scene and its aliased texture ids."""
    root = tmp_path_factory.mktemp("aliasing")
    synthesize(
        root,
        agents=3,
        seed=0,
        overlap=0.3,
        frames=FRAMES,
        preset="aliasing",
        width=WIDTH,
        height=HEIGHT,
    )
    aliased = json.loads((root / "scene.json").read_text())["layout"]["aliased_texture_ids"]
    return [v for views in _load_views(root, 3, first_agent=10) for v in views], aliased


@pytest.fixture(scope="module")
def prior() -> SimulatedPrior:
    return SimulatedPrior(EASY, TRUTH)


# ---------------------------------------------------------------------------------- helpers


def _pairs(frames: int, gaps: tuple[int, ...]) -> list[tuple[int, int]]:
    """Ordered pairs ``(i, i + gap)`` and ``(i + gap, i)`` of one agent."""
    out = []
    for gap in gaps:
        for i in range(frames - gap):
            out += [(i, i + gap), (i + gap, i)]
    return out


def _true_points(view: View) -> tuple[torch.Tensor, torch.Tensor]:
    """``(H, W, 3)`` camera-frame points from depth and ``(H, W)`` validity."""
    return unproject_depth(gt(view).depth, view.K), gt(view).depth > 0


def _relative_gt(view_i: View, view_j: View) -> torch.Tensor:
    """``(8,)`` ground-truth pose of camera j in camera i."""
    return sim3_compose(sim3_inverse(gt(view_i).T_WC), gt(view_j).T_WC).to(torch.float32)


def _pose_of_prediction(view_j: View, X_ji: torch.Tensor) -> torch.Tensor:
    """``(8,)`` similarity taking view j's true points to its predicted pointmap ``X_ji``."""
    points, valid = _true_points(view_j)
    return umeyama_sim3(points[valid].double(), X_ji[valid].double())


def _angle_deg(R_a: torch.Tensor, R_b: torch.Tensor) -> float:
    """Angle of the rotation ``R_a R_b^T`` in degrees."""
    return math.degrees(float(so3_log(matrix_to_quat((R_a @ R_b.T).double())).norm()))


def _covisible(view_i: View, view_j: View) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of i seen by j (z-buffer test on j's depth) and their ``(u, v)`` in j."""
    points, valid = _true_points(view_i)
    in_j = sim3_act(sim3_inverse(_relative_gt(view_i, view_j)), points)
    uv = project(in_j, view_j.K)
    H, W = view_j.shape
    col, row = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H) & valid & (in_j[..., 2] > 0)
    seen = gt(view_j).depth[row.clamp(0, H - 1), col.clamp(0, W - 1)]
    return inside & ((seen - in_j[..., 2]).abs() < 0.02 * in_j[..., 2]), uv


def _log_range_ratio(view: View, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``log(|X| / true range)`` ``(H, W)`` and the validity mask."""
    points, valid = _true_points(view)
    ratio = X.norm(dim=-1) / points.norm(dim=-1).clamp_min(1e-9)
    return torch.log(ratio.clamp_min(1e-9)), valid


def _depth_edges(view: View) -> torch.Tensor:
    """Pixels next to a relative depth jump of more than 10 % (independent of the prior)."""
    log_depth = torch.log(gt(view).depth.clamp_min(1e-6))
    jump_u = (log_depth[:, 1:] - log_depth[:, :-1]).abs() > 0.1
    jump_v = (log_depth[1:] - log_depth[:-1]).abs() > 0.1
    edge = torch.zeros_like(gt(view).depth, dtype=torch.bool)
    edge[:, 1:] |= jump_u
    edge[:, :-1] |= jump_u
    edge[1:] |= jump_v
    edge[:-1] |= jump_v
    return edge


# ---------------------------------------------------------------------------------- outputs


def test_outputs_have_mast3r_types_shapes_and_ranges(prior, default_views):
    views = default_views[0]
    H, W = views[0].shape
    prediction = prior.decode(prior.encode(views[0]), prior.encode(views[2]))
    assert isinstance(prediction, PairPrediction)
    for name in ("X_ii", "X_ji"):
        assert getattr(prediction, name).shape == (H, W, 3)
    for name in ("C_ii", "C_ji", "Q_ii", "Q_ji"):
        assert getattr(prediction, name).shape == (H, W)
    for name in ("D_ii", "D_ji"):
        assert getattr(prediction, name).shape == (H, W, 24)
        norms = getattr(prediction, name).norm(dim=-1)
        torch.testing.assert_close(norms, torch.ones_like(norms))
    for field in dataclasses.fields(prediction):
        value = getattr(prediction, field.name)
        assert value.dtype == torch.float32 and bool(torch.isfinite(value).all()), field.name
    assert bool((prediction.C_ii >= 1).all()) and bool((prediction.C_ji >= 1).all())
    assert bool((prediction.Q_ii > 0).all()) and bool((prediction.Q_ji > 0).all())
    assert prior.descriptor_dim == 24
    # camera-i frame: view i in front of its own camera, at its true ranges give or take 30 %
    assert bool((prediction.X_ii[..., 2] > 0).all())
    log_ratio, valid = _log_range_ratio(views[0], prediction.X_ii)
    assert float(log_ratio[valid].abs().max()) < math.log(1.3)


@pytest.mark.slow
def test_decode_is_deterministic_and_ordered_pairs_are_independent(prior, default_views):
    views = default_views[0]
    enc_a, enc_b = prior.encode(views[3]), prior.encode(views[4])
    first, again = prior.decode(enc_a, enc_b), prior.decode(enc_a, enc_b)
    fresh = SimulatedPrior(EASY, TRUTH).decode(prior.encode(views[3]), prior.encode(views[4]))
    for field in dataclasses.fields(first):
        assert torch.equal(getattr(first, field.name), getattr(again, field.name))
        assert torch.equal(getattr(first, field.name), getattr(fresh, field.name))
    other_seed = SimulatedPrior(dataclasses.replace(EASY, seed=1), TRUTH)
    assert not torch.equal(
        other_seed.decode(other_seed.encode(views[3]), other_seed.encode(views[4])).X_ii, first.X_ii
    )
    # The scale draw of (i, j) says nothing about the one of (j, i).
    encodings = [prior.encode(v) for v in views]
    forward, backward = [], []
    for i in range(0, FRAMES - 1):
        log_ij, valid_i = _log_range_ratio(
            views[i], prior.decode(encodings[i], encodings[i + 1]).X_ii
        )
        log_ji, valid_j = _log_range_ratio(
            views[i + 1], prior.decode(encodings[i + 1], encodings[i]).X_ii
        )
        forward.append(float(log_ij[valid_i].median()))
        backward.append(float(log_ji[valid_j].median()))
    correlation = np.corrcoef(forward, backward)[0, 1]
    assert abs(correlation) < 0.4


def test_decode_symmetric_matches_both_orders(prior, default_views):
    views = default_views[1]
    enc_a, enc_b = prior.encode(views[0]), prior.encode(views[1])
    ((ab, ba),) = prior.decode_symmetric([(enc_a, enc_b)])
    assert torch.equal(ab.X_ji, prior.decode(enc_a, enc_b).X_ji)
    assert torch.equal(ba.X_ji, prior.decode(enc_b, enc_a).X_ji)


# ---------------------------------------------------------------------------------- errors


def test_missing_inputs_raise_prior_error(prior, default_views):
    view = default_views[0][0]

    def encode_with(**changes: object) -> Encoding:
        return SimulatedPrior(EASY, _ChangedTruth([view], **changes)).encode(view)

    with pytest.raises(PriorError, match="lacks a depth map .*images alone take --prior mast3r"):
        encode_with(depth=None)
    with pytest.raises(PriorError, match="intrinsics K"):
        encode_with(K=None)
    with pytest.raises(PriorError, match="surface map .* or a ground-truth pose"):
        encode_with(surface=None, T_WC=None)
    with pytest.raises(PriorError, match="depth map of shape"):
        encode_with(depth=gt(view).depth[:-1])
    with pytest.raises(PriorError, match="no ground truth for agent 7, frame 0"):
        prior.encode(dataclasses.replace(view, agent=7))
    with pytest.raises(PriorError, match="no ground-truth source"):
        SimulatedPrior(EASY).encode(view)
    with pytest.raises(PriorError, match="cannot decode"):
        prior.decode(Encoding(0, 0, view.shape), prior.encode(view))


@pytest.mark.parametrize("key", ["scale_sigma", "range_noise", "depth_distortion_wavelength"])
def test_invalid_configuration_names_the_key(key):
    with pytest.raises(ConfigError, match=f"simulated_prior.{key}"):
        SimulatedPrior(dataclasses.replace(EASY, **{key: -1.0}), TRUTH)


# ---------------------------------------------------------------------------------- statistics


@pytest.mark.slow
def test_scale_error_spread_matches_scale_sigma(default_views):
    config = dataclasses.replace(EASY, depth_distortion_amplitude=0.0, range_noise=0.0)
    prior = SimulatedPrior(config, TRUTH)
    views = default_views[0]
    encodings = [prior.encode(v) for v in views]
    log_scales = []
    for i, j in _pairs(FRAMES, (1, 2))[:120]:
        log_ratio, valid = _log_range_ratio(views[i], prior.decode(encodings[i], encodings[j]).X_ii)
        log_scales.append(float(log_ratio[valid].median()))
    log_scales = np.asarray(log_scales)
    # 120 draws: the sample standard deviation is within 18 % of sigma with ~99.5 % probability.
    assert abs(log_scales.std() / config.scale_sigma - 1.0) < 0.18
    assert abs(log_scales.mean()) < 3.0 * config.scale_sigma / math.sqrt(len(log_scales))


@pytest.mark.slow
def test_scale_spread_with_every_error_source_on(prior, default_views):
    views = default_views[1]
    encodings = [prior.encode(v) for v in views]
    log_scales = []
    for i, j in _pairs(FRAMES, (1, 2))[:80]:
        log_ratio, valid = _log_range_ratio(views[i], prior.decode(encodings[i], encodings[j]).X_ii)
        log_scales.append(float(log_ratio[valid].median()))
    # The image mean of the smooth distortion adds a little spread on top of scale_sigma.
    assert 0.8 < np.std(log_scales) / prior.config.scale_sigma < 1.3


def test_range_noise_matches_config(default_views):
    views = default_views[0]
    isolated = SimulatedPrior(
        dataclasses.replace(EASY, scale_sigma=0.0, depth_distortion_amplitude=0.0), TRUTH
    )
    log_ratio, valid = _log_range_ratio(
        views[5], isolated.decode(isolated.encode(views[5]), isolated.encode(views[6])).X_ii
    )
    assert abs(float(log_ratio[valid].std()) / isolated.config.range_noise - 1.0) < 0.05

    # With every error on: a 3x3 high-pass removes the scale and the smooth distortion
    # (wavelength 32 px), leaving the per-pixel noise times sqrt(8 / 9).
    prior = SimulatedPrior(EASY, TRUTH)
    residuals = []
    for i in range(0, 20, 4):
        log_ratio, valid = _log_range_ratio(
            views[i], prior.decode(prior.encode(views[i]), prior.encode(views[i + 1])).X_ii
        )
        local_mean = F.avg_pool2d(log_ratio[None, None], 3, stride=1)[0, 0]
        usable = (
            F.max_pool2d((~valid | _depth_edges(views[i]))[None, None].float(), 3, stride=1)[0, 0]
            == 0
        )
        residuals.append((log_ratio[1:-1, 1:-1] - local_mean)[usable])
    noise = float(torch.cat(residuals).std()) / math.sqrt(8.0 / 9.0)
    assert abs(noise / prior.config.range_noise - 1.0) < 0.1


@pytest.mark.slow
def test_depth_distortion_amplitude_and_wavelength(default_views):
    config = dataclasses.replace(EASY, scale_sigma=0.0, range_noise=0.0)
    prior = SimulatedPrior(config, TRUTH)
    views = default_views[0]
    encodings = [prior.encode(v) for v in views]
    wavelength_px = config.depth_distortion_wavelength * max(views[0].shape)
    half, eighth = round(wavelength_px / 2), round(wavelength_px / 8)
    mean_square, corr_half, corr_eighth = [], [], []
    for i, j in _pairs(FRAMES, (1,))[:40]:
        log_ratio, valid = _log_range_ratio(views[i], prior.decode(encodings[i], encodings[j]).X_ii)
        field = torch.where(
            valid, log_ratio / config.depth_distortion_amplitude, torch.zeros_like(log_ratio)
        )
        mean_square.append(float(field[valid].square().mean()))
        both = valid[:, half:] & valid[:, :-half]
        corr_half.append(float((field[:, half:] * field[:, :-half])[both].mean()))
        both = valid[:, eighth:] & valid[:, :-eighth]
        corr_eighth.append(float((field[:, eighth:] * field[:, :-eighth])[both].mean()))
    rms = math.sqrt(np.mean(mean_square))
    assert abs(rms - 1.0) < 0.15  # RMS relative distortion = depth_distortion_amplitude
    # Isotropic random waves of wavelength L: correlation J0(2 pi lag / L) = -0.30 at L / 2,
    # 0.85 at L / 8.
    assert np.mean(corr_half) / rms**2 < -0.1
    assert np.mean(corr_eighth) / rms**2 > 0.7


def test_relative_pose_is_the_true_one_for_overlapping_views(default_views):
    prior = SimulatedPrior(NOISE_FREE, TRUTH)
    views = default_views[0]
    for i, j in [(0, 2), (10, 14), (25, 20), (33, 30)]:
        prediction = prior.decode(prior.encode(views[i]), prior.encode(views[j]))
        fitted, truth = (
            _pose_of_prediction(views[j], prediction.X_ji),
            _relative_gt(views[i], views[j]),
        )
        baseline = float(truth[:3].norm())
        assert _angle_deg(quat_to_matrix(fitted[3:7]).float(), quat_to_matrix(truth[3:7])) < 0.02
        assert float((fitted[:3].float() - truth[:3]).norm()) < 1e-3 + 0.002 * baseline
        assert abs(float(fitted[7]) - 1.0) < 1e-3


@pytest.mark.slow
def test_pose_noise_matches_config(default_views):
    prior = SimulatedPrior(POSE_NOISE_ONLY, TRUTH)
    views = default_views[0]
    encodings = [prior.encode(v) for v in views]
    angles, relative_shifts = [], []
    for i, j in _pairs(FRAMES, (2, 3))[:80]:
        # The noise-free fit is exact to ~1e-4 (test above), so the error w.r.t. the ground
        # truth is the pose noise.
        fitted = _pose_of_prediction(views[j], prior.decode(encodings[i], encodings[j]).X_ji)
        truth = _relative_gt(views[i], views[j])
        angles.append(_angle_deg(quat_to_matrix(fitted[3:7]).float(), quat_to_matrix(truth[3:7])))
        relative_shifts.append(float((fitted[:3].float() - truth[:3]).norm() / truth[:3].norm()))
    # 80 draws of a 3-D error: the RMS is within 15 % of its expectation with ~99.5 %
    # probability.
    rms_angle = math.sqrt(np.mean(np.square(angles)))
    rms_shift = math.sqrt(np.mean(np.square(relative_shifts)))
    assert abs(rms_angle / POSE_NOISE_ONLY.rotation_noise_deg - 1.0) < 0.15
    assert abs(rms_shift / POSE_NOISE_ONLY.translation_noise - 1.0) < 0.15


# ---------------------------------------------------------------------------------- cues


def test_descriptor_nearest_neighbours_find_true_correspondences(prior, default_views):
    views = default_views[0]
    for i, j in [(0, 2), (12, 15), (30, 27)]:
        prediction = prior.decode(prior.encode(views[i]), prior.encode(views[j]))
        covisible, uv = _covisible(views[i], views[j])
        assert int(covisible.sum()) > 500
        similarity = prediction.D_ii[covisible] @ prediction.D_ji.reshape(-1, 24).T
        nearest = similarity.argmax(-1)
        W = views[j].shape[1]
        error = torch.maximum(
            (nearest % W - uv[covisible][:, 0]).abs(), (nearest // W - uv[covisible][:, 1]).abs()
        )
        assert float((error <= 1.0).float().mean()) > 0.8


def test_confidence_falls_with_range_edges_and_missing_counterparts(prior, default_views):
    views = default_views[0]
    view_i, view_j = views[10], views[14]
    prediction = prior.decode(prior.encode(view_i), prior.encode(view_j))
    points, valid = _true_points(view_i)
    ranges = points.norm(dim=-1)
    near, far = ranges < ranges[valid].quantile(0.3), ranges > ranges[valid].quantile(0.7)
    interior = valid & ~_depth_edges(view_i)
    assert prediction.C_ii[near & interior].median() > prediction.C_ii[far & interior].median()
    assert prediction.Q_ii[near & interior].median() > prediction.Q_ii[far & interior].median()
    edges = _depth_edges(view_i) & valid
    assert int(edges.sum()) > 20
    assert prediction.C_ii[edges].mean() < prediction.C_ii[interior].mean()
    # Pixels of j that i does not see get low confidence in X_ji.
    seen_by_i, _ = _covisible(view_j, view_i)
    unseen = ~seen_by_i & (gt(view_j).depth > 0)
    assert int(unseen.sum()) > 100 and int(seen_by_i.sum()) > 100
    assert prediction.C_ji[seen_by_i].median() > 2.0 * prediction.C_ji[unseen].median()
    assert prediction.Q_ji[seen_by_i].median() > 1.5 > prediction.Q_ji[unseen].median()


def test_pair_without_common_keys_gets_low_confidence(prior, default_views):
    view_i = default_views[0][0]
    view_j = default_views[0][1]
    surface = gt(view_j).surface.clone()
    surface[..., 0] += 100_000  # textures view i has never seen
    prediction = prior.decode(
        prior.encode(view_i),
        SimulatedPrior(EASY, _ChangedTruth([view_j], surface=surface)).encode(view_j),
    )
    assert float(prediction.C_ji.max()) < 1.2
    assert float(prediction.Q_ji.median()) < 1.5
    assert bool(torch.isfinite(prediction.X_ji).all())
    overlapping = prior.decode(prior.encode(view_i), prior.encode(view_j))
    assert float(overlapping.C_ji.median()) > 3.0


def test_sky_is_far_with_confidence_near_one(prior, default_views):
    view = default_views[0][7]
    depth, surface = gt(view).depth.clone(), gt(view).surface.clone()
    depth[:10], surface[:10, :, 0] = 0.0, -1.0  # the top rows become sky
    changed = SimulatedPrior(EASY, _ChangedTruth([view], depth=depth, surface=surface))
    prediction = prior.decode(*[changed.encode(view)] * 2)
    # sky at 10-20 times the median valid range (scale error removed)
    points, _ = _true_points(view)
    true_ranges = points[10:].norm(dim=-1)
    scale = float(prediction.X_ii[10:].norm(dim=-1).median() / true_ranges.median())
    sky_ranges = prediction.X_ii[:10].norm(dim=-1) / (scale * float(true_ranges.median()))
    assert float(sky_ranges.min()) > 8.0 and float(sky_ranges.max()) < 26.0
    assert float(prediction.C_ii[:10].max()) < 1.1
    assert float(prediction.C_ii[12:].median()) > 3.0


def test_a_depth_sensors_holes_are_filled_matchable_and_unconfident(prior, default_views):
    """Without a surface map, pixels without depth are a sensor's holes, not sky: filled
    with the surface behind them (the farthest valid depth nearby), matchable (ordinary Q),
    with the sky's geometric confidence."""
    view = default_views[0][7]
    depth = gt(view).depth.clone()
    hole = (slice(20, 30), slice(40, 52))
    depth[hole] = 0.0
    sensor = SimulatedPrior(EASY, _ChangedTruth([view], depth=depth, surface=None))
    enc = sensor.encode(view)
    assert bool(enc.valid.all()) and bool(enc.filled[hole].all())
    assert int(enc.filled.sum()) == int((depth <= 0).sum())
    around = gt(view).depth[18:32, 38:54]
    filled_z = unproject_depth(fill_depth_holes(depth, depth > 0), view.K)[..., 2][hole]
    assert float(filled_z.min()) >= float(around[around > 0].min()) - 1e-4
    assert float(filled_z.max()) <= float(around.max()) + 1e-4
    prediction = sensor.decode(enc, enc)
    assert float(prediction.C_ii[hole].max()) < 1.1
    assert float(prediction.Q_ii[hole].median()) > 1.5
    # with a surface map, the same pixels are sky
    assert not bool(prior.encode(view).filled.any())


def test_fill_depth_holes_takes_the_farthest_depth_of_the_smallest_block():
    """A hole pixel takes the farthest valid depth of the smallest aligned 2^k block around
    it that has one (the surface behind, where near and far meet); valid depth is kept."""
    depth = torch.tensor(
        [[1.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]
    )
    filled = fill_depth_holes(depth, depth > 0)
    expected = torch.tensor(
        [[1.0, 2.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0], [2.0, 2.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0]]
    )
    assert torch.equal(filled, expected)


def test_world_keys_without_surface_maps(prior, default_views):
    views = default_views[0][:6]
    world_keys = SimulatedPrior(NOISE_FREE, _ChangedTruth(None, surface=None))
    prediction = world_keys.decode(*[world_keys.encode(v) for v in (views[0], views[3])])
    fitted, truth = _pose_of_prediction(views[3], prediction.X_ji), _relative_gt(views[0], views[3])
    assert _angle_deg(quat_to_matrix(fitted[3:7]).float(), quat_to_matrix(truth[3:7])) < 0.02
    assert float((fitted[:3].float() - truth[:3]).norm()) < 2e-3
    noisy = SimulatedPrior(EASY, _ChangedTruth(None, surface=None))
    default = noisy.decode(noisy.encode(views[0]), noisy.encode(views[3]))
    assert float(default.C_ji.median()) > 3.0


# ---------------------------------------------------------------------------------- aliasing


def _aliased_pair(views: list[View], aliased: list[int]) -> tuple[View, View]:
    """Two views of different agents, both mostly showing aliased façades, that share no
    surface point (z-buffer test both ways); the most façade-filled such pair."""
    ids = torch.tensor(aliased)
    fraction = [float(torch.isin(gt(v).surface[..., 0].long(), ids).float().mean()) for v in views]
    ranked = sorted(range(len(views)), key=lambda k: -fraction[k])[:24]
    for a in ranked:
        for b in ranked:
            if views[a].agent == views[b].agent:
                continue
            if not bool(
                _covisible(views[a], views[b])[0].any() | _covisible(views[b], views[a])[0].any()
            ):
                return views[a], views[b]
    raise AssertionError("the aliasing scene has no pair of disjoint façade views")


@pytest.mark.slow
def test_aliased_facades_are_confusable_and_give_a_wrong_pose(prior, aliasing_scene):
    views, aliased = aliasing_scene
    view_i, view_j = _aliased_pair(views, aliased)
    prediction = prior.decode(prior.encode(view_i), prior.encode(view_j))
    facade = torch.isin(gt(view_i).surface[..., 0].long(), torch.tensor(aliased)) & (
        gt(view_i).depth > 0
    )
    best = (prediction.D_ii[facade] @ prediction.D_ji.reshape(-1, 24).T).max(-1).values
    assert float(best.median()) > 0.9  # every façade pixel has a near-identical twin in j
    # ... and the prior places j where the twin façade would be: a confident wrong pose.
    fitted, truth = _pose_of_prediction(view_j, prediction.X_ji), _relative_gt(view_i, view_j)
    rotation_error = _angle_deg(quat_to_matrix(fitted[3:7]).float(), quat_to_matrix(truth[3:7]))
    translation_error = float((fitted[:3].float() - truth[:3]).norm())
    assert rotation_error > 5.0 or translation_error > 0.5
    assert float(prediction.C_ji[prediction.Q_ji > 1.5].median()) > 3.0
    # Keys from world coordinates cannot alias: the same pair then shares nothing.
    without_surface = SimulatedPrior(EASY, _ChangedTruth(None, surface=None))
    world_keys = prior.decode(*[without_surface.encode(v) for v in (view_i, view_j)])
    assert float(world_keys.C_ji.max()) < 1.2
    best = (world_keys.D_ii[facade] @ world_keys.D_ji.reshape(-1, 24).T).max(-1).values
    assert float(best.median()) < 0.85


# ---------------------------------------------------------------------------------- retrieval


def test_retrieval_features_rank_the_same_place_first(prior, default_views, tmp_path):
    views = default_views[0]
    descriptors, attention = prior.retrieval_features(prior.encode(views[0]))
    assert descriptors.shape[1] == prior.constants.retrieval_dim
    assert descriptors.shape[0] == attention.shape[0] <= prior.constants.retrieval_max_features
    torch.testing.assert_close(descriptors.norm(dim=-1), torch.ones(descriptors.shape[0]))
    assert bool((attention[:-1] >= attention[1:]).all()) and bool((attention <= 1).all())
    database = RetrievalDatabase(prior.codebook(size=64, cache_dir=tmp_path), RetrievalConfig())
    stored = [0, 12, 24, 36]
    for k in stored:
        database.add(0, k, *prior.retrieval_features(prior.encode(views[k])))
    for query in (1, 13, 25, 35):
        hits = database.query(
            prior.retrieval_features(prior.encode(views[query]))[0], k=1, min_similarity=-1.0
        )
        assert hits[0].keyframe == min(stored, key=lambda k: abs(k - query))


def test_codebook_is_trained_once_and_cached(prior, tmp_path, monkeypatch):
    first = prior.codebook(size=32, cache_dir=tmp_path)
    assert first.shape == (32, prior.constants.retrieval_dim) and first.dtype == np.float32
    assert len(list(tmp_path.glob("simulated_codebook_*.npy"))) == 1

    def no_training(*args, **kwargs):
        raise AssertionError("the cached codebook must be reused")

    monkeypatch.setattr("como3r.prior.codebook.train_codebook", no_training)
    np.testing.assert_array_equal(
        SimulatedPrior(truth=TRUTH).codebook(size=32, cache_dir=tmp_path), first
    )
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    np.testing.assert_array_equal(prior.codebook(size=32), first)  # deterministic
    assert len(list((tmp_path / "xdg" / "como3r").glob("simulated_codebook_*.npy"))) == 1
    assert not np.array_equal(
        SimulatedPrior(dataclasses.replace(EASY, seed=3), TRUTH).codebook(
            size=32, cache_dir=tmp_path
        ),
        first,
    )


def test_describe_reports_every_error_model_parameter():
    config = SimulatedPriorConfig(scale_sigma=0.07, seed=4)
    description = SimulatedPrior(config, TRUTH).describe()
    for field in dataclasses.fields(config):
        assert description[field.name] == getattr(config, field.name)
    assert description["name"] == "SimulatedPrior"
    assert description["constants"]["sky_range"] == (10.0, 20.0)
    assert description["model"] == "realistic" and "realistic_constants" in description
    assert SimulatedPrior(EASY, TRUTH).describe()["model"] == "easy"


def _refinement_success(scale: float, feature_map) -> float:
    """Share of pixels that the SLAM's descriptor search (radius 3, dilations 5 to 1) brings
    back to their true match from 7 pixels away, on a planar texture whose lengths and
    pixel size are ``scale`` times those of a 1 cm-per-pixel view, each view's descriptors
    with the prior's 0.1 noise."""
    side = 128
    v, u = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    footprint = 0.01 * scale
    coords = (
        torch.stack(
            [u * footprint + 3.7 * scale, v * footprint + 1.3 * scale, torch.zeros(side, side)], -1
        )
        .reshape(-1, 3)
        .float()
    )
    ids = torch.full((side * side,), 5)
    clean = feature_map(ids, coords, torch.full((side * side,), footprint))
    gen = torch.Generator().manual_seed(0)

    def view() -> torch.Tensor:
        noise = 0.1 / math.sqrt(clean.shape[1]) * torch.randn(clean.shape, generator=gen)
        return F.normalize(F.normalize(clean, dim=-1) + noise, dim=-1)

    D_search, D_query = view().reshape(1, side, side, -1), view()
    inner = ((u >= 32) & (u < 96) & (v >= 32) & (v < 96)).reshape(-1)
    truth = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[inner]
    start = truth + torch.tensor([7, -7])
    refined = refine_with_descriptors(D_search, D_query[inner][None], start[None], 3, 5)[0]
    return float(((refined - truth).abs().amax(-1) <= 1).float().mean())


def test_descriptor_search_works_at_every_scene_scale(prior):
    # `como3r synth --scale s` renders the same images with every length times s: a network
    # sees the same pixels, so its descriptors must serve the search as well at every scale.
    # Measured: 0.87-0.97 at every scale below. With one band of wavelengths fixed in metres
    # (0.05-10 m) it succeeded on 0.93 at 1 cm per pixel but 0.22 at 40 cm (the aerial
    # family's pixels: 6 of its 12 frames tracked) and 0.12 at 1 mm (a tabletop's)
    success = {
        scale: _refinement_success(scale, prior._descriptor_map)
        for scale in (0.01, 0.1, 1.0, 40.0, 1000.0)
    }
    assert min(success.values()) > 0.8, success


def test_the_feature_map_makes_a_large_view_block_by_block_as_whole(monkeypatch) -> None:
    """Issue 41: features of more keys than a block (a whole view's) are made
    ``FEATURE_ROWS`` keys at a time, each key's features as the whole call made them but for
    the phases' float32 rounding (a matrix product's rounding depends on its row count; the
    phases here reach 10^4 rad, so an ulp of phase is 10^-3 of a feature at most)."""
    from como3r.prior import simulated_keys

    feature_map = simulated_keys.RandomFeatureMap(24, 3, 0.01, 2.0, 0.5, 1.0, 64.0, "test")
    gen = torch.Generator().manual_seed(0)
    N = 3 * 1024 + 5
    ids = torch.randint(0, 50, (N,), generator=gen)
    ids[::7] = simulated_keys.WORLD_KEY_ID
    coords = torch.randn(N, 3, generator=gen) * 10
    footprint = torch.rand(N, generator=gen) * 0.05 + 1e-3
    whole = feature_map(ids, coords, footprint)
    monkeypatch.setattr(simulated_keys, "FEATURE_ROWS", 1024)
    blocks = feature_map(ids, coords, footprint)
    assert whole.shape == (N, 24) and bool(whole.abs().sum(-1).gt(0).all())
    assert float((blocks - whole).abs().max()) < 1e-3
    assert float((blocks == whole).float().mean()) > 0.999
