"""A simulated prior's pair (:mod:`.simulated`): a view's noisy pointmap as one decode
observes it, and the realistic models' prediction of a pair (:mod:`.simulated_errors`, with
the ``v2`` appearance of :mod:`.simulated_appearance` and :mod:`.simulated_overlap`).
:class:`~.simulated.SimulatedPrior` fits the pose and draws the pair's seeds; these turn
them into MASt3R's outputs."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.prior import simulated_appearance as appearance_model
from como3r.prior import simulated_errors as errors
from como3r.prior.base import PairPrediction
from como3r.prior.simulated_confidence import (
    confidence,
    descriptor_confidence,
    noisy_descriptors,
    realistic_logits,
)
from como3r.prior.simulated_encoding import SimulatedConstants, SimulatedEncoding
from como3r.prior.simulated_fit import random_pose
from como3r.prior.simulated_keys import KeyMatches, generator, reproducible_matmul
from como3r.prior.simulated_overlap import v2_logits


def decode_realistic(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    matches: KeyMatches,
    pose: tuple[Tensor, Tensor, Tensor],
    overlap: bool,
    scale: float,
    gen: torch.Generator,
    config: SimulatedPriorConfig,
    constants: SimulatedConstants,
) -> PairPrediction:
    """The realistic models' prediction of the pair (i, j) from the fitted (or random)
    ``pose`` (:mod:`~como3r.prior.simulated_errors`): gross failures and confident
    hallucinations, heavy-tailed pose error, scale drift, confidence that falls with the
    injected error and viewpoint-dependent descriptor noise; ``v2`` (``config.model``) adds
    per-pair rays and confidence from what the images reveal."""
    appearance = config.model == errors.V2
    extra = generator(
        config.seed, "realistic pair", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
    )
    hallucinated = (
        not overlap and float(torch.rand((), generator=extra)) < config.hallucination_rate
    )
    failed = overlap and float(torch.rand((), generator=extra)) < config.gross_failure_rate
    R, t, s = pose
    change = errors.viewpoint_change(R, enc_i.median_range, enc_j.median_range)
    if failed:
        R, t, s = random_pose(enc_i, constants, extra)
    R, t = errors.perturb_pose_realistic(R, t, enc_i.median_range, config, extra)
    scale *= math.exp(errors.scale_drift(config, enc_i.agent, enc_i.index))
    X_ii, error_i = observe(enc_i, gen, config, constants)
    X_j, error_j = observe(enc_j, gen, config, constants)
    # view j's observed ranges on its true rays, moved by the pair's (erroneous) pose
    # into camera i and bent as camera i is believed to be
    on_rays_j = enc_j.rays * X_j.norm(dim=-1, keepdim=True)
    X_j_in_i = s * reproducible_matmul(on_rays_j, R.T) + t
    X_ji = scale * errors.in_believed_camera(X_j_in_i, enc_i.rays, enc_i.pred_rays, enc_i.K)
    if appearance:  # v2: per-pair rays, the two heads apart (item 12)
        heads = generator(
            config.seed, "v2 pair rays", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
        )
        X_ii = appearance_model.jitter_rays(X_ii, enc_i.K, config, heads)
        X_ji = appearance_model.jitter_rays(X_ji, enc_i.K, config, heads)
    noise = config.confidence_noise
    descriptor_noise = config.descriptor_noise * (1.0 + config.descriptor_viewpoint_gain * change)
    if appearance:  # v2: confidence from what the images reveal (items 9-13)
        pair_gen = generator(
            config.seed, "v2 pair confidence", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
        )
        (conf_i, conf_j, q_i, q_j), (noise_i, noise_j) = v2_logits(
            enc_i,
            enc_j,
            pose,
            (error_i, error_j),
            config,
            constants,
            descriptor_noise,
            pair_gen,
        )
    else:
        conf_i, conf_j, q_i, q_j = realistic_logits(
            enc_i,
            enc_j,
            matches,
            overlap or hallucinated,
            (error_i, error_j),
            config,
            constants,
        )
        noise_i = noise_j = descriptor_noise
    return PairPrediction(
        X_ii=scale * X_ii,
        X_ji=X_ji,
        C_ii=confidence(conf_i, gen, noise),
        C_ji=confidence(conf_j, gen, noise),
        D_ii=noisy_descriptors(enc_i, gen, noise_i),
        D_ji=noisy_descriptors(enc_j, gen, noise_j),
        Q_ii=descriptor_confidence(q_i, gen, noise),
        Q_ji=descriptor_confidence(q_j, gen, noise),
    )


def observe(
    enc: SimulatedEncoding,
    gen: torch.Generator,
    config: SimulatedPriorConfig,
    constants: SimulatedConstants,
) -> tuple[Tensor, Tensor]:
    """One noisy prediction of the view's own camera-frame pointmap ``(H, W, 3)`` along
    its predicted rays, and its log-range error ``(H, W)`` (0 on sky)."""
    H, W = enc.shape
    device = enc.rays.device
    field = errors.fourier_field(
        H,
        W,
        config.depth_distortion_wavelength * max(H, W),
        constants.distortion_modes,
        gen,
    ).to(device)
    noise = torch.randn(H, W, generator=gen).to(device)
    log_factor = (
        config.depth_distortion_amplitude * field + config.range_noise * noise + enc.log_range_error
    )
    low, high = (enc.sky_scale * x for x in constants.sky_range)
    sky = enc.median_range * (low + (high - low) * torch.rand(H, W, generator=gen).to(device))
    # the out-of-distribution error the confidence never sees (item 14)
    hidden = log_factor if enc.hidden_log_error is None else log_factor + enc.hidden_log_error
    ranges = torch.where(enc.valid, enc.ranges * torch.exp(hidden), sky)
    log_error = torch.where(enc.valid, log_factor, torch.zeros_like(log_factor))
    return enc.pred_rays * ranges[..., None], log_error
