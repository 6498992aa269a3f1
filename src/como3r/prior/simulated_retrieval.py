"""Retrieval features of the simulated prior and their cached ASMK codebook.

MASt3R's retrieval head emits one descriptor per 16x16 token and keeps the tokens of
highest attention (MAST3R_SPEC.md §8.2). The simulated prior does the same from appearance
keys: a patch descriptor is the mean of a random-feature map
(:class:`~como3r.prior.simulated_keys.RandomFeatureMap`) over the keys of the patch, so two
views of the same place give similar patch descriptors and ASMK
(:mod:`como3r.prior.retrieval`) works unchanged. Its codebook is trained once by k-means on
the features of a fixed synthetic sample of patches and cached on disk.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.errors import PriorError
from como3r.prior.simulated_appearance import patch_appearance, random_patch_appearance
from como3r.prior.simulated_encoding import SimulatedConstants, SimulatedEncoding, normalize
from como3r.prior.simulated_keys import WORLD_KEY_ID, RandomFeatureMap, generator

logger = logging.getLogger(__name__)


def _noisy_unit(mean: Tensor, noise: float, gen: torch.Generator) -> Tensor:
    """Unit ``mean`` plus Gaussian noise of RMS norm ``noise``, renormalised."""
    perturbation = torch.randn(mean.shape, generator=gen).to(mean.device)
    unit = F.normalize(mean, dim=-1)
    return F.normalize(unit + noise / math.sqrt(mean.shape[-1]) * perturbation, dim=-1)


def patch_features(
    feature_map: RandomFeatureMap,
    key_ids: Tensor,
    key_coords: Tensor,
    footprint: Tensor,
    patch: int,
    stride: int,
    noise: float,
    gen: torch.Generator,
    appearance: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor]:
    """Descriptor and keyed fraction of every whole ``patch x patch`` patch of a view.

    Keys are sampled every ``stride`` pixels and their features blurred by that footprint.

    Args:
        feature_map: the retrieval feature map.
        key_ids: ``(H, W)`` int64, -1 where no key.
        key_coords: ``(H, W, 3)`` key coordinates, metres.
        footprint: ``(H, W)`` key-space pixel size, metres.
        patch: patch side in pixels (a multiple of ``stride``).
        stride: sampling step in pixels.
        noise: RMS norm of the per-view noise added to each unit descriptor.
        gen: generator of the noise.
        appearance: ``(P, d)`` unit appearance features and ``(P,)`` weights ``w`` of the
            keys (:func:`~como3r.prior.simulated_appearance.patch_appearance`): the noise is
            added to ``w`` times the unit key mean plus ``1 - w`` times the appearance;
            None: the key mean alone.

    Returns:
        ``(P, d)`` unit descriptors and ``(P,)`` fractions of keyed samples, patches in
        row-major order.
    """
    rows, cols = key_ids.shape[0] // patch, key_ids.shape[1] // patch
    window = (slice(stride // 2, rows * patch, stride), slice(stride // 2, cols * patch, stride))
    ids, coords = key_ids[window], key_coords[window]
    keyed = ids >= 0
    features = torch.zeros(*ids.shape, feature_map.dim, device=coords.device)
    if bool(keyed.any()):
        features[keyed] = feature_map(ids[keyed], coords[keyed], stride * footprint[window][keyed])
    per = patch // stride
    summed = features.reshape(rows, per, cols, per, -1).sum((1, 3)).reshape(rows * cols, -1)
    count = keyed.float().reshape(rows, per, cols, per).sum((1, 3)).reshape(-1)
    mean = summed / count.clamp_min(1.0)[:, None]
    if appearance is not None:
        mean = mix_appearance(mean, *appearance)
    return _noisy_unit(mean, noise, gen), count / (per * per)


def mix_appearance(keys: Tensor, appearance: Tensor, weight: Tensor) -> Tensor:
    """``w`` times the unit ``keys`` ``(P, d)`` plus ``1 - w`` times the unit ``appearance``
    ``(P, d)``, ``w`` = ``weight`` ``(P,)`` (not normalised)."""
    w = weight[:, None].to(keys)
    return w * F.normalize(keys, dim=-1) + (1.0 - w) * appearance.to(keys)


def select_patches(
    descriptors: Tensor, attention: Tensor, max_features: int, min_attention: float
) -> tuple[Tensor, Tensor]:
    """Top ``max_features`` patches by attention among those with at least
    ``min_attention`` (all patches if none has), highest first.

    Args:
        descriptors: ``(P, d)``.
        attention: ``(P,)``.

    Returns:
        ``(N, d)`` and ``(N,)``, ``N <= max_features``.
    """
    keep = attention >= min_attention
    if not bool(keep.any()):
        keep = torch.ones_like(keep)
    candidates = torch.nonzero(keep)[:, 0]
    order = torch.argsort(attention[candidates], descending=True, stable=True)
    chosen = candidates[order[:max_features]]
    return descriptors[chosen], attention[chosen]


def synthetic_patch_features(
    feature_map: RandomFeatureMap,
    count: int,
    patch: int,
    stride: int,
    noise: float,
    world_fraction: float,
    gen: torch.Generator,
) -> Tensor:
    """Descriptors ``(count, d)`` of random planar patches, sampled as :func:`patch_features`
    samples a view.

    A ``world_fraction`` of the patches carry world-coordinate keys in random 3-D planes
    within 200 m of the origin; the others show one of 256 textures at a random place of
    its first 100 m, in a random orientation. Pixel footprints are log-uniform between
    3 mm and 30 cm.
    """
    per = patch // stride
    world = torch.rand(count, generator=gen) < world_fraction
    ids = torch.where(world, WORLD_KEY_ID, torch.randint(0, 256, (count,), generator=gen))
    surface_origin = torch.cat(
        [100.0 * torch.rand(count, 2, generator=gen), torch.zeros(count, 1)], dim=-1
    )
    world_origin = 400.0 * torch.rand(count, 3, generator=gen) - 200.0
    origin = torch.where(world[:, None], world_origin, surface_origin)
    # in-plane axes: a random 2-D rotation of (s, t), or two random orthonormal 3-D vectors
    spatial_axes = torch.linalg.qr(torch.randn(count, 3, 3, generator=gen)).Q[..., :2]
    angle = 2.0 * math.pi * torch.rand(count, generator=gen)
    cos, sin, zero = torch.cos(angle), torch.sin(angle), torch.zeros(count)
    planar_axes = torch.stack(
        [torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1), torch.stack([zero, zero], -1)],
        dim=1,
    )
    axes = torch.where(world[:, None, None], spatial_axes, planar_axes)
    pixel = torch.exp(torch.empty(count).uniform_(math.log(3e-3), math.log(0.3), generator=gen))
    step = stride * pixel
    grid = (
        torch.stack(torch.meshgrid(torch.arange(per), torch.arange(per), indexing="ij"), dim=-1)
        .reshape(-1, 2)
        .float()
    )
    coords = origin[:, None] + step[:, None, None] * (grid @ axes.transpose(1, 2))
    samples = per * per
    features = feature_map(
        ids.repeat_interleave(samples), coords.reshape(-1, 3), step.repeat_interleave(samples)
    )
    return _noisy_unit(features.reshape(count, samples, -1).mean(1), noise, gen)


def view_features(
    retrieval_map: RandomFeatureMap, enc: SimulatedEncoding, c: SimulatedConstants, seed: int
) -> tuple[Tensor, Tensor]:
    """The retrieval features of a view
    (:meth:`SimulatedPrior.retrieval_features
    <como3r.prior.simulated.SimulatedPrior.retrieval_features>`): :func:`patch_features`
    of its keys, in the ``v2`` model mixed with its cells' appearance
    (:func:`~como3r.prior.simulated_appearance.patch_appearance`, item 10), then
    :func:`select_patches`. PriorError for a view smaller than a patch."""
    if min(enc.shape) < c.retrieval_patch:
        raise PriorError(
            f"simulated prior: a {enc.shape[1]}x{enc.shape[0]} view has no "
            f"{c.retrieval_patch}x{c.retrieval_patch} patch for retrieval"
        )
    gen = generator(seed, "retrieval", enc.agent, enc.index)
    appearance = None
    if enc.texture is not None and enc.colours is not None:
        appearance = patch_appearance(
            enc.colours, enc.texture, c.retrieval_patch, c.retrieval_stride, c.retrieval_dim, seed
        )
    descriptors, attention = patch_features(
        retrieval_map,
        enc.key_ids,
        enc.key_coords,
        enc.footprint,
        c.retrieval_patch,
        c.retrieval_stride,
        c.retrieval_noise,
        gen,
        appearance,
    )
    return select_patches(descriptors, attention, c.retrieval_max_features, c.retrieval_min_valid)


def codebook_sample(
    retrieval_map: RandomFeatureMap, c: SimulatedConstants, count: int, seed: int, appearance: bool
) -> Tensor:
    """``(count, retrieval_dim)`` retrieval features of random synthetic patches
    (:func:`synthetic_patch_features`) that the simulated prior's codebook is trained on,
    deterministic for ``seed``; with ``appearance`` (the ``v2`` model, item 10) mixed with
    the appearance of random smooth colour patches
    (:func:`~como3r.prior.simulated_appearance.random_patch_appearance`)."""
    gen = generator(seed, "codebook sample")
    sample = synthetic_patch_features(
        retrieval_map,
        count,
        c.retrieval_patch,
        c.retrieval_stride,
        c.retrieval_noise,
        c.codebook_world_fraction,
        gen,
    )
    if not appearance:
        return sample
    patches = random_patch_appearance(
        count, c.retrieval_patch, c.retrieval_stride, c.retrieval_dim, seed, gen
    )
    return normalize(mix_appearance(sample, *patches))


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/como3r``, or ``~/.cache/como3r`` when the variable is unset."""
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "como3r"


def cached_array(
    path: Path, shape: tuple[int, ...], compute: Callable[[], np.ndarray]
) -> np.ndarray:
    """The float32 array cached at ``path`` (``.npy``), computed and stored if absent.

    A file of another shape or dtype is recomputed. The file is written to a temporary
    name in the same folder and renamed, so concurrent processes never read half a file.
    """
    if path.is_file():
        array = np.load(path, allow_pickle=False)
        if array.shape == shape and array.dtype == np.float32:
            return array
        logger.warning("recomputing %s: it holds a %s %s array", path, array.dtype, array.shape)
    array = np.ascontiguousarray(compute(), dtype=np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.save(stream, array, allow_pickle=False)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return array
