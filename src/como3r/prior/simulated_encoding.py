"""The simulated prior's per-view state (:class:`SimulatedEncoding`), the fixed constants of
its sensor model (:class:`SimulatedConstants`), and what :meth:`SimulatedPrior.encode
<como3r.prior.simulated.SimulatedPrior.encode>` prepares from a view's ground truth: the
checked depth and intrinsics, depth edges, and a depth sensor's holes filled
(:func:`fill_depth_holes`; :mod:`como3r.prior.simulated`, module docstring).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.errors import PriorError
from como3r.prior.base import Encoding, View
from como3r.prior.ground_truth import GroundTruth
from como3r.prior.simulated_record import SimulatedTruthRecord


@dataclass(frozen=True)
class SimulatedConstants:
    """Fixed constants of the sensor model (reported by :meth:`SimulatedPrior.describe
    <como3r.prior.simulated.SimulatedPrior.describe>`).

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
    """Per-view state of the simulated prior (about 110 bytes per pixel). Holds no pose but
    in its ``record``, for the keys of a view without a surface map, which only the prior
    reads.

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
            local contrast (:func:`~como3r.prior.simulated_appearance.texture_weight`); None in
            the models that ignore the image (all but ``v2``).
        confidence_texture: ``(H, W)`` the texture weight the confidence sees, when it
            differs from ``texture`` (low light's noise taken for texture,
            :mod:`~como3r.prior.simulated_ood`); None otherwise.
        colours: ``(H // s, W // s, 3)`` float32 mean image colour of each ``s x s`` cell,
            ``s = retrieval_stride`` (:func:`~como3r.prior.simulated_appearance.cell_colours`);
            None as ``texture``.
        hidden_log_error: ``(H, W)`` log-range error of the out-of-distribution effects that
            the confidence never sees (:mod:`~como3r.prior.simulated_ood`); None without them.
        sky_scale: factor on the sky's range; sky_logit_raise: added to the sky's
            ``log(C - 1)`` (1 and 0 without the out-of-distribution effects).
        record: the ground truth the encoding was made from, which travels and is
            stored in its place (:meth:`portable`; :mod:`~como3r.prior.simulated_record`);
            None in an encoding made by hand.
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
    confidence_texture: Tensor | None = None
    colours: Tensor | None = None
    hidden_log_error: Tensor | None = None
    sky_scale: float = 1.0
    sky_logit_raise: float = 0.0
    record: SimulatedTruthRecord | None = None

    def portable(self) -> Encoding:
        """The ground-truth record, about a tenth of the encoding's size (compressed), from
        which a coordinator's prior makes the encoding again with the keyframe's colours."""
        return self if self.record is None else self.record

    def for_decoding(self) -> Encoding:
        """Without its record."""
        return self if self.record is None else dataclasses.replace(self, record=None)


def normalize(x: Tensor) -> Tensor:
    """Unit vectors along the last dimension."""
    return F.normalize(x, dim=-1)


def depth_edges(depth: Tensor, valid: Tensor, log_jump: float) -> Tensor:
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


def validated_inputs(view: View, truth: GroundTruth) -> tuple[Tensor, Tensor]:
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


def checked_encoding(enc: Encoding) -> SimulatedEncoding:
    if not isinstance(enc, SimulatedEncoding):
        raise PriorError(
            f"simulated prior: cannot decode a {type(enc).__name__} "
            "(encode the view with the simulated prior)"
        )
    return enc
