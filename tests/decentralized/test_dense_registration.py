"""The dense pose fit of a registered pair (``registration.pose_fit``, issue 37)."""

from __future__ import annotations

import math

import pytest
import torch

from como3r.config_decentralized import RegistrationConfig
from como3r.decentralized.dense_fit import camera_shift, dense_similarity, points_shift
from como3r.decentralized.matching import reciprocal_matches
from como3r.decentralized.registration import (
    RegistrationStats,
    ransac_similarity,
    register_predictions,
)
from como3r.errors import GeometryError
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse, so3_log
from como3r.geometry.umeyama import umeyama_sim3
from como3r.prior.base import PairPrediction
from como3r.prior.simulated_keys import generator

H, W = 48, 64


def _scene(seed: int) -> torch.Tensor:
    """``(H, W, 3)`` float64 points in front of camera i, 1-10 depths away."""
    gen = torch.Generator().manual_seed(seed)
    rays = torch.cat(
        [
            torch.rand(H, W, 2, generator=gen, dtype=torch.float64) - 0.5,
            torch.ones(H, W, 1, dtype=torch.float64),
        ],
        dim=-1,
    )
    return rays * (1.0 + 9.0 * torch.rand(H, W, 1, generator=gen, dtype=torch.float64))


def _true_T_ij() -> torch.Tensor:
    """A similarity of camera j into camera i: 0.4 rad turn, a baseline, scale 1.3."""
    return sim3_exp(
        torch.tensor([0.4, -0.1, 0.2, 0.05, 0.4, -0.1, math.log(1.3)], dtype=torch.float64)
    )


def _predictions(
    T_ij: torch.Tensor, seed: int, noise: float = 0.0, dtype: torch.dtype = torch.float64
) -> tuple[PairPrediction, PairPrediction]:
    """Both decodes of a pair whose two views see the same points at the same pixels, the
    pointmaps' errors proportional to range (``noise`` of it, each decode its own)."""
    gen = torch.Generator().manual_seed(seed)
    X_i = _scene(seed)  # the points in camera i
    X_j = sim3_act(sim3_inverse(T_ij), X_i)  # the same points in camera j

    def noisy(X: torch.Tensor) -> torch.Tensor:
        error = torch.randn(X.shape, generator=gen, dtype=torch.float64)
        return (X + noise * X.norm(dim=-1, keepdim=True) * error).to(dtype)

    descriptors = torch.nn.functional.normalize(torch.randn(H, W, 16, generator=gen), dim=-1)
    confidence = 1.0 + torch.rand(H, W, generator=gen)
    quality = torch.full((H, W), 3.0)

    def decode(X_own: torch.Tensor, X_other_here: torch.Tensor) -> PairPrediction:
        return PairPrediction(
            X_ii=noisy(X_own),
            X_ji=noisy(X_other_here),
            C_ii=confidence.to(dtype),
            C_ji=confidence.to(dtype),
            D_ii=descriptors,
            D_ji=descriptors,
            Q_ii=quality,
            Q_ji=quality,
        )

    # (i, j): view i in camera i, view j in camera i (the same points); (j, i) in camera j
    return decode(X_i, X_i), decode(X_j, X_j)


def _errors(T: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """Rotation error [rad] and translation error [units of camera i] of ``T``."""
    delta = sim3_compose(sim3_inverse(truth), T.double())
    return float(so3_log(delta[3:7]).norm()), float((T[:3].double() - truth[:3]).norm())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_similarity_recovers_the_pair_and_skips_unusable_pixels(dtype):
    truth = _true_T_ij()
    pred_ij, pred_ji = _predictions(truth, seed=0, dtype=dtype)
    pred_ij.X_ji[0, :5] = float("nan")  # a failed pixel
    pred_ij.X_ii[1, :5, 2] = -1.0  # behind camera i
    T = dense_similarity(pred_ij, pred_ji)
    rotation, translation = _errors(T, truth)
    tolerance = 1e-4 if dtype == torch.float32 else 1e-9
    assert rotation < tolerance and translation < tolerance
    assert abs(float(T[7]) - 1.3) < tolerance


def test_dense_similarity_weights_near_points_by_their_smaller_error():
    """With errors proportional to range, weighting by inverse squared range is the least
    squares fit of the error model: over 20 pairs its translation error is below that of
    the fit weighted by confidence alone."""
    truth = _true_T_ij()
    by_range, by_confidence = 0.0, 0.0
    for seed in range(20):
        pred_ij, pred_ji = _predictions(truth, seed, noise=0.03)
        by_range += _errors(dense_similarity(pred_ij, pred_ji), truth)[1]
        src = torch.cat([pred_ji.X_ii.reshape(-1, 3), pred_ji.X_ji.reshape(-1, 3)])
        dst = torch.cat([pred_ij.X_ji.reshape(-1, 3), pred_ij.X_ii.reshape(-1, 3)])
        confidence = torch.cat(
            [(pred_ij.C_ji * pred_ji.C_ii).reshape(-1), (pred_ij.C_ii * pred_ji.C_ji).reshape(-1)]
        )
        by_confidence += _errors(umeyama_sim3(src, dst, confidence), truth)[1]
    assert by_range < 0.6 * by_confidence  # measured 0.33


def test_dense_similarity_of_coincident_points_is_a_geometry_error():
    pred_ij, pred_ji = _predictions(_true_T_ij(), seed=1)
    for pred in (pred_ij, pred_ji):
        pred.X_ii[:] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        pred.X_ji[:] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    with pytest.raises(GeometryError):
        dense_similarity(pred_ij, pred_ji)


@pytest.mark.parametrize("pose_fit", ["dense", "matches"])
def test_register_predictions_returns_the_configured_fit(pose_fit):
    """The matches' consensus decides that the pair is registered; its pose is the dense
    fit's or the consensus's own, as configured."""
    truth = _true_T_ij()
    pred_ij, pred_ji = _predictions(truth, seed=2, noise=0.01)
    config = RegistrationConfig(pose_fit=pose_fit)
    registration = register_predictions(pred_ij, pred_ji, config, generator(0, "pair"))
    assert registration.T_ij is not None and registration.inliers >= config.min_inliers
    p_i, p_j = reciprocal_matches(pred_ij.D_ii, pred_ij.D_ji, pred_ij.Q_ii, pred_ij.Q_ji, config)
    consensus = ransac_similarity(
        pred_ji.X_ii.reshape(-1, 3)[p_j],
        pred_ij.X_ii.reshape(-1, 3)[p_i],
        config,
        generator(0, "pair"),
    )
    assert consensus is not None
    expected = dense_similarity(pred_ij, pred_ji) if pose_fit == "dense" else consensus[0]
    assert torch.allclose(registration.T_ij, expected)
    other = consensus[0] if pose_fit == "dense" else dense_similarity(pred_ij, pred_ji)
    assert not torch.allclose(registration.T_ij, other)


@pytest.mark.parametrize("offset, refused", [(2.0, True), (0.3, False)])
def test_a_dense_fit_far_from_the_consensus_is_refused(offset, refused):
    """Both cross-view heads (``X_ji``) place the other view as if camera j were ``offset``
    units off along x, as a prior's can where two views barely overlap (issue 37's 4-robot
    ring: a consecutive pair's dense fit 0.49 depths from its consensus, 136 deg off in
    direction): the dense fit, which takes every pixel of them, follows, while the
    consensus of the views' own pointmaps does not. At 2 units (the scene's median depth is
    about 5.5) camera j lies more than ``dense_max_shift_ratio`` of that depth from the
    consensus's, so the consensus's pose is kept (and counted); at 0.3 the dense fit is
    kept."""
    truth = _true_T_ij()
    pred_ij, pred_ji = _predictions(truth, seed=3, noise=0.01)
    believed = truth.clone()
    believed[0] += offset
    origin = torch.zeros(3, dtype=torch.float64)
    pred_ij.X_ji[..., 0] += offset  # view j in camera i, camera j believed moved
    pred_ji.X_ji[:] += sim3_act(sim3_inverse(believed), origin) - sim3_act(
        sim3_inverse(truth), origin
    )
    config = RegistrationConfig()
    stats = RegistrationStats()
    registration = register_predictions(pred_ij, pred_ji, config, generator(0, "pair"), stats)
    dense = dense_similarity(pred_ij, pred_ji)
    assert registration.T_ij is not None
    assert torch.equal(registration.T_ij, dense) != refused
    assert stats.dense_fits_refused == int(refused)
    assert stats.dense_fits_refused_points == 0  # the camera was off, not only the points
    assert abs(float(dense[0] - truth[0]) - offset) < 0.1  # the dense fit followed the heads
    assert _errors(registration.T_ij, truth)[1] < (0.1 if refused else 0.4)


def test_camera_shift_is_in_units_of_view_is_median_depth():
    """Camera j placed 1 unit apart by two estimates, view i's median depth 4 (invalid
    depths left out): a shift of 0.25."""
    T_a = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0], dtype=torch.float64)
    T_b = T_a.clone()
    T_b[0] = 1.0
    X_ii = torch.zeros(2, 3, 3, dtype=torch.float64)
    X_ii[..., 2] = torch.tensor([[3.0, 4.0, 5.0], [4.0, -1.0, float("nan")]])
    assert camera_shift(T_a, T_b, X_ii) == pytest.approx(0.25)
    X_ii[..., 2] = -1.0  # no point in front of camera i: no scale to measure the shift in
    assert camera_shift(T_a, T_b, X_ii) == math.inf


@pytest.mark.parametrize("turn, refused", [(0.5, True), (0.1, False)])
def test_a_dense_fit_turned_about_camera_i_is_refused(turn, refused):
    """Both cross-view heads place the other view as if camera j were turned by ``turn``
    rad about camera i's centre: the dense fit follows as a rotation that leaves camera j
    where the consensus places it (a shift under 0.05 depths, which the camera's test alone
    keeps) but moves view j's points by about ``2 sin(turn / 2)`` of their range: at 0.5 rad
    (0.48) beyond ``dense_max_shift_ratio``, so the consensus's pose is kept (and counted as
    refused by the points); at 0.1 rad (0.10) the dense fit is kept."""
    truth = _true_T_ij()
    pred_ij, pred_ji = _predictions(truth, seed=3, noise=0.01)
    rotation = sim3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, turn, 0.0, 0.0], dtype=torch.float64))
    believed = sim3_compose(rotation, truth)
    pred_ij.X_ji[:] = sim3_act(rotation, pred_ij.X_ji)  # view j in camera i, turned
    pred_ji.X_ji[:] = sim3_act(  # view i in camera j, as the turned camera j sees it
        sim3_compose(sim3_inverse(truth), sim3_inverse(rotation)), sim3_act(truth, pred_ji.X_ji)
    )
    config = RegistrationConfig()
    stats = RegistrationStats()
    registration = register_predictions(pred_ij, pred_ji, config, generator(0, "pair"), stats)
    dense = dense_similarity(pred_ij, pred_ji)
    assert _errors(dense, believed)[0] < 0.01  # the dense fit followed the heads
    assert camera_shift(truth, dense, pred_ij.X_ii) < 0.05  # the camera barely moved
    # a little less for points near the axis: 0.48 at 0.5 rad
    moved = points_shift(truth, dense, pred_ji.X_ii)
    assert moved == pytest.approx(2 * math.sin(turn / 2), abs=0.03)
    assert registration.T_ij is not None
    assert torch.equal(registration.T_ij, dense) != refused
    assert stats.dense_fits_refused == stats.dense_fits_refused_points == int(refused)
    assert _errors(registration.T_ij, truth)[0] < (0.02 if refused else 0.12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_points_shift_is_relative_to_each_points_range(dtype):
    """Camera j's points at depths 2, 4 and 5 on its axis (camera j = camera i), moved 1
    unit sideways by the second estimate: 0.5, 0.25, 0.2 of their range, median 0.25; points
    that are not finite or not in front of camera j are left out (with the two behind it,
    at 1/0.1 and 1/0.2, the median would be 0.5)."""
    T_a = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0], dtype=torch.float64)
    T_b = T_a.clone()
    T_b[0] = 1.0
    X_jj = torch.zeros(2, 3, 3, dtype=dtype)
    X_jj[..., 2] = torch.tensor([[2.0, 4.0, 5.0], [-0.1, -0.2, float("nan")]], dtype=dtype)
    assert points_shift(T_a, T_b, X_jj) == pytest.approx(0.25)
    assert points_shift(T_a, T_a, X_jj) == 0.0
    X_jj[..., 2] = -1.0  # no point in front of camera j
    assert points_shift(T_a, T_b, X_jj) == math.inf
