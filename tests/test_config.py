"""Configuration: Table 3 defaults, YAML round trip, dotted overrides, strict keys."""

from __future__ import annotations

import pytest

from como3r.config import Config, apply_overrides, dump_config, load_config
from como3r.errors import ConfigError


def test_defaults_equal_table_3() -> None:
    c = Config()
    assert c.input.long_side == 512
    assert (c.tracking.sigma_ray, c.tracking.sigma_dist) == (3e-3, 0.1)  # relative, see config
    # sigma_depth departs from Table 3's 10 (measured in config.TrackingConfig's comment)
    assert (c.tracking.sigma_pixel, c.tracking.sigma_depth) == (1.0, 0.1)
    assert c.tracking.huber_k == 1.345
    assert (c.tracking.max_iters, c.tracking.rel_cost_tol, c.tracking.step_tol) == (50, 1e-3, 1e-3)
    assert (c.tracking.keyframe_match_fraction, c.tracking.q_min) == (0.333, 1.5)
    assert (c.tracking.lambda_init, c.tracking.lambda_max, c.tracking.tikhonov_floor) == (
        1e-6,
        1e3,
        1e-9,
    )
    assert (c.local_solve.max_iters, c.local_solve.pinned_keyframes) == (10, 1)
    # both step tolerances depart from C-Sec. B.2's 1e-8 (measured in config.GlobalBAConfig)
    assert (c.local_solve.step_tol, c.global_ba.step_tol) == (1e-4, 1e-4)
    assert (c.global_ba.tikhonov_base, c.global_ba.tikhonov_retries, c.global_ba.lm_lambda) == (
        1e-6,
        6,
        0.0,
    )
    assert (c.retrieval.k_nn, c.retrieval.min_similarity, c.retrieval.alpha) == (3, 5e-3, 3.0)
    assert (c.retrieval.multiple_assignment_build, c.retrieval.multiple_assignment_query) == (1, 5)
    assert c.verification.tau_inter == 0.1
    assert c.gauge.min_correspondences == 64
    assert (c.global_ba.max_iters_stream, c.global_ba.max_iters_cleanup) == (50, 100)
    assert (c.global_ba.cleanup_passes, c.global_ba.cleanup_stop_translation) == (5, 5e-3)
    assert (c.depth.slic_segments, c.depth.slic_compactness, c.depth.slic_sigma) == (200, 8.0, 1.0)
    assert (c.depth.sigma_point, c.depth.lambda_smooth, c.depth.lambda_prior) == (0.05, 1.0, 1.0)
    assert (c.depth.lambda_lm, c.depth.step_clip, c.depth.inner_iters) == (0.05, 0.5, 10)
    assert c.depth.alternation_rounds == 100
    assert (c.matching.max_iters, c.matching.occlusion_ratio, c.matching.descriptor_radius) == (
        10,
        0.1,
        3,
    )


def test_yaml_round_trip(tmp_path) -> None:
    c = apply_overrides(Config(), ["tracking.sigma_ray=0.002", "depth.variant=pixel"])
    dump_config(c, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == c


def test_partial_yaml_keeps_defaults(tmp_path) -> None:
    (tmp_path / "c.yaml").write_text("tracking:\n  huber_k: 2.0\n")
    c = load_config(tmp_path / "c.yaml")
    assert c.tracking.huber_k == 2.0
    assert c.tracking.sigma_ray == Config().tracking.sigma_ray


def test_override_sets_value() -> None:
    c = apply_overrides(
        Config(), ["tracking.sigma_ray=0.002", "calibrated=true", "matching.occlusion_ratio=1e9"]
    )
    assert c.tracking.sigma_ray == 0.002
    assert c.matching.occlusion_ratio == 1e9
    assert c.calibrated is True


@pytest.mark.parametrize("key", ["verification.max_residual_ratio", "depth.depth_stall_ratio"])
def test_inf_turns_a_documented_gate_off(key: str, tmp_path) -> None:
    c = apply_overrides(Config(), [f"{key}=inf"])
    section, name = key.split(".")
    assert getattr(getattr(c, section), name) == float("inf")
    dump_config(c, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == c


@pytest.mark.parametrize(
    "override, message",
    [
        ("tracking.sigma_ray=inf", "tracking.sigma_ray: expected a finite number"),
        ("verification.max_residual_ratio=nan", "expected a finite number"),
        ("depth.depth_stall_ratio=-inf", "expected a finite number"),
        ("tracking.sigma_rya=1", "tracking.sigma_rya"),
        ("trackin.sigma_ray=1", "trackin"),
        ("tracking.max_iters=1.5", "tracking.max_iters"),
        ("tracking.huber_k=abc", "tracking.huber_k"),
        ("depth.variant=voxel", "depth.variant"),
        ("depth.refine_from=bogus", "depth.refine_from"),
        ("depth.boundary_residual=x", "depth.boundary_residual"),
        ("tracking.fusion=y", "tracking.fusion"),
        ("global_ba.linear_solver=cholmod", "global_ba.linear_solver"),
        ("session.team_resident_keyframes=-1", "session.team_resident_keyframes must be >= 0"),
        ("session.team_resident_keyframes=2.5", "session.team_resident_keyframes"),
        ("gauge.max_correspondences=-1", "gauge.max_correspondences must be >= 0"),
        ("gauge.max_correspondences=2.5", "gauge.max_correspondences"),
        ("global_ba.stream_max_matches=-1", "global_ba.stream_max_matches must be >= 0"),
        ("gauge.focal_max_matches=-5", "gauge.focal_max_matches must be >= 0"),
        ("verification.link_spacing=-1", "verification.link_spacing must be >= 0"),
        ("tracking=1", "section"),
        ("no_equals_sign", "section.key=value"),
    ],
)
def test_bad_override_names_key(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        apply_overrides(Config(), [override])


def test_unknown_yaml_key_is_error(tmp_path) -> None:
    (tmp_path / "c.yaml").write_text("tracking:\n  sigma_rays: 2.0\n")
    with pytest.raises(ConfigError, match=r"tracking\.sigma_rays"):
        load_config(tmp_path / "c.yaml")


def test_bad_yaml_is_error(tmp_path) -> None:
    (tmp_path / "c.yaml").write_text("tracking: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(tmp_path / "c.yaml")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
