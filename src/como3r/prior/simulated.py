"""The simulated prior: a seeded sensor simulator with MASt3R's outputs (manual:
docs/api/index.md, "The simulated prior").

For scenes with metric depth it produces :class:`~como3r.prior.base.PairPrediction` s of
exactly MASt3R's types, shapes and value ranges from the true geometry, corrupted by a
documented error model that imitates a learned prior. It is a sensor simulator, not an
oracle: the ground-truth pose of a view is used only by :meth:`SimulatedPrior.encode` to
build world-coordinate appearance keys when a view has no surface map; only the ground-truth
record the encoding keeps for its receivers stores it (:mod:`~como3r.prior.simulated_record`)
and no prediction is made from it. The relative placement of view j in camera i is what a
learned matcher would believe: a robust similarity fit (RANSAC +
:func:`~como3r.geometry.umeyama.umeyama_sim3`) between the depth points of both views whose
appearance keys coincide (:mod:`como3r.prior.simulated_keys`). Truly overlapping views with
unique textures get the true relative pose, aliased views the wrong one, views without common
keys a random one with low confidence.

Error model (:class:`~como3r.config.SimulatedPriorConfig`, ``model`` key): the
``realistic`` default, the ``easy`` near-oracle or ``v2`` (the realistic model with
descriptors and confidence that depend on the image's local contrast, a confidence blind
to the low-frequency error, per-pair ray errors, overlap judged from descriptor agreement
only and an out-of-distribution knob; not yet the default), documented parameter by
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
a surface there in the colour image.
:func:`~como3r.prior.simulated_encoding.fill_depth_holes` fills such holes with the surface
behind them. Their appearance is no worse than elsewhere (the hole is the depth
sensor's, not the image's), so their descriptors and ``Q`` are those of any pixel and they
are matched; their geometry is the simulator's guess, not a measurement, so its confidence
``C`` stays the sky's (about 1): tracking, fusion and the map weigh them down as before.
Depth edges are found on the measured depth alone. Treated as sky, the 28 %
of a TUM freiburg3_teddy frame without depth (12 % of 7-Scenes redkitchen) could never be
matched: the match fraction ``nu`` of tracking (C-Sec. 3.3) was capped at the measured
share, so a new keyframe came at ``nu < 0.333`` once 1 - 0.333 / 0.72 = 54 % of the
*visible* overlap was gone, not 67 %, and more of them on more holes.

The remaining shape of the model (confidence curves, sky range, RANSAC and feature-map
settings) is fixed by :class:`~como3r.prior.simulated_encoding.SimulatedConstants` and
:class:`~como3r.prior.simulated_errors.RealisticConstants` and reported by
:meth:`SimulatedPrior.describe` with the configuration.

Retrieval features are per 16x16 patch, from an independent random-feature map of the same
keys (:mod:`como3r.prior.simulated_retrieval`). :meth:`SimulatedPrior.codebook` trains their
ASMK codebook once by k-means on features of a fixed synthetic sample and caches it as
``simulated_codebook_<hash>.npy`` under ``$XDG_CACHE_HOME/como3r/`` (default
``~/.cache/como3r/``), the hash covering every parameter it depends on.

A view needs depth and intrinsics ``K``, plus a surface map or a ground-truth pose for its
keys, read through a lossless :class:`~como3r.prior.simulated_record.SimulatedTruthRecord`
that travels and is stored in place of the encoding. Decoding a 512x384 pair takes about 0.2 s on one CPU thread.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.config_simulated_prior import check_config
from como3r.errors import PriorError
from como3r.geometry.camera import rays_from_intrinsics, unproject_depth
from como3r.geometry.units import median_of_ranges
from como3r.prior import simulated_appearance as appearance_model
from como3r.prior import simulated_errors as errors
from como3r.prior.base import Encoding, EncodingRecord, PairPrediction, Prior, View
from como3r.prior.ground_truth import GroundTruth, GroundTruthSource
from como3r.prior.simulated_confidence import (
    easy_confidences,
    noisy_descriptors,
)
from como3r.prior.simulated_encoding import (
    SimulatedConstants,
    SimulatedEncoding,
    checked_encoding,
    depth_edges,
    fill_depth_holes,
    normalize,
    validated_inputs,
)
from como3r.prior.simulated_fit import match_keys, random_pose, robust_fit
from como3r.prior.simulated_keys import (
    RandomFeatureMap,
    generator,
    key_footprint,
    keys_from_surface,
    keys_from_world,
    reproducible_matmul,
    stable_seed,
)
from como3r.prior.simulated_ood import OodConstants, v2_appearance
from como3r.prior.simulated_overlap import OverlapConstants
from como3r.prior.simulated_pair import decode_realistic, observe
from como3r.prior.simulated_record import (
    SimulatedTruthRecord,
    checked_record,
    record_truth,
    truth_of_record,
)
from como3r.prior.simulated_retrieval import (
    cached_array,
    codebook_sample,
    default_cache_dir,
    view_features,
)

logger = logging.getLogger(__name__)

CODEBOOK_CACHE_VERSION = 3
"""Bump when the codebook sample or the retrieval feature map changes."""


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
        check_config(self.config)
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
        depth, K = validated_inputs(view, truth)
        return self._encode(view, record_truth(view, truth, depth, K))

    def encode_from_record(self, view: View, record: EncodingRecord) -> SimulatedEncoding:
        """:meth:`encode` of ``view`` (a keyframe's colours) from the ground truth ``record``
        holds (:mod:`~como3r.prior.simulated_record`), without a ground-truth source.

        Raises:
            PriorError: ``record`` is not a :class:`SimulatedTruthRecord` of this view.
        """
        if not isinstance(record, SimulatedTruthRecord):
            return super().encode_from_record(view, record)  # type: ignore[return-value]
        return self._encode(view, checked_record(view, record))

    def _encode(self, view: View, record: SimulatedTruthRecord) -> SimulatedEncoding:
        """:meth:`encode` from the ground truth in ``record``, which it keeps
        (:meth:`SimulatedEncoding.portable`)."""
        truth = truth_of_record(record)
        depth, K = validated_inputs(view, truth)
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
        texture = seen_texture = colours = ood = None
        if self.appearance:  # v2: what the image shows (items 9, 10 and 14)
            descriptors, texture, seen_texture, colours, ood = v2_appearance(
                view.image,
                descriptors,
                ranges,
                valid,
                self.config,
                view.agent,
                view.index,
                self.constants,
            )
            if ood is not None:
                log_range_error = log_range_error + ood.known_log_error
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
            edges=depth_edges(depth, valid & ~filled, self.constants.edge_log_jump),
            key_ids=key_ids,
            key_coords=key_coords,
            footprint=footprint,
            median_footprint=median_footprint,
            # float16 as MASt3R-SLAM's matching kernels use them; far below the noise
            descriptors=descriptors.half(),
            texture=texture,
            confidence_texture=seen_texture,
            colours=colours,
            hidden_log_error=ood.hidden_log_error if ood is not None else None,
            sky_scale=ood.sky_scale if ood is not None else 1.0,
            sky_logit_raise=ood.sky_logit_raise if ood is not None else 0.0,
            record=record,
        )

    def _truth_of(self, view: View) -> GroundTruth:
        if self.truth is None:
            raise PriorError(
                f"simulated prior: no ground-truth source to encode agent "
                f"{view.agent}, frame {view.index} (it was built to decode only)"
            )
        return self.truth.truth(view.agent, view.index)

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
            out[keyed] = normalize(
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
        enc_i, enc_j = checked_encoding(enc_i), checked_encoding(enc_j)
        gen = generator(
            self.config.seed, "pair", enc_i.agent, enc_i.index, enc_j.agent, enc_j.index
        )
        scale = math.exp(self.config.scale_sigma * float(torch.randn((), generator=gen)))
        matches = match_keys(enc_i, enc_j, self.constants, gen)
        fitted = robust_fit(enc_i, enc_j, matches, self.constants, gen)
        overlap = fitted is not None
        R, t, s = fitted if overlap else random_pose(enc_i, self.constants, gen)
        if self.realistic:
            return decode_realistic(
                enc_i, enc_j, matches, (R, t, s), overlap, scale, gen, self.config, self.constants
            )
        R, t = errors.perturb_pose_easy(R, t, self.config, gen)
        X_ii, _ = observe(enc_i, gen, self.config, self.constants)
        X_j, _ = observe(enc_j, gen, self.config, self.constants)
        X_ji = scale * (s * reproducible_matmul(X_j, R.T) + t)
        C_ii, C_ji, Q_ii, Q_ji = easy_confidences(
            enc_i, enc_j, matches, overlap, self.constants, gen
        )
        noise = self.config.descriptor_noise
        return PairPrediction(
            X_ii=scale * X_ii,
            X_ji=X_ji,
            C_ii=C_ii,
            C_ji=C_ji,
            D_ii=noisy_descriptors(enc_i, gen, noise),
            D_ji=noisy_descriptors(enc_j, gen, noise),
            Q_ii=Q_ii,
            Q_ji=Q_ji,
        )

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
        return view_features(
            self._retrieval_map, checked_encoding(enc), self.constants, self.config.seed
        )

    def codebook(self, size: int | None = None, cache_dir: str | Path | None = None) -> np.ndarray:
        """ASMK codebook of the retrieval features, trained once and cached on disk.

        k-means (:func:`como3r.prior.codebook.train_codebook`) on the retrieval features of
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
        from como3r.prior.codebook import train_codebook  # deferred: imports faiss

        c = self.constants
        size = size or c.codebook_size
        directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        v2 = (
            (repr(dataclasses.astuple(appearance_model.AppearanceConstants())),)
            if self.appearance
            else ()
        )
        digest = stable_seed(
            CODEBOOK_CACHE_VERSION, size, self.config.seed, repr(dataclasses.astuple(c)), *v2
        )

        def train() -> np.ndarray:
            logger.info("training the simulated prior's %d-word codebook (once)", size)
            sample = codebook_sample(
                self._retrieval_map,
                c,
                size * c.codebook_samples_per_word,
                self.config.seed,
                self.appearance,
            )
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
            out["appearance_constants"] = dataclasses.asdict(appearance_model.AppearanceConstants())
            out["overlap_constants"] = dataclasses.asdict(OverlapConstants())
        if self.config.ood_severity > 0:
            out["ood_constants"] = dataclasses.asdict(OodConstants())
        return out
