"""The simulated prior's confidences and noisy descriptors: the pair-independent logits of
a view (range and edge cues), the ``easy`` model's confidences of a pair, and the noisy draws
``C = 1 + exp(logit + noise)``, ``Q = exp(logit + noise)`` and unit descriptors with noise,
each from the decode's seeded generator
(:meth:`SimulatedPrior.decode <como3r.prior.simulated.SimulatedPrior.decode>`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.prior.simulated_encoding import SimulatedConstants, SimulatedEncoding
from como3r.prior.simulated_errors import RealisticConstants, error_logit
from como3r.prior.simulated_keys import KeyMatches


def confidence(logit: Tensor, gen: torch.Generator, sigma: float) -> Tensor:
    """``C = 1 + exp(logit + noise)``, noise of RMS ``sigma``."""
    noise = torch.randn(logit.shape, generator=gen).to(logit.device)
    return 1.0 + torch.exp(logit + sigma * noise)


def descriptor_confidence(logit: Tensor, gen: torch.Generator, sigma: float) -> Tensor:
    """``Q = exp(logit + noise)``, noise of RMS ``sigma``."""
    noise = torch.randn(logit.shape, generator=gen).to(logit.device)
    return torch.exp(logit + sigma * noise)


def noisy_descriptors(
    enc: SimulatedEncoding, gen: torch.Generator, sigma: float | Tensor
) -> Tensor:
    """``(H, W, d)`` unit descriptors plus noise of RMS norm ``sigma`` (a number or an
    ``(H, W)`` map)."""
    d = enc.descriptors.shape[-1]
    noisy = torch.randn(enc.descriptors.shape, generator=gen).to(enc.descriptors.device)
    # in place: these are the largest tensors of a decode
    if isinstance(sigma, Tensor):
        noisy.mul_(sigma[..., None].to(noisy) / math.sqrt(d)).add_(enc.descriptors)
    else:
        noisy.mul_(sigma / math.sqrt(d)).add_(enc.descriptors)
    return noisy.div_(noisy.norm(dim=-1, keepdim=True).clamp_min_(1e-12))


def base_logits(enc: SimulatedEncoding, c: SimulatedConstants) -> tuple[Tensor, Tensor]:
    """Pair-independent ``log(C - 1)`` and ``log Q``: falling with range (relative to the
    median valid range) and at edges; ``C`` of filled holes is the sky's."""
    ranges, valid, edges = enc.ranges, enc.valid, enc.edges
    distance = torch.log1p(ranges / (c.conf_range_ref * enc.median_range))
    conf = c.conf_base - c.conf_range_slope * distance - c.conf_edge_drop * edges.float()
    desc_conf = c.q_base - c.q_range_slope * distance - c.q_edge_drop * edges.float()
    conf = torch.where(valid & ~enc.filled, conf, torch.full_like(conf, c.conf_sky))
    desc_conf = torch.where(valid, desc_conf, torch.full_like(desc_conf, c.q_sky))
    return conf, desc_conf


def easy_confidences(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    matches: KeyMatches,
    overlap: bool,
    c: SimulatedConstants,
    gen: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``C_ii, C_ji, Q_ii, Q_ji``: the range and edge cues of each view, lowered where a
    pixel's key has no counterpart in the other view (everywhere without overlap) and,
    without overlap, ``C_ji`` about 1 everywhere."""
    unmatched_i = ~matches.counterpart_i.view(enc_i.shape) & enc_i.valid
    unmatched_j = ~matches.counterpart_j.view(enc_j.shape) & enc_j.valid
    conf_i, desc_conf_i = base_logits(enc_i, c)
    conf_j, desc_conf_j = base_logits(enc_j, c)
    if not overlap:
        unmatched_i, unmatched_j = enc_i.valid, enc_j.valid
        conf_j = torch.full_like(conf_j, c.conf_no_overlap)
    return (
        confidence(conf_i, gen, c.conf_noise),
        confidence(conf_j - c.conf_unmatched_drop * unmatched_j.float(), gen, c.conf_noise),
        descriptor_confidence(
            desc_conf_i - c.q_unmatched_drop * unmatched_i.float(), gen, c.q_noise
        ),
        descriptor_confidence(
            desc_conf_j - c.q_unmatched_drop * unmatched_j.float(), gen, c.q_noise
        ),
    )


def realistic_logits(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    matches: KeyMatches,
    confident: bool,
    errors_ij: tuple[Tensor, Tensor],
    config: SimulatedPriorConfig,
    c: SimulatedConstants,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The ``realistic`` model's ``log(C_ii - 1), log(C_ji - 1), log Q_ii, log Q_ji`` before
    the noise (:mod:`~como3r.prior.simulated_errors`, item 7): the range and edge cues, the
    injected errors ``errors_ij`` ``(H, W)`` of ``X_ii`` and of view j, a weak drop where a
    pixel's key has no counterpart in the other view and, unless the pair is
    ``confident`` (its keys overlap, or it hallucinates), a weak drop of the pair."""
    r = RealisticConstants
    unmatched_i = ~matches.counterpart_i.view(enc_i.shape) & enc_i.valid
    unmatched_j = ~matches.counterpart_j.view(enc_j.shape) & enc_j.valid
    drop_i = r.weak_unmatched_drop * unmatched_i.float()
    drop_j = r.weak_unmatched_drop * unmatched_j.float()
    if not confident:
        drop_i, drop_j = drop_i + r.weak_no_overlap_drop, drop_j + r.weak_no_overlap_drop
    conf_i, q_i = base_logits(enc_i, c)
    conf_j, q_j = base_logits(enc_j, c)
    return (
        conf_i - error_logit(errors_ij[0], config),
        conf_j - error_logit(errors_ij[1], config) - drop_j,
        q_i - drop_i,
        q_j - drop_j,
    )
