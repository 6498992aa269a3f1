"""The estimator of ``benchmarks/start_scale.py``: a robot's odometry start-scale error from
its own prior chain (``benchmarks/_start_scale.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from _start_scale import (  # noqa: E402
    StartScale,
    estimate_start_error,
    pair_log_sigma,
    start_discount,
    start_weights,
)

DECAY = 0.3 / 0.07  # the vio preset's convergence (0.3 scene depths) in keyframe spacings
GAPS = (1, 3, 5)


def _chain(start_error: float, prior_log_sigma: float, seed: int, count: int = 20):
    """Pairs ``(i, i + gap)`` of a robot driving one keyframe spacing per keyframe: the
    odometry's distance over the segment is stretched by ``1 + e0 exp(-d / DECAY)`` (the
    ``vio`` model of odometry_sim, e0 = 0 for a metric odometry), the prior's distance is
    the truth times 1.1 (its own scale) with a log-normal error."""
    rng = np.random.default_rng(seed)
    fine = np.linspace(0.0, count, 100 * count + 1)
    stretch = 1.0 + start_error * np.exp(-fine / DECAY)
    # odometry position along the path: the integral of the stretch
    travelled = np.concatenate([[0.0], np.cumsum((stretch[1:] + stretch[:-1]) / 2 * 0.01)])
    odometry_at = np.interp(np.arange(count + 1), fine, travelled)
    i = np.concatenate([np.arange(count + 1 - g) for g in GAPS])
    j = np.concatenate([np.arange(g, count + 1) for g in GAPS])
    truth = (j - i).astype(np.float64)
    prior = 1.1 * truth * np.exp(prior_log_sigma * rng.standard_normal(len(i)))
    # travelled in keyframe spacings of the odometry: its converged spacing is 1
    return odometry_at[j] - odometry_at[i], prior, i.astype(float), j.astype(float)


@pytest.mark.parametrize("start_error", [0.3, -0.3])
def test_a_vio_like_start_is_found_and_discounted(start_error):
    """A VIO-like chain (30 % off at the start, converging over 0.3 scene depths) under a
    prior of 5 % distance noise: e0 found within a factor of 2, the discount on."""
    found = [estimate_start_error(*_chain(start_error, 0.05, seed), DECAY) for seed in range(10)]
    for estimate in found:
        assert 0.5 * abs(start_error) < abs(estimate.error) < 2 * abs(start_error)
        assert np.sign(estimate.error) == np.sign(start_error)
        assert estimate.sigma < 0.1  # measured 0.024-0.047
        assert 0.5 * abs(start_error) < start_discount(estimate) < 2 * abs(start_error)


def test_a_metric_chain_gets_no_discount():
    """A metric odometry (ratio flat along the path) gets no discount: the ratio's own
    scale (the prior's 1.1) is not a start error."""
    for seed in range(10):
        estimate = estimate_start_error(*_chain(0.0, 0.05, seed), DECAY)
        assert abs(estimate.error) < 2.5 * estimate.sigma
        assert start_discount(estimate) == 0.0


def test_under_the_prior_v2_noise_a_vio_start_is_not_significant():
    """At the prior v2's measured distance noise (:func:`pair_log_sigma`, about 0.2-0.5 in
    log) one robot's 20 keyframes do not tell a 30 % start error from none: e0's standard
    error is about as large as the error itself (module docstring)."""
    sigmas = []
    for seed in range(10):
        od, pd, i, j = _chain(0.3, 0.0, seed)
        pd = pd * np.exp(
            pair_log_sigma(j - i) * np.random.default_rng(seed).standard_normal(len(i))
        )
        sigmas.append(estimate_start_error(od, pd, i, j, DECAY).sigma)
    assert 0.12 < np.median(sigmas) < 0.5  # measured 0.25


def test_too_few_pairs_give_no_estimate():
    estimate = estimate_start_error(
        np.array([1.0, 1.0]), np.array([1.0, 1.0]), np.array([0.0, 1.0]), np.array([1.0, 2.0]), 4.0
    )
    assert estimate == StartScale(0.0, float("inf"), 2)
    assert start_discount(estimate) == 0.0


def test_start_weights_average_the_decay_over_the_segment():
    g = start_weights(np.array([0.0, 2.0]), np.array([1e-4, 6.0]), 4.0)
    assert g[0] == pytest.approx(1.0, abs=1e-4)
    assert g[1] == pytest.approx(np.mean(np.exp(-np.linspace(2.0, 6.0, 100001) / 4.0)), rel=1e-4)
