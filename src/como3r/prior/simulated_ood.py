"""Out-of-distribution images for the ``v2`` simulated prior (item 14 of
:mod:`como3r.prior.simulated_errors`): blur, low light, sky and thin structures, each with
a failure mode of its own, scaled by ``simulated_prior.ood_severity`` (0, the default,
off; 1 the strongest we model) times a per-effect weight (``ood_blur``, ``ood_low_light``,
``ood_sky``, ``ood_thin``, default 1 each).

Blur and low light vary from image to image as a camera's exposure and motion do: image k
gets ``severity weight u_k`` with ``u_k`` in [0, 1], the normal CDF of a per-image draw
that is correlated along the sequence as the image's intrinsics error
(:class:`~como3r.prior.simulated_errors.ImageDraws`, own seed). Sky and thin structures are
properties of the scene and take ``severity weight`` wherever they occur. Every draw is
seeded by ``(config.seed, agent, index)`` and made at encode, so all pairs of an image
share it; with ``ood_severity = 0`` nothing is drawn and the model is ``v2`` unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.prior.simulated_appearance import (
    appearance_descriptors,
    cell_colours,
    texture_weight,
)
from como3r.prior.simulated_encoding import SimulatedConstants, normalize
from como3r.prior.simulated_errors import ImageDraws, fourier_field
from como3r.prior.simulated_keys import generator, stable_seed


@dataclass(frozen=True)
class OodConstants:
    """Strength of each effect at severity 1 (sources in
    :mod:`como3r.prior.simulated_errors`, item 14).

    ``blur_sigma`` and ``thin_width`` are fractions of the image's long side,
    ``low_light_noise`` is in intensity units of the prior's [-1, 1] image, ``*_bias`` and
    ``*_range_noise`` are log-range errors, ``sky_near_range`` a multiple of the view's
    median valid depth, ``sky_conf_raise`` a ``log(C - 1)`` step.
    """

    blur_sigma: float = 0.008
    blur_depth_bias: float = 0.06
    low_light_gain: float = 0.6
    low_light_noise: float = 0.15
    low_light_range_noise: float = 0.04
    low_light_descriptor_noise: float = 0.6
    sky_near_range: float = 2.0
    sky_conf_raise: float = 3.0
    thin_width: float = 0.012
    thin_jump: float = 0.1


@dataclass(frozen=True)
class OodImage:
    """What the out-of-distribution effects do to one image.

    Attributes:
        image: ``(3, H, W)`` the image the prior sees (blurred, darkened, noisy), in
            [-1, 1] before the noise.
        signal: ``(3, H, W)`` the same without the noise: the texture there is to match.
        descriptor_noise: RMS of the per-image noise on its clean descriptors (low light).
        known_log_error: ``(H, W)`` log-range error the confidence may see (low light's
            pixel noise: it differs from its neighbours).
        hidden_log_error: ``(H, W)`` log-range error the confidence never sees (blur's
            smooth bias, thin structures taken for their background).
        sky_scale: factor on the sky's range (below 1: a near wrong dome).
        sky_logit_raise: added to the sky's ``log(C - 1)``.
    """

    image: Tensor
    signal: Tensor
    descriptor_noise: float
    known_log_error: Tensor
    hidden_log_error: Tensor
    sky_scale: float
    sky_logit_raise: float


def _image_amount(config: SimulatedPriorConfig, agent: int, index: int) -> tuple[float, float]:
    """``(u_blur, u_low_light)`` in [0, 1] of image ``index`` (module docstring)."""
    draws = ImageDraws(config, stable_seed(config.seed, "ood"), agent, index)
    n = draws.normal(2)
    return tuple(0.5 * (1.0 + math.erf(float(v) / math.sqrt(2.0))) for v in n)  # type: ignore[return-value]


def _gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """``(C, H, W)`` image blurred by a separable Gaussian of ``sigma`` pixels (borders
    replicated); unchanged below a tenth of a pixel."""
    if sigma < 0.1:
        return image
    radius = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = (kernel / kernel.sum()).to(image)
    channels = image.shape[0]
    out = F.pad(image[None].float(), (radius, radius, radius, radius), mode="replicate")
    out = F.conv2d(out, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    out = F.conv2d(out, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)
    return out[0]


def thin_log_error(ranges: Tensor, valid: Tensor, width: int, strength: float) -> Tensor:
    """``(H, W)`` log-range error of thin structures: a valid pixel with a surface more than
    ``thin_jump`` (log) farther within ``width`` pixels is pulled ``strength`` of the way
    (in log range) to the farthest of them. A pole narrower than ``2 width`` disappears into
    its background, a wider object loses its rim; the depth edge itself moves."""
    if width < 1 or strength <= 0:
        return torch.zeros_like(ranges)
    size = 2 * width + 1
    near = torch.where(valid, ranges, torch.zeros_like(ranges))
    far = F.max_pool2d(near[None, None], size, stride=1, padding=width)[0, 0]
    jump = torch.log(far.clamp_min(1e-12)) - torch.log(ranges.clamp_min(1e-12))
    thin = valid & (jump > OodConstants.thin_jump)
    return torch.where(thin, strength * jump, torch.zeros_like(jump))


def ood_image(
    image: Tensor,
    ranges: Tensor,
    valid: Tensor,
    config: SimulatedPriorConfig,
    agent: int,
    index: int,
    sky_low: float,
) -> OodImage | None:
    """The out-of-distribution effects on one image, None when ``ood_severity`` is 0.

    Args:
        image: ``(3, H, W)`` the view's image in [-1, 1].
        ranges: ``(H, W)`` true ranges, valid where ``valid`` (the others are sky).
        sky_low: the near end of the sky's range (multiple of the median valid depth)
            without the effects; severity 1 moves it to ``sky_near_range``.
    """
    if config.ood_severity <= 0:
        return None
    c = OodConstants
    H, W = ranges.shape
    long_side = max(H, W)
    u_blur, u_dark = _image_amount(config, agent, index)
    blur = config.ood_severity * config.ood_blur * u_blur
    dark = config.ood_severity * config.ood_low_light * u_dark
    sky = config.ood_severity * config.ood_sky
    thin = config.ood_severity * config.ood_thin
    gen = generator(config.seed, "ood image", agent, index)
    seen = _gaussian_blur(image, blur * c.blur_sigma * long_side)
    gain = max(0.0, 1.0 - c.low_light_gain * dark)
    noise = torch.randn(seen.shape, generator=gen).to(seen)
    signal = (seen + 1.0) * gain - 1.0
    seen = signal + dark * c.low_light_noise * noise
    bias = fourier_field(H, W, long_side / 3.0, 8, gen).to(ranges)
    hidden = blur * c.blur_depth_bias * bias + thin_log_error(
        ranges, valid, round(thin * c.thin_width * long_side), thin
    )
    known = dark * c.low_light_range_noise * torch.randn(H, W, generator=gen).to(ranges)
    zero = torch.zeros_like(ranges)
    return OodImage(
        image=seen,
        signal=signal,
        descriptor_noise=dark * c.low_light_descriptor_noise,
        known_log_error=torch.where(valid, known, zero),
        hidden_log_error=torch.where(valid, hidden, zero),
        sky_scale=(c.sky_near_range / sky_low) ** sky,
        sky_logit_raise=sky * c.sky_conf_raise,
    )


def v2_appearance(
    image: Tensor,
    key_descriptors: Tensor,
    ranges: Tensor,
    valid: Tensor,
    config: SimulatedPriorConfig,
    agent: int,
    index: int,
    constants: SimulatedConstants,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor, OodImage | None]:
    """What the ``v2`` encoding takes from the image the prior sees (items 9, 10 and 14):
    ``(H, W, d)`` unit descriptors (the key's weighted by the texture weight, the rest the
    image patch's appearance, plus low light's per-image noise), the ``(H, W)`` texture
    weight of the signal, the texture weight the confidence sees (of the noisy image; None
    without out-of-distribution effects, when it is the same), the retrieval cells' colours
    and the out-of-distribution effects (None when off).

    Low light's pixel noise raises the local contrast: the confidence takes it for texture,
    but the key's share of a descriptor follows the texture the noise-free signal has, so
    noise never makes matching easier.

    Args:
        image: ``(3, H, W)`` the view's image in [-1, 1].
        key_descriptors: ``(H, W, d)`` unit descriptors of the appearance keys.
        ranges, valid: ``(H, W)`` true ranges and where they are valid.
        constants: the prior's sensor constants (sky range, retrieval cells).
    """
    image = image.to(key_descriptors.device)
    ood = ood_image(image, ranges, valid, config, agent, index, constants.sky_range[0])
    seen = ood.image if ood is not None else image
    texture = texture_weight(ood.signal if ood is not None else image)
    appearance = appearance_descriptors(seen, key_descriptors.shape[-1], config.seed)
    weight = texture[..., None]
    descriptors = normalize(weight * key_descriptors + (1.0 - weight) * appearance)
    if ood is not None and ood.descriptor_noise > 0:
        gen = generator(config.seed, "ood descriptors", agent, index)
        noise = torch.randn(descriptors.shape, generator=gen).to(descriptors)
        scale = ood.descriptor_noise / math.sqrt(descriptors.shape[-1])
        descriptors = normalize(descriptors + scale * noise)
    seen_texture = texture_weight(seen) if ood is not None else None
    return descriptors, texture, seen_texture, cell_colours(seen, constants.retrieval_stride), ood
