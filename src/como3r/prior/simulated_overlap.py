"""The ``v2`` model's confidence of a pair from what its two images reveal (item 13 of
:mod:`como3r.prior.simulated_errors`), and its confidence logits as a whole.

In the ``realistic`` model a pair's confidence knows the true overlap: a pixel is lowered
when its appearance key has no counterpart in the other view, and a pair whose keys do not
support a similarity fit is lowered as a whole unless a coin says it hallucinates. Here a
pixel's drop comes from the *descriptor agreement of the correspondence the pair predicts*:
each pixel is placed in the other camera by the pose the matcher believes (the key fit, or
the random pose of a pair it could not fit, before the pose noise and gross failures that
the confidence never knows), projected into the other image, and its clean descriptor
compared with the one that image has there (:func:`agreement`); occluded and out-of-view
pixels disagree. The pair's drop comes from *appearance similarity* alone, no pose: how
well pixels of j find a look-alike anywhere in i (:func:`look_alike_evidence`), weighted
by the texture weight ``w`` of item 9. A look-alike wrong place (one wallpaper in two
rooms, aliased façades) is confident; a true overlap on flat paint looks like any flat
paint and gives little evidence. Nothing here looks at the true geometry or at which keys
coincide.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.prior.simulated_appearance import AppearanceConstants, local_error
from como3r.prior.simulated_confidence import base_logits
from como3r.prior.simulated_encoding import SimulatedConstants, SimulatedEncoding
from como3r.prior.simulated_errors import error_logit
from como3r.prior.simulated_keys import reproducible_matmul


@dataclass(frozen=True)
class OverlapConstants:
    """Fixed shape of the ``v2`` overlap evidence (module docstring; every value OUR
    ASSUMPTION, set from the measured descriptor agreements on our synthetic scenes,
    ``benchmarks/prior_statistics.py``).

    ``agreement_floor``: cosine of two clean descriptors at or below which a predicted
    correspondence is no evidence of overlap, ``agreement_full`` at or above which it is
    full evidence (one key seen from two frames: 0.95 and above; the best look-alike of a
    pixel of another room's textures: around 0.65). ``look_alike_samples`` pixels of view j
    search their best look-alike in a grid of ``look_alike_grid`` pixels along view i's
    long side (:func:`look_alike_evidence`); that pair evidence is about 0.35 for pairs
    without overlap in the textured ``default`` rooms and 0.45-0.9 for pairs that share a
    third to nine tenths of their pixels. The pair drop falls linearly from all of it at
    ``evidence_none`` to none at ``evidence_full``.
    ``pixel_drop`` / ``pair_drop``: logit drops of a pixel and of a pair without evidence
    (the ``realistic`` model's ``weak_unmatched_drop`` and ``weak_no_overlap_drop``).
    ``pair_noise``: RMS of a per-pair logit offset (MASt3R's confidence level varies from
    pair to pair with the scene content).
    """

    agreement_floor: float = 0.6
    agreement_full: float = 0.9
    look_alike_samples: int = 400
    look_alike_grid: int = 96
    evidence_none: float = 0.3
    evidence_full: float = 0.7
    pixel_drop: float = 0.5
    pair_drop: float = 1.5
    pair_noise: float = 0.5


def believed_pixels(points: Tensor, K: Tensor, shape: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Where ``points`` ``(H, W, 3)`` of a target camera's frame fall in its image ``shape``:
    flat pixel indices ``(H * W,)`` (0 where outside) and ``(H, W)`` bool inside (in front,
    within the image)."""
    Ht, Wt = shape
    z = points[..., 2]
    front = z > 1e-9
    safe = torch.where(front, z, torch.ones_like(z))
    u = (K[0, 0] * points[..., 0] / safe + K[0, 2]).round()
    v = (K[1, 1] * points[..., 1] / safe + K[1, 2]).round()
    inside = front & (u >= 0) & (u < Wt) & (v >= 0) & (v < Ht)
    index = torch.where(inside, v * Wt + u, torch.zeros_like(u)).long()
    return index.reshape(-1), inside


def agreement(source: Tensor, target: Tensor, index: Tensor, inside: Tensor) -> Tensor:
    """``(H, W)`` cosine between each pixel's descriptor ``source`` ``(H, W, d)`` and the
    target's ``(Ht, Wt, d)`` at its predicted pixel ``index`` ``(H * W,)``; -1 outside."""
    d = source.shape[-1]
    there = target.reshape(-1, d)[index].float()
    cosine = (source.reshape(-1, d).float() * there).sum(-1).reshape(inside.shape)
    return torch.where(inside, cosine, torch.full_like(cosine, -1.0))


def pixel_evidence(cosine: Tensor) -> Tensor:
    """``(H, W)`` evidence in [0, 1] of a predicted correspondence from its agreement."""
    c = OverlapConstants
    return ((cosine - c.agreement_floor) / (c.agreement_full - c.agreement_floor)).clamp(0, 1)


def look_alike_evidence(
    enc_i: SimulatedEncoding, enc_j: SimulatedEncoding, gen: torch.Generator
) -> float:
    """The pair's evidence of overlap: how well ``look_alike_samples`` random valid pixels
    of j find a look-alike anywhere in i (best cosine of their clean descriptors over i's
    pixels on a grid of ``look_alike_grid`` along its long side, :func:`pixel_evidence`),
    weighted by their texture weight ``w`` (item 9): the mean of ``w e``. It looks at
    descriptors only, not at any pose: one wallpaper seen in two places looks like overlap.
    """
    c = OverlapConstants
    assert enc_j.texture is not None
    valid = enc_j.valid.reshape(-1).nonzero()[:, 0]
    if valid.numel() == 0:
        return 0.0
    pick = torch.randperm(valid.numel(), generator=gen)[: c.look_alike_samples]
    samples = valid[pick.to(valid.device)]
    d = enc_j.descriptors.shape[-1]
    step = max(1, round(max(enc_i.shape) / c.look_alike_grid))
    grid = enc_i.descriptors[::step, ::step].reshape(-1, d).float()
    queries = enc_j.descriptors.reshape(-1, d)[samples].float()
    # one rank-1 term at a time: a fixed summation order (a max of cosines decides a
    # confidence, so it must not change by an ulp between calls) without the
    # (samples, grid, d) intermediate of reproducible_matmul
    cosine = torch.zeros(queries.shape[0], grid.shape[0], device=grid.device)
    for k in range(d):
        cosine.add_(queries[:, k : k + 1] * grid[:, k])
    evidence = pixel_evidence(cosine.max(-1).values)
    return float((enc_j.texture.reshape(-1)[samples] * evidence).mean())


def pair_evidences(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    pose: tuple[Tensor, Tensor, Tensor],
    gen: torch.Generator,
) -> tuple[Tensor, Tensor, float]:
    """Evidence of every valid pixel of i and of j ``(H, W)`` (0 elsewhere) from the
    agreement of its predicted correspondence, and of the pair
    (:func:`look_alike_evidence`).

    Args:
        enc_i, enc_j: ``v2`` encodings (``texture`` set).
        pose: ``(R (3, 3), t (3,), s ())`` the similarity ``x_i = s R x_j + t`` the matcher
            believes (module docstring).
        gen: draws the look-alike samples.
    """
    R, t, s = pose
    points_j = enc_j.rays * enc_j.ranges[..., None]
    points_i = enc_i.rays * enc_i.ranges[..., None]
    j_in_i = s * reproducible_matmul(points_j, R.T) + t
    i_in_j = reproducible_matmul(points_i - t, R) / s.clamp_min(1e-12)
    out = []
    for src, dst, moved in ((enc_i, enc_j, i_in_j), (enc_j, enc_i, j_in_i)):
        index, inside = believed_pixels(moved, dst.K, dst.shape)
        cosine = agreement(src.descriptors, dst.descriptors, index, inside & src.valid)
        out.append(torch.where(src.valid, pixel_evidence(cosine), torch.zeros_like(cosine)))
    return out[0], out[1], look_alike_evidence(enc_i, enc_j, gen)


def pair_drop(pair: float, hallucinated: bool, noise: float) -> float:
    """Logit drop of the pair's ``C_ji``: ``pair_drop`` times the
    missing share of the evidence (0 at ``evidence_full`` and above, all of it at
    ``evidence_none`` and below), none for a pair that hallucinates, plus the pair's offset
    ``pair_noise n`` (``noise`` is ``n``)."""
    c = OverlapConstants
    missing = (c.evidence_full - pair) / (c.evidence_full - c.evidence_none)
    return c.pair_drop * (0.0 if hallucinated else min(1.0, max(0.0, missing))) + (
        c.pair_noise * noise
    )


def v2_logits(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    pose: tuple[Tensor, Tensor, Tensor],
    errors_ij: tuple[Tensor, Tensor],
    config: SimulatedPriorConfig,
    constants: SimulatedConstants,
    descriptor_noise: float,
    gen: torch.Generator,
) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]:
    """The ``v2`` logits ``log(C_ii - 1), log(C_ji - 1), log Q_ii, log Q_ji`` (each
    ``(H, W)`` of its view, before the confidence noise) and the descriptor noise RMS maps
    of i and j: the range and edge cues, items 9 and 11 (texture weight, local error only)
    and the overlap evidence above (item 13) in place of the key counterparts.

    Args:
        pose: the believed similarity of :func:`pair_evidences`.
        errors_ij: the ``(H, W)`` injected log-range errors of ``X_ii`` and of view j.
        constants: the prior's sensor constants (confidence curves).
        descriptor_noise: the pair's descriptor noise RMS before the texture gain.
        gen: the pair's generator for the hallucination coin and the pair offset.
    """
    a = AppearanceConstants
    c = OverlapConstants
    assert enc_i.texture is not None and enc_j.texture is not None
    logits = []
    noises = []
    for enc, error in ((enc_i, errors_ij[0]), (enc_j, errors_ij[1])):
        conf, desc_conf = base_logits(enc, constants)
        # out-of-distribution sky: low but not zero (item 14)
        conf = torch.where(enc.valid, conf, conf + enc.sky_logit_raise)
        flat = 1.0 - enc.texture
        # what the confidence takes for texture (low light's noise included, item 14)
        looks_flat = flat if enc.confidence_texture is None else 1.0 - enc.confidence_texture
        known = local_error(error, enc.valid)
        logits.append(
            (
                conf - a.conf_texture_drop * looks_flat - error_logit(known, config),
                desc_conf - a.contrast_q_drop * looks_flat,
            )
        )
        noises.append(descriptor_noise * (1.0 + a.contrast_noise_gain * flat))
    evidence_i, evidence_j, pair = pair_evidences(enc_i, enc_j, pose, gen)
    # the coin is drawn for every pair: whether a pair hallucinates does not look at truth
    hallucinated = float(torch.rand((), generator=gen)) < config.hallucination_rate
    drop = pair_drop(pair, hallucinated, float(torch.randn((), generator=gen)))
    drop_i = c.pixel_drop * (1.0 - evidence_i) * enc_i.valid
    drop_j = c.pixel_drop * (1.0 - evidence_j) * enc_j.valid
    (conf_i, q_i), (conf_j, q_j) = logits
    # the pair's drop lowers its geometry (C_ji), not the matchability of its pixels (Q):
    # on Q it made the share of consecutive low-texture pixels above tracking's absolute
    # Q_min jump from pair to pair (0.01-0.86) and tracking lost frames
    return (conf_i, conf_j - drop_j - drop, q_i - drop_i, q_j - drop_j), (noises[0], noises[1])
