"""The ``v2`` error model of the simulated prior: the ``realistic`` model
(:mod:`como3r.prior.simulated_errors`, items 1-8) plus what the image can reveal.

The ``v2`` model (towards a prior as hard as MASt3R; not the default) is the realistic model
plus what the image the prior sees can and cannot reveal (:class:`AppearanceConstants`,
every value OUR ASSUMPTION unless a source is named; items 13, overlap from descriptor
agreement, and 14, out-of-distribution images, are in :mod:`como3r.prior.simulated_errors`):

9. Descriptors from the image's local appearance. In ``realistic`` they are functions of the
   true surface keys alone, so flat paint matches as well as rich texture (93-96 % of the
   global nearest-neighbour matches within 2 px on the ``low-texture`` family as on textured
   scenes, ``benchmarks/prior_statistics.py``). Here a pixel's texture weight
   ``w = w0 + (1 - w0) c^2 / (c^2 + c_ref^2)`` comes from the local contrast ``c`` of the
   rendered image (RMS central-difference intensity gradient over a window of
   ``contrast_window`` of the long side, intensities in [-1, 1]),
   ``c_ref = contrast_ref = 0.02`` (on our synthetic scenes at 320x240 the median ``c`` is
   0.064 on the textured ``default`` rooms and 0.0007 on ``low-texture`` walls); the clean
   descriptor is ``w`` times the key's descriptor plus ``1 - w`` times an appearance
   descriptor of the image patch around the pixel (random Fourier features of its blurred
   colours sampled on a 3x3 grid, bandwidth ``appearance_bandwidth`` intensity units):
   equal for every pixel of one flat paint, so flat regions are ambiguous.
   ``w0 = context_weight = 0.25`` keeps some position information everywhere, as MASt3R's
   descriptors come from a ViT whose attention spans the whole pair (a flat wall's pixel
   still knows where its edges are). The per-pair descriptor noise is multiplied by
   ``1 + contrast_noise_gain (1 - w)`` (``contrast_noise_gain = 3``) and the descriptor
   confidence logit ``log Q`` lowered by ``contrast_q_drop (1 - w)``
   (``contrast_q_drop = 1.5``): a matcher is least sure where nothing can be told apart.
10. Retrieval features likewise: a patch's unit key feature is weighted by the mean ``w`` of
    its pixels and the rest is random Fourier features of the mean colours of its
    ``retrieval_stride`` cells, before the per-view noise, so places of one flat paint look
    alike to retrieval too. The ``v2`` codebook is trained on the synthetic key patches
    mixed so with random smooth colour patches (:func:`random_patch_appearance`).
11. Confidence does not know the low-frequency error. In ``realistic`` ``C`` falls with the
    pixel's whole injected error, its smooth per-image and per-pair distortion included
    (Spearman rho between ``log(C - 1)`` and ``|error|`` -0.58 for the smooth part alone on
    our scenes): a network that knew its low-frequency bias would correct it. Here item 7
    sees only the error minus its mean over a window of ``local_error_window = 1/8`` of the
    long side (:func:`local_error`): flying pixels, outliers and pixel noise, which differ
    from their neighbours. And ``log(C - 1)`` falls by ``conf_texture_drop (1 - w)``
    (``conf_texture_drop = 1.0``, ``w`` of item 9): where the image shows nothing, depth
    is a guess from context.
12. Intrinsics errors reach the correspondences. In ``realistic`` both pointmaps of a pair
    lie on one set of believed rays of camera i drawn once per image (item 1), so the
    correspondence ``X_ji`` implies is wrong by the pose error alone. MASt3R's ``X_ii``
    changes with the partner image and its two heads disagree; here each pair moves the
    normalised image coordinates of ``X_ii`` and, independently, of ``X_ji`` by a focal
    factor ``exp(pair_intrinsics_share focal_error n)`` and a principal-point shift of
    ``pair_intrinsics_share principal_point_error`` of the long side per axis
    (``pair_intrinsics_share = 0.25``: 2 % focal wobble between partners for an 8 % error
    per image), ranges kept (:func:`jitter_rays`). Zero when the image's intrinsics errors
    are zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.prior.simulated_keys import generator


@dataclass(frozen=True)
class AppearanceConstants:
    """Fixed shape of the ``v2`` model's image-derived descriptors (module docstring, 9).

    ``contrast_window`` and ``patch_step`` are fractions of the image's long side;
    ``contrast_ref`` and ``appearance_bandwidth`` are in intensity units of the prior's
    [-1, 1] image.
    """

    contrast_window: float = 1.0 / 48.0
    contrast_ref: float = 0.02
    context_weight: float = 0.25
    patch_step: float = 1.0 / 80.0
    appearance_bandwidth: float = 0.1
    contrast_noise_gain: float = 3.0
    contrast_q_drop: float = 1.5
    local_error_window: float = 1.0 / 8.0
    conf_texture_drop: float = 1.0
    pair_intrinsics_share: float = 0.25


def _box_mean(x: Tensor, size: int) -> Tensor:
    """``(H, W)`` mean of ``x`` over a ``size x size`` window (odd), borders renormalised."""
    return F.avg_pool2d(x[None, None], size, stride=1, padding=size // 2, count_include_pad=False)[
        0, 0
    ]


def jitter_rays(
    points: Tensor, K: Tensor, config: SimulatedPriorConfig, gen: torch.Generator
) -> Tensor:
    """``points`` ``(H, W, 3)`` of camera i with their normalised image coordinates
    ``x / z, y / z`` scaled by ``exp(-share focal_error n)`` and shifted by
    ``share principal_point_error`` of the long side (in pixels of ``K``'s focal) per axis,
    ranges kept; points at or behind the camera plane unchanged (module docstring, 12)."""
    share = AppearanceConstants.pair_intrinsics_share
    draws = torch.randn(3, generator=gen, dtype=torch.float64)
    factor = math.exp(-share * config.focal_error * float(draws[0]))
    focal = 0.5 * float(K[0, 0] + K[1, 1])
    long_side = max(points.shape[0], points.shape[1])
    shift = (share * config.principal_point_error * long_side / focal) * draws[1:].float()
    z = points[..., 2:]
    front = z[..., 0] > 1e-9
    xy = points[..., :2] / torch.where(front[..., None], z, torch.ones_like(z))
    xy = factor * xy + shift.to(xy)
    direction = F.normalize(torch.cat([xy, torch.ones_like(z)], dim=-1), dim=-1)
    moved = direction * points.norm(dim=-1, keepdim=True)
    return torch.where(front[..., None], moved, points)


def _box_sum(x: Tensor, size: int) -> Tensor:
    """``(H, W)`` float64 sum of ``x`` over a ``size x size`` window (odd; zeros outside), by
    an integral image: cost independent of ``size``."""
    pad = size // 2
    integral = F.pad(x.double(), (pad + 1, pad, pad + 1, pad)).cumsum(0).cumsum(1)
    return (
        integral[size:, size:]
        - integral[:-size, size:]
        - integral[size:, :-size]
        + integral[:-size, :-size]
    )


def local_error(log_error: Tensor, valid: Tensor) -> Tensor:
    """``(H, W)`` ``log_error`` minus its mean over the valid pixels of a window of
    ``local_error_window`` of the long side (0 where ``~valid``): the part of a pixel's
    error that the ``v2`` confidence sees (module docstring, 11)."""
    size = max(3, round(AppearanceConstants.local_error_window * max(log_error.shape)) | 1)
    weight = valid.to(log_error.dtype)
    mean = _box_sum(log_error * weight, size) / _box_sum(weight, size).clamp_min(1.0)
    return torch.where(valid, log_error - mean.to(log_error), torch.zeros_like(log_error))


def texture_weight(image: Tensor) -> Tensor:
    """``(H, W)`` weight ``w`` in ``[context_weight, 1]`` of the key in a pixel's descriptor,
    from the local contrast of ``image`` ``(3, H, W)`` in [-1, 1] (module docstring, 9)."""
    c = AppearanceConstants
    gray = image.float().mean(0)
    padded = F.pad(gray[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    # central differences: an edge counts on both of its sides
    gx = 0.5 * (padded[1:-1, 2:] - padded[1:-1, :-2])
    gy = 0.5 * (padded[2:, 1:-1] - padded[:-2, 1:-1])
    size = max(3, round(c.contrast_window * max(gray.shape)) | 1)
    energy = _box_mean(gx * gx + gy * gy, size)
    share = energy / (energy + c.contrast_ref**2)
    return c.context_weight + (1.0 - c.context_weight) * share


def appearance_descriptors(image: Tensor, dim: int, seed: int) -> Tensor:
    """``(H, W, dim)`` unit descriptors of the image patch around each pixel: random Fourier
    features ``cos(x A / bandwidth + b)`` of the 3x3-blurred colours ``x`` sampled on a 3x3
    grid of step ``patch_step`` of the long side (27 values; borders replicated)."""
    c = AppearanceConstants
    _, H, W = image.shape
    blurred = F.avg_pool2d(F.pad(image.float()[None], (1, 1, 1, 1), mode="replicate"), 3, stride=1)[
        0
    ]
    step = max(1, round(c.patch_step * max(H, W)))
    padded = F.pad(blurred[None], (step, step, step, step), mode="replicate")[0]
    samples = [
        padded[:, step + dv : step + dv + H, step + du : step + du + W]
        for dv in (-step, 0, step)
        for du in (-step, 0, step)
    ]
    patch = torch.cat(samples, dim=0).permute(1, 2, 0)  # (H, W, 27)
    return random_fourier(patch, dim, generator(seed, "appearance descriptor"))


def random_fourier(x: Tensor, dim: int, gen: torch.Generator) -> Tensor:
    """``(..., dim)`` unit random Fourier features ``cos(x A / appearance_bandwidth + b)`` of
    ``x`` ``(..., K)``, ``A`` standard normal and ``b`` uniform phases drawn from ``gen``:
    inputs closer than the bandwidth get similar features."""
    A = torch.randn(x.shape[-1], dim, generator=gen) / AppearanceConstants.appearance_bandwidth
    b = 2.0 * math.pi * torch.rand(dim, generator=gen)
    A = A.to(x)
    # one rank-1 term at a time: a fixed summation order (as reproducible_matmul) without
    # its (..., K, dim) intermediate
    phase = b.to(x).expand(*x.shape[:-1], dim).clone()
    for k in range(x.shape[-1]):
        phase.add_(x[..., k : k + 1] * A[k])
    return F.normalize(torch.cos(phase), dim=-1)


def cell_colours(image: Tensor, cell: int) -> Tensor:
    """``(H // cell, W // cell, 3)`` mean colour of each ``cell x cell`` block of ``image``
    ``(3, H, W)``: what the ``v2`` retrieval features see of the image."""
    return F.avg_pool2d(image.float()[None], cell)[0].permute(1, 2, 0).contiguous()


def patch_appearance(
    colours: Tensor, texture: Tensor, patch: int, cell: int, dim: int, seed: int
) -> tuple[Tensor, Tensor]:
    """Appearance features ``(P, dim)`` and texture weights ``(P,)`` of every whole
    ``patch x patch`` patch (row-major, as
    :func:`~como3r.prior.simulated_retrieval.patch_features`): random Fourier features of
    its cells' colours (``colours`` of :func:`cell_colours`) and the mean of ``texture``
    ``(H, W)`` (:func:`texture_weight`) over the patch (module docstring, 10)."""
    per = patch // cell
    rows, cols = texture.shape[0] // patch, texture.shape[1] // patch
    grid = colours[: rows * per, : cols * per].reshape(rows, per, cols, per, 3)
    flat = grid.permute(0, 2, 1, 3, 4).reshape(rows * cols, per * per * 3)
    weight = F.avg_pool2d(texture[None, None].float(), patch)[0, 0, :rows, :cols].reshape(-1)
    return random_fourier(flat, dim, generator(seed, "appearance retrieval")), weight


def random_patch_appearance(
    count: int, patch: int, cell: int, dim: int, seed: int, gen: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Appearance features and texture weights of ``count`` random patches for the ``v2``
    codebook sample: a uniform colour in [-1, 1] plus a linear ramp of up to 0.2 across the
    patch, weights uniform in ``[context_weight, 1]``."""
    per = patch // cell
    base = 2.0 * torch.rand(count, 1, 1, 3, generator=gen) - 1.0
    ramp = 0.2 * (2.0 * torch.rand(count, 2, 3, generator=gen) - 1.0)
    position = torch.linspace(-0.5, 0.5, per)
    colours = (
        base
        + position[None, :, None, None] * ramp[:, None, None, 0]
        + position[None, None, :, None] * ramp[:, None, None, 1]
    )
    w0 = AppearanceConstants.context_weight
    weight = w0 + (1.0 - w0) * torch.rand(count, generator=gen)
    return (
        random_fourier(colours.reshape(count, -1), dim, generator(seed, "appearance retrieval")),
        weight,
    )
