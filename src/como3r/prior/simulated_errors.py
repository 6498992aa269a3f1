"""Error model of the simulated prior: the ``realistic`` default and the ``easy`` near-oracle.

The ``easy`` model (round 1) corrupts exact geometry with small, independent per-pair errors:
log-normal pair scale ``scale_sigma``, a smooth per-pair range distortion
(``depth_distortion_amplitude``, wavelength ``depth_distortion_wavelength`` of the long
side), per-pixel range noise ``range_noise``, Gaussian pose noise (``rotation_noise_deg``,
``translation_noise`` of the baseline) and descriptor noise ``descriptor_noise``; its rays are
the true intrinsics' rays and its confidence is an overlap oracle.

The ``realistic`` model keeps those per-pair terms and adds what makes MASt3R hard
(:class:`~como3r.config.SimulatedPriorConfig` key, default, source). Where no published
figure exists the value is OUR ASSUMPTION and says so. The MUSt3R and Light3R-SfM figures
below were read from secondary summaries of those papers, not from their tables; DUSt3R's
own depth and pose tables (DUSt3R paper, Tables 2-3) could not be consulted when this model
was written and should replace them where they differ. Every length is relative (a
fraction of a range, a baseline or the view's median valid depth ``m``), so a scene scaled
by any factor gets the same relative errors.

1. Intrinsics, per image (shared by all its pairs): focal ``f exp(focal_error n)``,
   ``focal_error = 0.08`` (RMS log error); MUSt3R (Cabon et al., CVPR 2025, uncalibrated VO
   on TUM RGB-D) reports a mean field-of-view error of 4 deg, i.e. about 7-8 % of the focal
   at a 60 deg field of view, for a network of the same family trained on the same data.
   Principal point moved by ``principal_point_error = 0.01`` of the long side per axis (our
   assumption) and ray directions bent by a smooth field of RMS ``ray_field_deg = 0.3`` deg
   (our assumption; pointmap regression has no exact pinhole). ``X_ii`` lies on these rays,
   not on the true ``K``'s, and so does ``X_ji``: the pair is regressed in camera i, so view
   j's points sit on camera i's believed rays where they truly project
   (:func:`in_believed_camera`); the correspondence the pair implies is wrong only by the
   pair's pose error, not by the two images' intrinsics errors.
2. Range error, per image: a smooth unit-RMS field times ``image_distortion_amplitude =
   0.04`` shared by every pair of the image, on top of the per-pair field
   (``depth_distortion_amplitude``) and pixel noise. Total RMS about 5 %: MUSt3R (same paper,
   multi-view depth on KITTI/ScanNet/ETH3D/DTU/T&T) reports 3.7-4.7 % average relative
   error and calls it close to DUSt3R-512; a two-view pair without multi-view context is
   worse, so 5 % is our assumption.
   Items 1 and 2 are per image but not independent between images: one camera filming one
   scene gives the network nearly the same input from frame to frame, so its intrinsics and
   depth errors change slowly along a sequence. Each per-image draw is
   ``rho (cos(pi t / 2) a_b + sin(pi t / 2) a_(b+1)) + sqrt(1 - rho^2) e_k`` for frame ``k``,
   with ``a_b`` drawn once per block of ``image_error_frames = 30`` frames (``b = floor(k /
   30)``, ``t`` the position in the block), ``e_k`` drawn for the frame alone and
   ``rho = image_error_correlation = 0.9``: unit variance everywhere, correlation about
   ``rho^2`` between neighbouring frames and 0 beyond two blocks. Our assumption (no
   published figure); independent per-image draws made every consecutive frame pair
   disagree by the full focal error, which a video never shows.
3. Scale: the pair scale ``exp(scale_sigma n)`` times a drift ``exp(scale_drift d(k))``
   along an agent's frame index ``k``, ``d`` a unit-RMS random Fourier series of wavelength
   about ``scale_drift_frames = 60`` frames seeded per agent, ``scale_drift = 0.08``. MUSt3R
   reports a median scale error of 4.6 % (TUM RGB-D VO); the drift amplitude and wavelength
   are our assumption.
4. Relative pose: RMS errors grow with the viewpoint change
   ``v = rotation angle + baseline / m`` (degrees): rotation
   ``rotation_noise_deg (1 + pose_noise_growth v)``, translation
   ``translation_noise (1 + pose_noise_growth v) |t| + translation_floor m``
   (``pose_noise_growth = 0.05`` per degree, ``translation_floor = 0.002``: our assumption),
   drawn from a multivariate Student-t with ``pose_tail_dof = 3`` degrees of freedom (heavy
   tail). A fraction ``gross_failure_rate = 0.03`` of overlapping pairs gets a random pose
   at full confidence: MASt3R on two-view CO3Dv2 pairs reaches RRA@15 94.2 % / RTA@15 86.5 %
   (MASt3R row of the CO3Dv2 table of Light3R-SfM, Elflein et al., CVPR 2025), i.e. about
   6 % of wide-baseline object pairs err by more than 15 deg in rotation; SLAM pairs are
   narrower, hence half of that (our assumption).
5. Flying pixels: ``flying_pixel_fraction = 0.5`` of the pixels at a depth discontinuity
   (relative jump above ``edge_log_jump``) get a range uniformly between the local
   foreground and background along their ray; ``outlier_fraction = 0.005`` of the pixels get
   a log-range error of RMS ``outlier_log_sigma``. Our assumption (MASt3R's regression head
   smooths across discontinuities; no published rate).
6. Hallucinations: a fraction ``hallucination_rate = 0.3`` of pairs without common keys keeps
   full confidence on its random pose (our assumption; MASt3R always outputs a pose).
7. Confidence: ``log(C - 1)`` falls with range (relative to ``m``) and at edges as before,
   and by ``confidence_error_slope = 1.0`` per ``conf_error_ref`` (5 %) of the pixel's own
   injected range error, plus noise of RMS ``confidence_noise = 0.5``; the pair's pose error
   (gross failures included) does not lower it. The overlap oracle of the easy model
   survives only as a weak drop (``weak_unmatched_drop``, ``weak_no_overlap_drop``) under the
   same noise. Our assumption.
8. Descriptors: noise RMS ``descriptor_noise (1 + descriptor_viewpoint_gain v)`` with ``v``
   the pair's rotation angle plus ``|log|`` of its scale change (radians;
   ``descriptor_viewpoint_gain = 1.0``, our assumption), and the per-texture embedding
   weighted up by ``descriptor_ambiguity = 0.5`` so that repeated texture is ambiguous.

The ``v2`` model (towards a prior as hard as MASt3R; not the default) is the realistic model
plus what the image the prior sees can and cannot reveal: items 9-12 in
:mod:`como3r.prior.simulated_appearance`, and:

13. No truth-decided overlap (:mod:`como3r.prior.simulated_overlap`). Items 6 and 7 lower a
    pair by whether its surface keys support a similarity fit and a pixel by whether its key
    has a counterpart: confidence that knows the true overlap (overlap AUC 0.96-1.00 in
    ``benchmarks/prior_statistics.py``, below 1 only by the hallucination coin). Here a pixel's drop ``pixel_drop (1 - e)`` comes
    from the agreement ``e`` of its clean descriptor with the one at the pixel its predicted
    correspondence lands on (the pose the matcher believes, before the pose noise the
    confidence never knows), and the pair's drop (of ``C_ji`` only: a pair-level drop of
    ``Q`` moved the share of a low-texture pair's pixels above tracking's absolute
    ``Q_min`` from 0.95 to 0.01-0.86 and lost frames) from how well 400 random pixels of
    view j find a look-alike anywhere in view i, weighted by their texture weight (item 9): two
    views of one wallpaper, aliased façades or flat paint look like overlap, a true overlap
    on flat paint gives little evidence. The hallucination coin (item 6) is drawn for every
    pair, not for the pairs the keys could not fit, and a per-pair offset of RMS
    ``pair_noise = 0.5`` moves the pair's confidence level. Values in
    :class:`~como3r.prior.simulated_overlap.OverlapConstants`, our assumption, set from the
    descriptor agreements measured on our synthetic scenes.
14. Out-of-distribution images, ``ood_severity`` (0 = off, the default; 1 the strongest
    modelled) times a weight per effect (``ood_blur``, ``ood_low_light``, ``ood_sky``,
    ``ood_thin``, 1 each; :mod:`como3r.prior.simulated_ood`, values at severity 1 in
    :class:`~como3r.prior.simulated_ood.OodConstants`). Corruptions of this kind (defocus
    and motion blur, Gaussian/shot noise, low brightness at graded severities: ImageNet-C,
    Hendrycks and Dietterich, ICLR 2019) raise the error of learned monocular depth
    monotonically with severity (RoboDepth, Kong et al., NeurIPS 2023 Datasets and
    Benchmarks); no published figure for MASt3R under them could be consulted, so every
    magnitude below is OUR ASSUMPTION and only the kind of failure has a source.

    * Blur (per image, ``u_k`` of the sequence): the image the prior sees is blurred by a
      Gaussian of up to ``blur_sigma = 0.008`` of the long side (4 px at 512), so its local
      contrast and with it the texture weight (item 9) fall: descriptors become ambiguous;
      and a smooth depth bias of RMS ``blur_depth_bias = 0.06`` (log range) that the
      confidence does not see.
    * Low light (per image): the image darkened by up to ``low_light_gain = 0.6`` plus
      pixel noise of RMS ``low_light_noise = 0.15`` intensity units; per-image descriptor
      noise of RMS norm ``low_light_descriptor_noise = 0.6`` (two views of one place
      disagree) and pixel range noise ``low_light_range_noise = 0.04``. The image noise
      raises the local contrast that ``C`` and ``Q`` see (item 9's texture drops), so they
      rise on flat paint: a confidence that takes noise for texture, not fully informative;
      the key's share of a descriptor follows the noise-free signal, so noise never makes
      matching easier.
    * Sky: no depth to learn from (DUSt3R and MASt3R exclude pixels without ground truth
      from the loss, naver/dust3r issue 194; a depth network puts the sky at close, varying
      values because stereo ground truth does, lpiccinelli-eth/UniDepth issue 69): the
      sky's range moves from 10-20 to ``sky_near_range = 2``-4 times the median depth and
      its ``log(C - 1)`` rises by ``sky_conf_raise = 3`` (``C`` about 1.4 instead of 1.02):
      large wrong depth, low but not zero confidence.
    * Thin structures: the network regresses 16x16-pixel patch tokens upsampled by a DPT
      head (DUSt3R, Wang et al., CVPR 2024), so a structure much thinner than a patch is
      smoothed into its background: every pixel with a surface farther by more than
      ``thin_jump = 0.1`` (log) within ``thin_width = 0.012`` of the long side (6 px at
      512) is pulled towards it (all the way at severity 1), an error the confidence does
      not see beyond the usual edge drop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.config import SimulatedPriorConfig
from como3r.geometry.lie import quat_to_matrix, so3_exp
from como3r.prior.simulated_keys import generator, reproducible_matmul

REALISTIC = "realistic"
V2 = "v2"
#: the models with the realistic error terms (``v2`` adds to them)
REALISTIC_MODELS = (REALISTIC, V2)


@dataclass(frozen=True)
class RealisticConstants:
    """Fixed shape of the realistic model (reported by ``describe``)."""

    ray_field_wavelength: float = 1.0
    edge_log_jump: float = 0.1
    outlier_log_sigma: float = 0.5
    conf_error_ref: float = 0.05
    conf_error_cap: float = 4.0
    weak_unmatched_drop: float = 0.5
    weak_no_overlap_drop: float = 1.5
    drift_modes: int = 4
    distortion_modes: int = 8


def fourier_field(H: int, W: int, wavelength_px: float, modes: int, gen: torch.Generator) -> Tensor:
    """``(H, W)`` unit-RMS random Fourier field of wavelength ``wavelength_px`` pixels.

    ``sqrt(2 / M) sum_m cos(a_m u + b_m v + phi_m)`` with ``(a_m, b_m)`` of fixed length in
    random directions, expanded as ``cos(a u) cos(b v + phi) - sin(a u) sin(b v + phi)`` so
    the field is two ``(H, M) @ (M, W)`` products.
    """
    wavenumber = 2.0 * math.pi / wavelength_px
    angle = 2.0 * math.pi * torch.rand(modes, generator=gen)
    phase = 2.0 * math.pi * torch.rand(modes, generator=gen)
    along_u = wavenumber * torch.arange(W, dtype=torch.float32)[:, None] * torch.cos(angle)
    along_v = wavenumber * torch.arange(H, dtype=torch.float32)[:, None] * torch.sin(angle) + phase
    field = torch.cos(along_v) @ torch.cos(along_u).T - torch.sin(along_v) @ torch.sin(along_u).T
    return math.sqrt(2.0 / modes) * field


class ImageDraws:
    """Standard normal draws and unit-RMS fields of one image, correlated along its sequence.

    Every draw is the weighted sum of the same draw from a few generators whose squared
    weights add up to 1 (module docstring, "Items 1 and 2"), so each has unit variance and
    neighbouring frames share most of it. Call the methods in the same order for every
    image: the generators advance together.

    Args:
        config: the error model (``image_error_correlation``, ``image_error_frames``).
        seed, agent, index: which image.
    """

    def __init__(self, config: SimulatedPriorConfig, seed: int, agent: int, index: int) -> None:
        rho = config.image_error_correlation
        position = index / config.image_error_frames
        block = math.floor(position)
        angle = 0.5 * math.pi * (position - block)
        self.jitter = generator(seed, "image", agent, index)
        self._parts = [
            (rho * math.cos(angle), generator(seed, "image block", agent, block)),
            (rho * math.sin(angle), generator(seed, "image block", agent, block + 1)),
            (math.sqrt(max(0.0, 1.0 - rho * rho)), self.jitter),
        ]

    def normal(self, *shape: int) -> Tensor:
        """Standard normal draws of ``shape``."""
        return sum(w * torch.randn(shape, generator=g) for w, g in self._parts)

    def field(self, H: int, W: int, wavelength_px: float, modes: int) -> Tensor:
        """``(H, W)`` unit-RMS random Fourier field (:func:`fourier_field`)."""
        return sum(w * fourier_field(H, W, wavelength_px, modes, g) for w, g in self._parts)


def predicted_rays(
    K: Tensor, H: int, W: int, config: SimulatedPriorConfig, draws: ImageDraws
) -> Tensor:
    """``(H, W, 3)`` unit rays the realistic prior believes in for one image.

    Pinhole rays of ``K`` with the focal scaled by ``exp(focal_error n)`` and the principal
    point moved by ``principal_point_error`` of the long side, bent by a smooth field of RMS
    ``ray_field_deg`` (added to the normalised image coordinates); ``n`` and the fields come
    from the image's sequence-correlated ``draws``.
    """
    long_side = max(H, W)
    focal_factor = math.exp(config.focal_error * float(draws.normal()))
    shift = config.principal_point_error * long_side * draws.normal(2)
    fx, fy = float(K[0, 0]) * focal_factor, float(K[1, 1]) * focal_factor
    cx, cy = float(K[0, 2] + shift[0]), float(K[1, 2] + shift[1])
    u = torch.arange(W, dtype=torch.float32)[None, :].expand(H, W)
    v = torch.arange(H, dtype=torch.float32)[:, None].expand(H, W)
    x, y = (u - cx) / fx, (v - cy) / fy
    # per-axis RMS ray_field / sqrt(2), so that the 2-D bend has RMS ray_field_deg
    bend = math.radians(config.ray_field_deg) / math.sqrt(2.0)
    wavelength = RealisticConstants.ray_field_wavelength * long_side
    modes = RealisticConstants.distortion_modes
    x = x + bend * draws.field(H, W, wavelength, modes)
    y = y + bend * draws.field(H, W, wavelength, modes)
    return F.normalize(torch.stack([x, y, torch.ones_like(x)], dim=-1), dim=-1).to(K.device)


def in_believed_camera(points: Tensor, rays: Tensor, pred_rays: Tensor, K: Tensor) -> Tensor:
    """Points of camera i moved onto the rays camera i's prediction believes in.

    A network regresses both pointmaps of a pair in camera i's frame, so its belief about
    camera i (focal, principal point, ray field) bends ``X_ji`` as it bends ``X_ii``: a
    point of view j lands on the predicted ray of the pixel of i where it truly projects,
    and the correspondence that ``X_ji`` implies in image i stays right. Drawing view j's
    own intrinsics error into ``X_ji`` instead makes that correspondence wrong by the
    difference of two images' focal errors, which MASt3R's jointly regressed pointmaps
    (the basis of MASt3R-SLAM's projective matching) do not show. Our assumption.

    The bend is taken in normalised image coordinates: an affine fit of the predicted on
    the true coordinates over the image (exact for the focal and principal-point errors)
    plus the smooth remainder, sampled at the true pixel (border values outside the image).

    Args:
        points: ``(..., 3)`` points in camera i (true geometry).
        rays: ``(H, W, 3)`` true unit rays of image i; pred_rays: ``(H, W, 3)`` predicted.
        K: ``(3, 3)`` true intrinsics of image i.

    Returns:
        ``(..., 3)`` the points at their range along the believed rays (points at or behind
        the camera plane unchanged).
    """
    H, W = rays.shape[:2]
    true_xy = (rays[..., :2] / rays[..., 2:]).reshape(-1, 2)
    pred_xy = (pred_rays[..., :2] / pred_rays[..., 2:]).reshape(-1, 2)
    design = torch.cat([true_xy, torch.ones_like(true_xy[:, :1])], dim=1)
    affine = _least_squares(design, pred_xy)  # (3, 2)
    remainder = (pred_xy - reproducible_matmul(design, affine)).reshape(H, W, 2)
    z = points[..., 2:]
    front = z[..., 0] > 1e-9
    xy = points[..., :2] / torch.where(front[..., None], z, torch.ones_like(z))
    pixels = reproducible_matmul(xy, K[:2, :2].T.to(xy)) + K[:2, 2].to(xy)
    grid = torch.stack(
        [2 * pixels[..., 0] / max(W - 1, 1) - 1, 2 * pixels[..., 1] / max(H - 1, 1) - 1], dim=-1
    )
    bend = F.grid_sample(
        remainder.permute(2, 0, 1)[None],
        grid.reshape(1, 1, -1, 2),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    believed_xy = reproducible_matmul(
        torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1), affine
    ) + bend[0, :, 0].T.reshape(xy.shape)
    direction = F.normalize(torch.cat([believed_xy, torch.ones_like(z)], dim=-1), dim=-1)
    moved = direction * points.norm(dim=-1, keepdim=True)
    return torch.where(front[..., None], moved, points)


def _least_squares(A: Tensor, B: Tensor) -> Tensor:
    """``argmin_X |A X - B|`` for ``A`` ``(N, K)`` of full column rank and ``B`` ``(N, M)``,
    by the normal equations in float64 with fixed summation order: LAPACK's blocked QR
    (``torch.linalg.lstsq``) rounds differently with the operands' memory alignment, which
    made the same decode differ between two calls."""
    A64, B64 = A.double(), B.double()
    gram = (A64[:, :, None] * A64[:, None, :]).sum(0)
    rhs = (A64[:, :, None] * B64[:, None, :]).sum(0)
    return torch.linalg.solve(gram, rhs).to(A.dtype)


def image_log_range_error(
    ranges: Tensor, valid: Tensor, config: SimulatedPriorConfig, draws: ImageDraws
) -> Tensor:
    """``(H, W)`` per-image log-range error: shared smooth field, flying pixels, outliers.

    The smooth field comes from the image's sequence-correlated ``draws``; flying pixels and
    outliers from its own generator (``draws.jitter``). A flying pixel next to a depth
    discontinuity (relative jump above ``edge_log_jump`` in its 3x3 neighbourhood) takes a
    range uniform between the neighbourhood's nearest and farthest valid range, along its
    own ray.
    """
    H, W = ranges.shape
    c = RealisticConstants
    gen = draws.jitter
    field = draws.field(
        H, W, config.depth_distortion_wavelength * max(H, W), c.distortion_modes
    ).to(ranges.device)
    log_error = config.image_distortion_amplitude * field
    far = torch.where(valid, ranges, torch.zeros_like(ranges))
    near = torch.where(valid, ranges, torch.full_like(ranges, math.inf))
    far = F.max_pool2d(far[None, None], 3, stride=1, padding=1)[0, 0]
    near = -F.max_pool2d(-near[None, None], 3, stride=1, padding=1)[0, 0]
    jump = valid & (
        torch.log(far.clamp_min(1e-12)) - torch.log(near.clamp_min(1e-12)) > c.edge_log_jump
    )
    draw = torch.rand(H, W, generator=gen).to(ranges.device)
    flying = jump & (draw < config.flying_pixel_fraction)
    where = torch.rand(H, W, generator=gen).to(ranges.device)
    flown = near + where * (far - near)
    log_error = torch.where(
        flying, torch.log(flown.clamp_min(1e-12) / ranges.clamp_min(1e-12)), log_error
    )
    outlier = valid & (torch.rand(H, W, generator=gen).to(ranges.device) < config.outlier_fraction)
    jolt = c.outlier_log_sigma * torch.randn(H, W, generator=gen).to(ranges.device)
    log_error = torch.where(outlier, log_error + jolt, log_error)
    return torch.where(valid, log_error, torch.zeros_like(log_error))


def scale_drift(config: SimulatedPriorConfig, agent: int, index: int) -> float:
    """Log scale drift at frame ``index`` of ``agent``: ``scale_drift`` times a unit-RMS
    random Fourier series of wavelengths log-uniform in ``[1/2, 2] scale_drift_frames``,
    seeded by ``(seed, agent)`` only."""
    gen = generator(config.seed, "scale drift", agent)
    modes = RealisticConstants.drift_modes
    wavelength = config.scale_drift_frames * torch.exp(
        math.log(2.0) * (2.0 * torch.rand(modes, generator=gen, dtype=torch.float64) - 1.0)
    )
    phase = 2.0 * math.pi * torch.rand(modes, generator=gen, dtype=torch.float64)
    series = torch.cos(2.0 * math.pi * index / wavelength + phase).sum()
    return config.scale_drift * math.sqrt(2.0 / modes) * float(series)


def rotation_angle(R: Tensor) -> float:
    """Angle of the rotation matrix ``R`` ``(3, 3)`` in radians."""
    cosine = (float(torch.diagonal(R).sum()) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, cosine)))


def _heavy_tailed(sigma: float, dof: int, gen: torch.Generator) -> Tensor:
    """``(3,)`` float64 multivariate Student-t vector: ``N(0, sigma^2 / 3 I)`` over
    ``sqrt(chi2_dof / dof)``."""
    gaussian = sigma / math.sqrt(3.0) * torch.randn(3, generator=gen, dtype=torch.float64)
    chi2 = float(torch.randn(dof, generator=gen, dtype=torch.float64).square().sum())
    return gaussian / math.sqrt(max(chi2, 1e-12) / dof)


def perturb_pose_easy(
    R: Tensor, t: Tensor, config: SimulatedPriorConfig, gen: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Rotation ``Exp(omega) R`` and translation ``t + delta``, Gaussian (easy model)."""
    sigma_rotation = math.radians(config.rotation_noise_deg) / math.sqrt(3.0)
    omega = sigma_rotation * torch.randn(3, generator=gen, dtype=torch.float64)
    sigma_translation = config.translation_noise * float(t.norm()) / math.sqrt(3.0)
    delta = sigma_translation * torch.randn(3, generator=gen, dtype=torch.float64)
    noise = quat_to_matrix(so3_exp(omega)).to(R)
    return noise @ R, t + delta.to(t)


def perturb_pose_realistic(
    R: Tensor, t: Tensor, unit: float, config: SimulatedPriorConfig, gen: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Heavy-tailed pose error growing with the viewpoint change (module docstring, 4).

    Args:
        R: ``(3, 3)`` rotation, t: ``(3,)`` translation of view j in camera i.
        unit: median valid depth of view i (the length unit of the translation floor).
    """
    change_deg = math.degrees(rotation_angle(R) + float(t.norm()) / unit)
    growth = 1.0 + config.pose_noise_growth * change_deg
    omega = _heavy_tailed(
        math.radians(config.rotation_noise_deg) * growth, config.pose_tail_dof, gen
    )
    sigma_t = config.translation_noise * growth * float(t.norm()) + config.translation_floor * unit
    delta = _heavy_tailed(sigma_t, config.pose_tail_dof, gen)
    return quat_to_matrix(so3_exp(omega)).to(R) @ R, t + delta.to(t)


def viewpoint_change(R: Tensor, unit_i: float, unit_j: float) -> float:
    """Rotation angle plus ``|log|`` of the scale change between two views (radians)."""
    return rotation_angle(R) + abs(math.log(max(unit_j, 1e-12) / max(unit_i, 1e-12)))


def error_logit(log_error: Tensor, config: SimulatedPriorConfig) -> Tensor:
    """Confidence-logit drop for a pixel's injected log-range error (module docstring, 7)."""
    c = RealisticConstants
    return config.confidence_error_slope * (log_error.abs() / c.conf_error_ref).clamp_max(
        c.conf_error_cap
    )
