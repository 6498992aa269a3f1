"""The simulated prior's configuration section and its range checks.

:class:`SimulatedPriorConfig` is ``Config.simulated_prior``; the error model it sets is
:mod:`como3r.prior.simulated_errors` (units and sources of every key there). Kept apart from
the prior so that :mod:`como3r.config` validates the section without importing the prior.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from como3r.errors import ConfigError


@dataclass(frozen=True)
class SimulatedPriorConfig:
    """Error model of the simulated prior (manual: docs/api/index.md, "The simulated prior").

    ``model`` selects it: ``"realistic"`` (default) imitates MASt3R's failure modes,
    ``"easy"`` is the near-oracle of round 1 for tests that need precision, ``"v2"`` (in
    progress, not yet the default) adds to the realistic model what the image reveals
    (descriptors, retrieval and confidence from local contrast; a confidence blind to the
    low-frequency error; per-pair rays); the keys from ``focal_error`` on are used by the
    realistic and v2 models only. ``ood_severity`` (0 off, 1 the strongest modelled; ``v2``
    only) adds out-of-distribution images: blur, low light, sky and thin structures, each
    scaled by its weight ``ood_blur``, ``ood_low_light``, ``ood_sky``, ``ood_thin``
    (:mod:`como3r.prior.simulated_ood`). Units and sources of every key:
    :mod:`como3r.prior.simulated_errors`. Lengths are fractions (of a range, a baseline,
    the view's median valid depth or the image's long side), never metres.
    """

    model: Literal["realistic", "easy", "v2"] = "realistic"
    scale_sigma: float = 0.05
    depth_distortion_amplitude: float = 0.03
    depth_distortion_wavelength: float = 1.0 / 3.0
    range_noise: float = 0.005
    rotation_noise_deg: float = 0.5
    translation_noise: float = 0.01
    descriptor_dim: int = 24
    descriptor_noise: float = 0.1
    seed: int = 0
    focal_error: float = 0.08
    principal_point_error: float = 0.01
    ray_field_deg: float = 0.3
    image_distortion_amplitude: float = 0.04
    image_error_correlation: float = 0.9
    image_error_frames: float = 30.0
    scale_drift: float = 0.08
    scale_drift_frames: float = 60.0
    pose_noise_growth: float = 0.05
    translation_floor: float = 0.002
    pose_tail_dof: int = 3
    gross_failure_rate: float = 0.03
    hallucination_rate: float = 0.3
    flying_pixel_fraction: float = 0.5
    outlier_fraction: float = 0.005
    confidence_error_slope: float = 1.0
    confidence_noise: float = 0.5
    descriptor_viewpoint_gain: float = 1.0
    descriptor_ambiguity: float = 0.5
    ood_severity: float = 0.0
    ood_blur: float = 1.0
    ood_low_light: float = 1.0
    ood_sky: float = 1.0
    ood_thin: float = 1.0


def check_config(config: SimulatedPriorConfig) -> None:
    """Raise ConfigError naming the first out-of-range simulated_prior key."""
    non_negative = (
        "scale_sigma",
        "depth_distortion_amplitude",
        "range_noise",
        "rotation_noise_deg",
        "translation_noise",
        "descriptor_noise",
        "focal_error",
        "principal_point_error",
        "ray_field_deg",
        "image_distortion_amplitude",
        "scale_drift",
        "pose_noise_growth",
        "translation_floor",
        "confidence_error_slope",
        "confidence_noise",
        "descriptor_viewpoint_gain",
        "descriptor_ambiguity",
        "ood_blur",
        "ood_low_light",
        "ood_sky",
        "ood_thin",
    )
    for name in non_negative:
        if getattr(config, name) < 0:
            raise ConfigError(f"simulated_prior.{name} must be >= 0, got {getattr(config, name)}")
    for name in (
        "gross_failure_rate",
        "hallucination_rate",
        "flying_pixel_fraction",
        "outlier_fraction",
        "image_error_correlation",
        "ood_severity",
    ):
        if not 0.0 <= getattr(config, name) <= 1.0:
            raise ConfigError(
                f"simulated_prior.{name} must be in [0, 1], got {getattr(config, name)}"
            )
    for name in ("depth_distortion_wavelength", "scale_drift_frames", "image_error_frames"):
        if getattr(config, name) <= 0:
            raise ConfigError(f"simulated_prior.{name} must be > 0, got {getattr(config, name)}")
    if config.pose_tail_dof < 1:
        raise ConfigError(f"simulated_prior.pose_tail_dof must be >= 1, got {config.pose_tail_dof}")
    if config.descriptor_dim < 2:
        raise ConfigError(
            f"simulated_prior.descriptor_dim must be >= 2, got {config.descriptor_dim}"
        )
    if config.ood_severity > 0 and config.model != "v2":
        raise ConfigError(
            f"simulated_prior.ood_severity={config.ood_severity} needs simulated_prior.model=v2 "
            f"(the out-of-distribution effects act on what the image shows), got "
            f"model={config.model}"
        )
