"""The simulated prior: a seeded sensor simulator with MASt3R's outputs (README,
"Python API").

For scenes with metric depth it produces :class:`~como3r.prior.base.PairPrediction` s of
exactly MASt3R's types, shapes and value ranges from the true geometry, corrupted by a
documented error model that imitates a learned prior. It is a sensor simulator, not an
oracle: the ground-truth pose of a view is used only by :meth:`SimulatedPrior.encode` to
build world-coordinate appearance keys when a view has no surface map; no encoding stores it
and no prediction is made from it. The relative placement of view j in camera i is what a
learned matcher would believe: a robust similarity fit (RANSAC + :func:`umeyama_sim3`)
between the depth points of both views whose appearance keys coincide
(:mod:`como3r.prior.simulated_keys`). Truly overlapping views with unique textures get the
true relative pose, aliased views the wrong one, views without common keys a random one with
low confidence.

Error model (:class:`~como3r.config.SimulatedPriorConfig`, ``model`` key): the
``realistic`` default, the ``easy`` near-oracle or ``v2`` (the realistic model with
descriptors and confidence that depend on the image's local contrast, a confidence blind
to the low-frequency error and per-pair ray errors, in progress), documented parameter by
parameter, with their sources, in :mod:`como3r.prior.simulated_errors`. Draws that
belong to one image (its intrinsics and ray errors, its range-error field, flying pixels
and outliers) are made once at :meth:`SimulatedPrior.encode`, seeded by ``(config.seed,
agent, index)`` only, so every pair of that image shares them; per-pair draws are seeded
by ``(config.seed, agent and index of view i, agent and index of view j)``, so a decode is
deterministic and (i, j), (j, i) are independent. Every model places sky pixels (no
depth) at 10-20 times the view's median valid depth with confidence about 1, and every
length is relative to that median.

Sky is what a surface map says it is (texture id < 0). A view without a surface map has its
depth from a sensor (the Kinect of TUM RGB-D and 7-Scenes), whose holes are not the scene's
sky: the Kinect loses its structured light in the shadow a foreground edge casts on the
background, on dark, shiny or slanted surfaces and beyond its range, but a learned prior sees
a surface there in the colour image. :func:`fill_depth_holes` fills such holes with the
surface behind them. Their appearance is no worse than elsewhere (the hole is the depth
sensor's, not the image's), so their descriptors and ``Q`` are those of any pixel and they
are matched; their geometry is the simulator's guess, not a measurement, so its confidence
``C`` stays the sky's (about 1): tracking, fusion and the map weigh them down as before.
Depth edges are found on the measured depth alone. Treated as sky, the 28 %
of a TUM freiburg3_teddy frame without depth (12 % of 7-Scenes redkitchen) could never be
matched: the match fraction ``nu`` of tracking (C-Sec. 3.3) was capped at the measured
share, so a new keyframe came at ``nu < 0.333`` once 1 - 0.333 / 0.72 = 54 % of the
*visible* overlap was gone, not 67 %, and more of them on more holes.

The remaining shape of the model (confidence curves, sky range, RANSAC and feature-map
settings) is fixed by :class:`SimulatedConstants` and
:class:`~como3r.prior.simulated_errors.RealisticConstants` and reported by
:meth:`SimulatedPrior.describe` with the configuration.

Retrieval features are per 16x16 patch, from an independent random-feature map of the same
keys (:mod:`como3r.prior.simulated_retrieval`). :meth:`SimulatedPrior.codebook` trains their
ASMK codebook once by k-means on features of a fixed synthetic sample and caches it as
``simulated_codebook_<hash>.npy`` under ``$XDG_CACHE_HOME/como3r/`` (default
``~/.cache/como3r/``), the hash covering every parameter it depends on.

A view needs depth and intrinsics ``K``, plus a surface map or a ground-truth pose for its
keys. Decoding a 512x384 pair takes about 0.2 s on one CPU thread.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.errors import PriorError
from como3r.geometry.camera import rays_from_intrinsics, unproject_depth
from como3r.geometry.lie import quat_to_matrix, so3_exp
from como3r.geometry.units import median_of_ranges
from como3r.prior import simulated_errors as errors
from como3r.prior.base import Encoding, PairPrediction, Prior, View
from como3r.prior.ground_truth import GroundTruth, GroundTruthSource
from como3r.prior.simulated_fit import match_keys, robust_fit
from como3r.prior.simulated_keys import (
    KeyMatches,
    RandomFeatureMap,
    generator,
    key_footprint,
    keys_from_surface,
    keys_from_world,
    reproducible_matmul,
    stable_seed,
)
from como3r.prior.simulated_retrieval import (
    cached_array,
    default_cache_dir,
    mix_appearance,
    patch_features,
    select_patches,
    synthetic_patch_features,
)

logger = logging.getLogger(__name__)

CODEBOOK_CACHE_VERSION = 3
"""Bump when the codebook sample or the retrieval feature map changes."""


@dataclass(frozen=True)
class SimulatedConstants:
    """Fixed constants of the sensor model (reported by :meth:`SimulatedPrior.describe`).

    Logits are natural logs: ``C = 1 + exp(conf_*)``, ``Q = exp(q_*)``; ``sky_range`` and
    ``conf_range_ref`` are multiples of the view's median valid depth. ``*_wavelengths`` are
    the base bands (key units, metres) of the descriptor and retrieval feature maps, tiled
    over every scale, and ``*_coarse_footprints`` the wavelength in pixel footprints above
    which texture fades (:class:`~como3r.prior.simulated_keys.RandomFeatureMap`): what a
    view sees is relative to its pixels, not to the metre.
    """

    sky_range: tuple[float, float] = (10.0, 20.0)
    conf_base: float = 3.0
    conf_range_ref: float = 1.0
    conf_range_slope: float = 1.0
    conf_edge_drop: float = 2.0
    conf_unmatched_drop: float = 2.5
    conf_sky: float = -4.0
    conf_no_overlap: float = -3.0
    conf_noise: float = 0.1
    q_base: float = 2.5
    q_range_slope: float = 0.5
    q_edge_drop: float = 1.0
    q_unmatched_drop: float = 2.5
    q_sky: float = -1.5
    q_noise: float = 0.1
    edge_log_jump: float = 0.1
    distortion_modes: int = 8
    descriptor_wavelengths: tuple[float, float] = (0.05, 10.0)
    descriptor_coarse_footprints: float = 1024.0
    descriptor_id_weight: float = 1.0
    footprint_blur: float = 0.5
    footprint_max_ratio: float = 20.0
    cell_per_footprint: float = 2.0
    ransac_hypotheses: int = 128
    ransac_max_correspondences: int = 2048
    ransac_scored_correspondences: int = 512
    ransac_inlier_cells: float = 3.0
    refine_inlier_cells: tuple[float, ...] = (1.0, 0.1, 0.01, 0.01)
    newton_steps: int = 1
    min_overlap_fraction: float = 0.005
    min_inliers: int = 32
    random_pose_max_angle_deg: float = 45.0
    random_pose_distance: tuple[float, float] = (0.2, 1.0)
    retrieval_dim: int = 128
    retrieval_wavelengths: tuple[float, float] = (0.5, 20.0)
    retrieval_coarse_footprints: float = 1024.0
    retrieval_noise: float = 0.05
    retrieval_patch: int = 16
    retrieval_stride: int = 4
    retrieval_max_features: int = 300
    retrieval_min_valid: float = 0.5
    codebook_size: int = 1024
    codebook_samples_per_word: int = 24
    codebook_world_fraction: float = 0.25


@dataclass(frozen=True)
class SimulatedEncoding(Encoding):
    """Per-view state of the simulated prior (about 110 bytes per pixel). Holds no pose.

    Attributes:
        K: ``(3, 3)`` true intrinsics at the view's resolution.
        rays: ``(H, W, 3)`` unit rays of the pixels, camera frame.
        pred_rays: ``(H, W, 3)`` unit rays the prior predicts (``rays`` in the easy model).
        log_range_error: ``(H, W)`` this image's share of the log-range error (0 in the
            easy model).
        median_range: median measured (valid, not filled) range (the view's length unit).
        ranges: ``(H, W)`` true distance to the camera centre, 0 where ``~valid``.
        valid: ``(H, W)`` bool, pixels with depth, measured or filled (the others are sky).
        filled: ``(H, W)`` bool, valid pixels whose depth was filled into a sensor's hole
            (:func:`fill_depth_holes`).
        edges: ``(H, W)`` bool, valid pixels next to a depth discontinuity or the sky.
        key_ids: ``(H, W)`` int64 appearance-key ids, -1 where none.
        key_coords: ``(H, W, 3)`` float32 key coordinates (metres).
        footprint: ``(H, W)`` key-space pixel size (metres).
        median_footprint: median of ``footprint`` over keyed pixels (metres).
        descriptors: ``(H, W, d)`` float16 noise-free unit descriptors.
        texture: ``(H, W)`` float32 weight of the key in each descriptor, from the image's
            local contrast (:func:`~como3r.prior.simulated_errors.texture_weight`); None in
            the models that ignore the image (all but ``v2``).
        colours: ``(H // s, W // s, 3)`` float32 mean image colour of each ``s x s`` cell,
            ``s = retrieval_stride`` (:func:`~como3r.prior.simulated_errors.cell_colours`);
            None as ``texture``.
    """

    K: Tensor
    rays: Tensor
    pred_rays: Tensor
    log_range_error: Tensor
    median_range: float
    ranges: Tensor
    valid: Tensor
    filled: Tensor
    edges: Tensor
    key_ids: Tensor
    key_coords: Tensor
    footprint: Tensor
    median_footprint: float
    descriptors: Tensor
    texture: Tensor | None = None
    colours: Tensor | None = None


def _normalize(x: Tensor) -> Tensor:
    """Unit vectors along the last dimension."""
    return F.normalize(x, dim=-1)


def _depth_edges(depth: Tensor, valid: Tensor, log_jump: float) -> Tensor:
    """``(H, W)`` bool: pixels within one pixel of a depth discontinuity or the sky border."""
    log_depth = torch.log(depth.clamp_min(1e-6))
    edge = torch.zeros_like(valid)
    for dim in (0, 1):
        n = depth.shape[dim] - 1
        jump = (log_depth.narrow(dim, 1, n) - log_depth.narrow(dim, 0, n)).abs() > log_jump
        jump |= valid.narrow(dim, 1, n) != valid.narrow(dim, 0, n)
        edge.narrow(dim, 1, n).logical_or_(jump)
        edge.narrow(dim, 0, n).logical_or_(jump)
    dilated = F.max_pool2d(edge[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    return dilated & valid


def fill_depth_holes(depth: Tensor, valid: Tensor) -> Tensor:
    """``(H, W)`` depth with every hole (``~valid``) filled by the surface behind it.

    Pull-push over a pyramid of 2x2 maxima of the valid depth: a hole pixel takes the
    farthest valid depth of the smallest aligned block around it that has any (a block
    twice the hole's radius at most). The farthest, because a depth sensor's holes are
    mostly the background it could not see: the shadow beside a foreground edge and surfaces
    beyond its range; an average would float points between the two surfaces, as the
    flying pixels a learned prior is penalised for.

    Args:
        depth: ``(H, W)`` z-depth, anything where ``~valid``.
        valid: ``(H, W)`` bool, at least one True.
    """
    levels = [torch.where(valid, depth, torch.zeros_like(depth))[None, None]]
    factors = []  # per level, the block's (rows, columns): 1 along a side already 1 long
    while bool((levels[-1] <= 0).any()) and max(levels[-1].shape[-2:]) > 1:
        factors.append(tuple(min(2, n) for n in levels[-1].shape[-2:]))
        levels.append(F.max_pool2d(levels[-1], factors[-1], ceil_mode=True))
    filled = levels[-1]
    for level, (rows, cols) in zip(reversed(levels[:-1]), reversed(factors)):
        H, W = level.shape[-2:]
        coarse = filled.repeat_interleave(rows, -2).repeat_interleave(cols, -1)[..., :H, :W]
        filled = torch.where(level > 0, level, coarse)
    return filled[0, 0]


class SimulatedPrior(Prior):
    """Sensor simulator behind the :class:`~como3r.prior.base.Prior` interface.

    Args:
        config: error model (``simulated_prior`` section of the configuration).
        truth: where :meth:`encode` finds each view's ground truth (depth, intrinsics,
            surface keys or pose) by its agent and frame index; None for a prior that only
            decodes encodings made elsewhere (a coordinator).
        constants: fixed constants of the sensor model; the defaults are the documented ones.
    """

    def __init__(
        self,
        config: SimulatedPriorConfig | None = None,
        truth: GroundTruthSource | None = None,
        constants: SimulatedConstants | None = None,
    ) -> None:
        self.config = config or SimulatedPriorConfig()
        self.truth = truth
        self.constants = constants or SimulatedConstants()
        errors.check_config(self.config)
        self.realistic = self.config.model in errors.REALISTIC_MODELS
        self.appearance = self.config.model == errors.V2
        self.descriptor_dim = self.config.descriptor_dim
        c = self.constants
        ambiguity = self.config.descriptor_ambiguity if self.realistic else 0.0
        self._descriptor_map = RandomFeatureMap(
            self.config.descriptor_dim,
            self.config.seed,
            *c.descriptor_wavelengths,
            id_weight=c.descriptor_id_weight + ambiguity,
            blur=c.footprint_blur,
            coarse_footprints=c.descriptor_coarse_footprints,
            name="descriptor",
        )
        self._retrieval_map = RandomFeatureMap(
            c.retrieval_dim,
            self.config.seed,
            *c.retrieval_wavelengths,
            id_weight=1.0,
            blur=c.footprint_blur,
            coarse_footprints=c.retrieval_coarse_footprints,
            name="retrieval",
        )

    # ------------------------------------------------------------------ encode

    def encode(self, view: View) -> SimulatedEncoding:
        """Keys, true camera-frame geometry and noise-free descriptors of ``view``.

        Raises:
            PriorError: the prior has no ground-truth source, or the view's frame lacks
                depth or intrinsics ``K``, or has neither a surface map nor a ground-truth
                pose to make keys from, or its maps do not match the image size.
        """
        truth = self._truth_of(view)
        depth, K = self._validated_inputs(view, truth)
        H, W = view.shape
        valid = torch.isfinite(depth) & (depth > 0)
        depth = torch.where(valid, depth, torch.zeros_like(depth))
        filled = torch.zeros_like(valid)
        if truth.surface is None and bool(valid.any()):  # a sensor's holes (module docstring)
            depth, filled = fill_depth_holes(depth, valid), ~valid
            valid = torch.ones_like(valid)
        points = unproject_depth(depth, K)
        rays = rays_from_intrinsics(H, W, K)
        ranges = points.norm(dim=-1)
        if truth.surface is not None:
            key_ids, key_coords = keys_from_surface(truth.surface, valid)
        else:
            key_ids, key_coords = keys_from_world(points, truth.T_WC, valid)
        focal = 0.5 * float(K[0, 0] + K[1, 1])
        footprint = key_footprint(
            key_ids, key_coords, ranges / focal + 1e-9, self.constants.footprint_max_ratio
        )
        keyed = key_ids >= 0
        median_footprint = float(footprint[keyed].median()) if bool(keyed.any()) else 0.0
        if self.realistic:
            draws = errors.ImageDraws(self.config, self.config.seed, view.agent, view.index)
            pred_rays = errors.predicted_rays(K, H, W, self.config, draws)
            log_range_error = errors.image_log_range_error(ranges, valid, self.config, draws)
        else:
            pred_rays, log_range_error = rays, torch.zeros_like(ranges)
        descriptors = self._clean_descriptors(key_ids, key_coords, footprint)
        texture = colours = None
        if self.appearance:
            image = view.image.to(descriptors.device)
            texture = errors.texture_weight(image)
            appearance = errors.appearance_descriptors(image, self.descriptor_dim, self.config.seed)
            descriptors = _normalize(
                texture[..., None] * descriptors + (1.0 - texture[..., None]) * appearance
            )
            colours = errors.cell_colours(image, self.constants.retrieval_stride)
        return SimulatedEncoding(
            agent=view.agent,
            index=view.index,
            shape=(H, W),
            K=K,
            rays=rays,
            pred_rays=pred_rays,
            log_range_error=log_range_error,
            median_range=float(median_of_ranges(ranges.flatten(), (valid & ~filled).flatten())),
            ranges=ranges,
            valid=valid,
            filled=filled,
            edges=_depth_edges(depth, valid & ~filled, self.constants.edge_log_jump),
            key_ids=key_ids,
            key_coords=key_coords,
            footprint=footprint,
            median_footprint=median_footprint,
            # float16 as MASt3R-SLAM's matching kernels use them; far below the noise
            descriptors=descriptors.half(),
            texture=texture,
            colours=colours,
        )

    def _truth_of(self, view: View) -> GroundTruth:
        if self.truth is None:
            raise PriorError(
                f"simulated prior: no ground-truth source to encode agent "
                f"{view.agent}, frame {view.index} (it was built to decode only)"
            )
        return self.truth.truth(view.agent, view.index)

    @staticmethod
    def _validated_inputs(view: View, truth: GroundTruth) -> tuple[Tensor, Tensor]:
        """``(depth (H, W), K (3, 3))`` as float32; PriorError naming what is missing."""
        name = f"simulated prior: view (agent {view.agent}, frame {view.index})"
        missing = [
            what
            for what, value in (
                ("a depth map (depth/)", truth.depth),
                ("intrinsics K (calib.txt)", truth.K),
            )
            if value is None
        ]
        if truth.surface is None and truth.T_WC is None:
            missing.append("a surface map (surface/) or a ground-truth pose (groundtruth.txt)")
        if missing:
            raise PriorError(
                f"{name} lacks {' and '.join(missing)}, which the simulated "
                "prior needs; images alone take --prior mast3r"
            )
        H, W = view.shape
        if tuple(truth.depth.shape) != (H, W):
            raise PriorError(
                f"{name}: depth map of shape {tuple(truth.depth.shape)} does not "
                f"match the {W}x{H} image"
            )
        if truth.surface is not None and tuple(truth.surface.shape) != (H, W, 3):
            raise PriorError(
                f"{name}: surface map of shape {tuple(truth.surface.shape)}, expected ({H}, {W}, 3)"
            )
        if tuple(truth.K.shape) != (3, 3):
            raise PriorError(f"{name}: K of shape {tuple(truth.K.shape)}, expected (3, 3)")
        return truth.depth.to(torch.float32), truth.K.to(torch.float32)

    def _base_logits(self, enc: SimulatedEncoding) -> tuple[Tensor, Tensor]:
        """Pair-independent ``log(C - 1)`` and ``log Q``: falling with range (relative to the
        median valid range) and at edges; ``C`` of filled holes is the sky's."""
        c = self.constants
        ranges, valid, edges = enc.ranges, enc.valid, enc.edges
        distance = torch.log1p(ranges / (c.conf_range_ref * enc.median_range))
        conf = c.conf_base - c.conf_range_slope * distance - c.conf_edge_drop * edges.float()
        desc_conf = c.q_base - c.q_range_slope * distance - c.q_edge_drop * edges.float()
        conf = torch.where(valid & ~enc.filled, conf, torch.full_like(conf, c.conf_sky))
        desc_conf = torch.where(valid, desc_conf, torch.full_like(desc_conf, c.q_sky))
        return conf, desc_conf

    def _clean_descriptors(self, key_ids: Tensor, key_coords: Tensor, footprint: Tensor) -> Tensor:
        """``(H, W, d)`` unit descriptors of the keys; keyless pixels share the sky vector."""
        keyed = key_ids >= 0
        out = (
            self._descriptor_map.embedding(-1)
            .to(key_coords.device)
            .expand(*key_ids.shape, -1)
            .clone()
        )
        if bool(keyed.any()):
            out[keyed] = _normalize(
                self._descriptor_map(key_ids[keyed], key_coords[keyed], footprint[keyed])
            )
        return out

    # ------------------------------------------------------------------ decode

    def decode(self, enc_i: Encoding, enc_j: Encoding) -> PairPrediction:
        """Predict the ordered pair (i, j), both pointmaps in camera i (module docstring).

        Returns:
            PairPrediction with ``X_ii (H_i, W_i, 3)``, ``X_ji (H_j, W_j, 3)``, ``C > 1``,
            unit ``D`` of dimension ``config.descriptor_dim`` and ``Q > 0``, float32.
        """
        enc_i, enc_j = self._checked(enc_i), self._checked(enc_j)
        gen = generator(
            self.config.seed, "pair", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
        )
        scale = math.exp(self.config.scale_sigma * float(torch.randn((), generator=gen)))
        matches = match_keys(enc_i, enc_j, self.constants, gen)
        fitted = robust_fit(enc_i, enc_j, matches, self.constants, gen)
        overlap = fitted is not None
        R, t, s = fitted if overlap else self._random_pose(enc_i, gen)
        if self.realistic:
            return self._decode_realistic(enc_i, enc_j, matches, (R, t, s), overlap, scale, gen)
        R, t = errors.perturb_pose_easy(R, t, self.config, gen)
        X_ii, _ = self._observe(enc_i, gen)
        X_j, _ = self._observe(enc_j, gen)
        X_ji = scale * (s * reproducible_matmul(X_j, R.T) + t)
        C_ii, C_ji, Q_ii, Q_ji = self._confidences(enc_i, enc_j, matches, overlap, gen)
        noise = self.config.descriptor_noise
        return PairPrediction(
            X_ii=scale * X_ii,
            X_ji=X_ji,
            C_ii=C_ii,
            C_ji=C_ji,
            D_ii=self._noisy_descriptors(enc_i, gen, noise),
            D_ji=self._noisy_descriptors(enc_j, gen, noise),
            Q_ii=Q_ii,
            Q_ji=Q_ji,
        )

    def _decode_realistic(
        self,
        enc_i: SimulatedEncoding,
        enc_j: SimulatedEncoding,
        matches: KeyMatches,
        pose: tuple[Tensor, Tensor, Tensor],
        overlap: bool,
        scale: float,
        gen: torch.Generator,
    ) -> PairPrediction:
        """The realistic model's prediction from the fitted (or random) ``pose``
        (:mod:`~como3r.prior.simulated_errors`): gross failures and confident hallucinations,
        heavy-tailed pose error, scale drift, confidence that falls with the injected error
        and viewpoint-dependent descriptor noise."""
        cfg = self.config
        extra = generator(
            cfg.seed, "realistic pair", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
        )
        hallucinated = not overlap and float(torch.rand((), generator=extra)) < (
            cfg.hallucination_rate
        )
        failed = overlap and float(torch.rand((), generator=extra)) < cfg.gross_failure_rate
        R, t, s = pose
        change = errors.viewpoint_change(R, enc_i.median_range, enc_j.median_range)
        if failed:
            R, t, s = self._random_pose(enc_i, extra)
        R, t = errors.perturb_pose_realistic(R, t, enc_i.median_range, cfg, extra)
        scale *= math.exp(errors.scale_drift(cfg, enc_i.agent, enc_i.index))
        X_ii, error_i = self._observe(enc_i, gen)
        X_j, error_j = self._observe(enc_j, gen)
        # view j's observed ranges on its true rays, moved by the pair's (erroneous) pose
        # into camera i and bent as camera i is believed to be
        on_rays_j = enc_j.rays * X_j.norm(dim=-1, keepdim=True)
        X_j_in_i = s * reproducible_matmul(on_rays_j, R.T) + t
        X_ji = scale * errors.in_believed_camera(X_j_in_i, enc_i.rays, enc_i.pred_rays, enc_i.K)
        if self.appearance:  # v2: per-pair rays, the two heads apart (errors, item 12)
            heads = generator(
                cfg.seed, "v2 pair rays", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
            )
            X_ii = errors.jitter_rays(X_ii, enc_i.K, cfg, heads)
            X_ji = errors.jitter_rays(X_ji, enc_i.K, cfg, heads)
        r = errors.RealisticConstants
        unmatched_i = ~matches.counterpart_i.view(enc_i.shape) & enc_i.valid
        unmatched_j = ~matches.counterpart_j.view(enc_j.shape) & enc_j.valid
        drop_i = r.weak_unmatched_drop * unmatched_i.float()
        drop_j = r.weak_unmatched_drop * unmatched_j.float()
        if not (overlap or hallucinated):
            drop_i, drop_j = drop_i + r.weak_no_overlap_drop, drop_j + r.weak_no_overlap_drop
        conf_i, desc_conf_i = self._base_logits(enc_i)
        conf_j, desc_conf_j = self._base_logits(enc_j)
        noise = cfg.confidence_noise
        descriptor_noise = cfg.descriptor_noise * (1.0 + cfg.descriptor_viewpoint_gain * change)
        noise_i = noise_j = descriptor_noise
        known_i, known_j = error_i, error_j
        if enc_i.texture is not None and enc_j.texture is not None:  # v2 (errors, 9 and 11)
            a = errors.AppearanceConstants
            noise_i = descriptor_noise * (1.0 + a.contrast_noise_gain * (1.0 - enc_i.texture))
            noise_j = descriptor_noise * (1.0 + a.contrast_noise_gain * (1.0 - enc_j.texture))
            desc_conf_i = desc_conf_i - a.contrast_q_drop * (1.0 - enc_i.texture)
            desc_conf_j = desc_conf_j - a.contrast_q_drop * (1.0 - enc_j.texture)
            known_i = errors.local_error(error_i, enc_i.valid)
            known_j = errors.local_error(error_j, enc_j.valid)
            conf_i = conf_i - a.conf_texture_drop * (1.0 - enc_i.texture)
            conf_j = conf_j - a.conf_texture_drop * (1.0 - enc_j.texture)
        return PairPrediction(
            X_ii=scale * X_ii,
            X_ji=X_ji,
            C_ii=self._conf(conf_i - errors.error_logit(known_i, cfg), gen, noise),
            C_ji=self._conf(conf_j - errors.error_logit(known_j, cfg) - drop_j, gen, noise),
            D_ii=self._noisy_descriptors(enc_i, gen, noise_i),
            D_ji=self._noisy_descriptors(enc_j, gen, noise_j),
            Q_ii=self._desc_conf(desc_conf_i - drop_i, gen, noise),
            Q_ji=self._desc_conf(desc_conf_j - drop_j, gen, noise),
        )

    def _confidences(
        self,
        enc_i: SimulatedEncoding,
        enc_j: SimulatedEncoding,
        matches: KeyMatches,
        overlap: bool,
        gen: torch.Generator,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``C_ii, C_ji, Q_ii, Q_ji``: the range and edge cues of each view, lowered where a
        pixel's key has no counterpart in the other view (everywhere without overlap) and,
        without overlap, ``C_ji`` about 1 everywhere."""
        c = self.constants
        unmatched_i = ~matches.counterpart_i.view(enc_i.shape) & enc_i.valid
        unmatched_j = ~matches.counterpart_j.view(enc_j.shape) & enc_j.valid
        conf_i, desc_conf_i = self._base_logits(enc_i)
        conf_j, desc_conf_j = self._base_logits(enc_j)
        if not overlap:
            unmatched_i, unmatched_j = enc_i.valid, enc_j.valid
            conf_j = torch.full_like(conf_j, c.conf_no_overlap)
        return (
            self._conf(conf_i, gen, c.conf_noise),
            self._conf(conf_j - c.conf_unmatched_drop * unmatched_j.float(), gen, c.conf_noise),
            self._desc_conf(desc_conf_i - c.q_unmatched_drop * unmatched_i.float(), gen, c.q_noise),
            self._desc_conf(desc_conf_j - c.q_unmatched_drop * unmatched_j.float(), gen, c.q_noise),
        )

    @staticmethod
    def _checked(enc: Encoding) -> SimulatedEncoding:
        if not isinstance(enc, SimulatedEncoding):
            raise PriorError(
                f"simulated prior: cannot decode a {type(enc).__name__} "
                "(encode the view with the simulated prior)"
            )
        return enc

    def _random_pose(
        self, enc_i: SimulatedEncoding, gen: torch.Generator
    ) -> tuple[Tensor, Tensor, Tensor]:
        """A plausible wrong pose for views without common keys: near camera i, turned."""
        c = self.constants
        axis = _normalize(torch.randn(3, generator=gen))
        angle = math.radians(c.random_pose_max_angle_deg) * float(torch.rand((), generator=gen))
        direction = _normalize(torch.randn(3, generator=gen))
        low, high = c.random_pose_distance
        distance = enc_i.median_range * (low + (high - low) * float(torch.rand((), generator=gen)))
        device = enc_i.rays.device
        R = quat_to_matrix(so3_exp(axis * angle)).to(device)
        return R, (direction * distance).to(device), torch.ones((), device=device)

    def _observe(self, enc: SimulatedEncoding, gen: torch.Generator) -> tuple[Tensor, Tensor]:
        """One noisy prediction of the view's own camera-frame pointmap ``(H, W, 3)`` along
        its predicted rays, and its log-range error ``(H, W)`` (0 on sky)."""
        H, W = enc.shape
        device = enc.rays.device
        field = errors.fourier_field(
            H,
            W,
            self.config.depth_distortion_wavelength * max(H, W),
            self.constants.distortion_modes,
            gen,
        ).to(device)
        noise = torch.randn(H, W, generator=gen).to(device)
        log_factor = (
            self.config.depth_distortion_amplitude * field
            + self.config.range_noise * noise
            + enc.log_range_error
        )
        low, high = self.constants.sky_range
        sky = enc.median_range * (low + (high - low) * torch.rand(H, W, generator=gen).to(device))
        ranges = torch.where(enc.valid, enc.ranges * torch.exp(log_factor), sky)
        log_error = torch.where(enc.valid, log_factor, torch.zeros_like(log_factor))
        return enc.pred_rays * ranges[..., None], log_error

    @staticmethod
    def _conf(logit: Tensor, gen: torch.Generator, sigma: float) -> Tensor:
        """``C = 1 + exp(logit + noise)``, noise of RMS ``sigma``."""
        noise = torch.randn(logit.shape, generator=gen).to(logit.device)
        return 1.0 + torch.exp(logit + sigma * noise)

    @staticmethod
    def _desc_conf(logit: Tensor, gen: torch.Generator, sigma: float) -> Tensor:
        """``Q = exp(logit + noise)``, noise of RMS ``sigma``."""
        noise = torch.randn(logit.shape, generator=gen).to(logit.device)
        return torch.exp(logit + sigma * noise)

    @staticmethod
    def _noisy_descriptors(
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

    # ------------------------------------------------------------------ retrieval

    def retrieval_features(self, enc: Encoding) -> tuple[Tensor, Tensor]:
        """Per-16x16-patch retrieval descriptors of a view.

        Each patch averages the retrieval random features of its keys plus per-view noise
        (:func:`~como3r.prior.simulated_retrieval.patch_features`); its attention is the
        fraction of keyed (non-sky) pixels. As MASt3R's head keeps its top tokens by
        attention, the ``retrieval_max_features`` patches of highest attention among those
        with at least ``retrieval_min_valid`` are kept.

        Returns:
            ``(N, retrieval_dim)`` float32 unit descriptors and ``(N,)`` attention, highest
            first.
        """
        enc = self._checked(enc)
        c = self.constants
        if min(enc.shape) < c.retrieval_patch:
            raise PriorError(
                f"simulated prior: a {enc.shape[1]}x{enc.shape[0]} view has no "
                f"{c.retrieval_patch}x{c.retrieval_patch} patch for retrieval"
            )
        gen = generator(self.config.seed, "retrieval", enc.agent, enc.index)
        appearance = None
        if enc.texture is not None and enc.colours is not None:  # v2 (errors, item 10)
            appearance = errors.patch_appearance(
                enc.colours,
                enc.texture,
                c.retrieval_patch,
                c.retrieval_stride,
                c.retrieval_dim,
                self.config.seed,
            )
        descriptors, attention = patch_features(
            self._retrieval_map,
            enc.key_ids,
            enc.key_coords,
            enc.footprint,
            c.retrieval_patch,
            c.retrieval_stride,
            c.retrieval_noise,
            gen,
            appearance,
        )
        return select_patches(
            descriptors, attention, c.retrieval_max_features, c.retrieval_min_valid
        )

    def codebook(self, size: int | None = None, cache_dir: str | Path | None = None) -> np.ndarray:
        """ASMK codebook of the retrieval features, trained once and cached on disk.

        k-means (:func:`como3r.prior.retrieval.train_codebook`) on the retrieval features of
        ``codebook_samples_per_word * size`` random synthetic patches
        (:func:`~como3r.prior.simulated_retrieval.synthetic_patch_features`), deterministic
        for the seed. Cached as ``simulated_codebook_<hash>.npy`` in ``cache_dir`` (default
        ``$XDG_CACHE_HOME/como3r`` or ``~/.cache/como3r``), the hash covering the size, the
        seed and every constant; written atomically.

        Args:
            size: number of centroids; default ``constants.codebook_size``.
            cache_dir: cache folder.

        Returns:
            ``(size, retrieval_dim)`` float32 centroids.
        """
        from como3r.prior.retrieval import train_codebook  # deferred: imports faiss

        c = self.constants
        size = size or c.codebook_size
        directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        v2 = (repr(dataclasses.astuple(errors.AppearanceConstants())),) if self.appearance else ()
        digest = stable_seed(
            CODEBOOK_CACHE_VERSION, size, self.config.seed, repr(dataclasses.astuple(c)), *v2
        )

        def train() -> np.ndarray:
            logger.info("training the simulated prior's %d-word codebook (once)", size)
            count = size * c.codebook_samples_per_word
            gen = generator(self.config.seed, "codebook sample")
            sample = synthetic_patch_features(
                self._retrieval_map,
                count,
                c.retrieval_patch,
                c.retrieval_stride,
                c.retrieval_noise,
                c.codebook_world_fraction,
                gen,
            )
            if self.appearance:  # v2: key patches mixed with image appearance (errors, 10)
                mixed = mix_appearance(
                    sample,
                    *errors.random_patch_appearance(
                        count,
                        c.retrieval_patch,
                        c.retrieval_stride,
                        c.retrieval_dim,
                        self.config.seed,
                        gen,
                    ),
                )
                sample = _normalize(mixed)
            return train_codebook(sample.numpy(), size, self.config.seed)

        return cached_array(
            directory / f"simulated_codebook_{digest:016x}.npy", (size, c.retrieval_dim), train
        )

    # ------------------------------------------------------------------ report

    def describe(self) -> dict[str, object]:
        """Every parameter of the error model (reported with every result)."""
        out = {
            "name": type(self).__name__,
            **dataclasses.asdict(self.config),
            "constants": dataclasses.asdict(self.constants),
        }
        if self.realistic:
            out["realistic_constants"] = dataclasses.asdict(errors.RealisticConstants())
        if self.appearance:
            out["appearance_constants"] = dataclasses.asdict(errors.AppearanceConstants())
        return out
