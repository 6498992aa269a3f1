"""Typed configuration of como3r.

Every default equals CoMo3R-SLAM Table 3 ("C-Tab. 3"); where the paper inherits a value
from MASt3R-SLAM without listing it (matching iterations, occlusion distance, descriptor
window, relocalization threshold), the MASt3R-SLAM released value is used and marked so.

A configuration is a tree of frozen dataclasses. ``load_config`` reads YAML,
``dump_config`` writes it, ``apply_overrides`` applies dotted ``key=value`` overrides as
given on the command line (``--set tracking.sigma_ray=0.002``). Unknown keys, values of
the wrong type and values out of range (:func:`validate`, which both run) are a
:class:`~como3r.errors.ConfigError` naming the key.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar, get_args, get_origin

import yaml

from como3r.config_backend import (
    DepthRefinementConfig,
    GaugeConfig,
    GlobalBAConfig,
    RetrievalConfig,
    VerificationConfig,
)
from como3r.config_decentralized import DecentralizedConfig
from como3r.config_decentralized import check_config as check_decentralized
from como3r.config_frontend import InputConfig, LocalSolveConfig, MatchingConfig, TrackingConfig
from como3r.config_simulated_prior import SimulatedPriorConfig
from como3r.config_simulated_prior import check_config as check_simulated_prior
from como3r.errors import ConfigError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

# the sections defined in config_frontend, config_backend and config_simulated_prior are
# part of this module's interface: import every configuration class from here
__all__ = [
    "Config",
    "DepthRefinementConfig",
    "GaugeConfig",
    "GlobalBAConfig",
    "InputConfig",
    "LocalSolveConfig",
    "MatchingConfig",
    "RetrievalConfig",
    "SessionConfig",
    "SimulatedPriorConfig",
    "TrackingConfig",
    "VerificationConfig",
    "VisualizationConfig",
    "apply_overrides",
    "config_from_dict",
    "config_to_dict",
    "differing_key",
    "dump_config",
    "load_config",
    "validate",
]


@dataclass(frozen=True)
class VisualizationConfig:
    """Map export and mesh visualisation (C-Tab. 3)."""

    tau_slant: float = 0.1
    map_min_confidence: float = 1.5
    #: ``map.ply`` keeps the first point of every voxel of this edge in metres (world units);
    #: 0 leaves the choice to ``map_voxel``
    voxel_size_m: float = 0.0
    #: ``map.ply`` keeps the first point of every voxel whose edge is this fraction of the
    #: map's reference depth (the median over keyframes of their points' median range, in
    #: world units), 0 every confident pixel of every keyframe (not in C-Tab. 3). Overlapping
    #: keyframes see the same surface; 0.005 (about 1.7 px at 512 px with a 75 deg field of
    #: view) keeps 59 % of the demo scene's 2.69 M points (0.003: 78 %, 0.01: 29 %), far below
    #: the map evaluation's 5 % threshold, which reads the keyframes, not ``map.ply``
    map_voxel: float = 0.005


@dataclass(frozen=True)
class SessionConfig:
    """The coordinator's memory and its session store (not in C-Tab. 3; manual:
    docs/outputs.md).

    ``resident_keyframes``: per agent, how many of its newest keyframes the coordinator keeps
    whole in memory (a count). The others' encodings, images and pointmaps, and the matches
    of the sequential edges between them, are paged out to the session store after every
    message and read back while a verification or a solve needs them
    (:mod:`como3r.store.paging`), so the coordinator's memory does not grow with
    the sequence. Each agent's front-end keeps as many of its own keyframes whole and pages
    the others, and the matches of the edges between them, out to a private spill folder
    after every frame (:class:`como3r.frontend.paging.AgentPaging`). The results are the
    same for every value.

    ``team_resident_keyframes``: of those, how many the coordinator keeps whole at most,
    across the team (a count): the newest by arrival; the others are paged out as above.
    0: no team-wide bound (every agent's ``resident_keyframes``, so the coordinator's
    resident keyframes grow with the team). The default 32 is four agents' worth at the
    default ``resident_keyframes`` of 8: a team of up to four keeps what it kept before,
    a larger one holds as many keyframes as four agents (issue 41: 16 agents held 128
    whole). The agents' front-ends page their own keyframes by ``resident_keyframes``
    alone. The results are the same for every value; only memory and time (reads from the
    store) change. Measured (8 agents of a 320x240 ``como3r synth`` scene, 27 keyframes,
    multi-process, simulated prior, ``resident_keyframes=2``): 4 keyframes held after
    every message instead of 16, byte-identical trajectories; the coordinator's peak memory
    1.33 / 1.35 GB with / without: the arrays let go of were freed but stayed in glibc's
    heap (given back since, :mod:`como3r.heap`), and the encoding cache below holds
    up to ``encoding_cache`` encodings besides.

    ``spill_dir``: the folder in which each agent makes its spill folder (removed when the
    agent ends); empty: the system's temporary folder.

    ``disk_reserve_mb``: the free space (MB) below which a run stops, resumably, before its
    disk is full (:mod:`como3r.runtime.disk_guard`); 0: eight keyframes at the rate the
    store has filled the disk so far, plus the outputs, estimated as large as the store's
    files, at least 16 MB.

    ``encoding_cache``: how many keyframe encodings (a count) the coordinator keeps after
    encoding a keyframe's colours again, least recently used first out. Where its prior can
    remake an agent's encodings from the keyframe's colours (MASt3R; not the simulated
    prior, whose encodings need the agent's ground truth) the agent sends none and the
    session store keeps none
    (:mod:`como3r.coordination.encodings`); a verification then re-encodes the keyframes it
    decodes. 0: re-encode at every use. The results are the same for every value. The
    default 64 holds a team's recent keyframes, which cross-agent retrieval hits anywhere
    in the map. Measured with benchmarks/team_scale.py (``--sizes 4 16``, multi-process,
    simulated prior at 512x384, whose encoding is 13.4 MB where MASt3R's 768x1024 float
    tokens are 3.1 MB) at 16: re-encodes per keyframe 1.2 / 2.15 at 4 / 16 agents, the
    coordinator's CPU per keyframe 2130 / 2880 ms (16 against 4: 1.35x) and peak memory
    2350 / 4020 MB; at 64: 1.0 / 1.0, 2010 / 2450 ms (1.22x), 2390 / 4530 MB (1.90x).

    ``encoding_cache_mb``: the most memory (MB) those encodings take together, least
    recently used first out; 0 (default): no bound but the count. It matters for a heavy
    prior's encodings only (MASt3R's at 512x384 are 3.1 MB: 64 take 200 MB; the simulated
    prior's 23 MB: 1.5 GB). Measured at 1024 (44 of the simulated prior's) with
    benchmarks/team_scale.py (``--sizes 4 16 --frames 48``, session 40): the 16-agent
    coordinator's peak 4221 -> 3883 MB, its re-encodes 302 -> 413 and its CPU per keyframe
    1940 -> 2069 ms; the 4-agent run's cache never reaches it.
    """

    resident_keyframes: int = 8
    team_resident_keyframes: int = 32
    spill_dir: str = ""
    disk_reserve_mb: float = 0.0
    encoding_cache: int = 64
    encoding_cache_mb: float = 0.0


@dataclass(frozen=True)
class Config:
    """The full effective configuration of a run."""

    input: InputConfig = field(default_factory=InputConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    local_solve: LocalSolveConfig = field(default_factory=LocalSolveConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    gauge: GaugeConfig = field(default_factory=GaugeConfig)
    global_ba: GlobalBAConfig = field(default_factory=GlobalBAConfig)
    depth: DepthRefinementConfig = field(default_factory=DepthRefinementConfig)
    visualization: VisualizationConfig = field(default_factory=VisualizationConfig)
    session: SessionConfig = field(default_factory=SessionConfig)
    simulated_prior: SimulatedPriorConfig = field(default_factory=SimulatedPriorConfig)
    decentralized: DecentralizedConfig = field(default_factory=DecentralizedConfig)
    calibrated: bool = False
    loop_closure: bool = True
    seed: int = 0


C = TypeVar("C", bound="DataclassInstance")

# Ranges checked by validate(); a key not listed takes any (finite) value of its type, and
# Literal keys are checked against their choices when read. 0 stays allowed where it means
# "off" (descriptor_radius, alternation_rounds, prefetch_frames, damping and retries).
_POSITIVE = (
    "input.frame_rate_hz",
    "matching.convergence_tol",
    "matching.occlusion_ratio",
    "tracking.sigma_ray",
    "tracking.sigma_dist",
    "tracking.sigma_pixel",
    "tracking.sigma_depth",
    "tracking.huber_k",
    "tracking.rel_cost_tol",
    "tracking.step_tol",
    "tracking.lambda_max",
    "tracking.inlier_angle_deg",
    "local_solve.step_tol",
    "local_solve.relinearize_tol",
    "retrieval.alpha",
    "verification.max_residual_ratio",
    "gauge.focal_search",
    "gauge.focal_prior",
    "gauge.scale_alarm_log",
    "global_ba.cleanup_stop_translation",
    "global_ba.step_tol",
    "depth.slic_compactness",
    "depth.sigma_point",
    "depth.step_clip",
    "depth.depth_convergence_tol",
    "depth.depth_stall_ratio",
)
_NON_NEGATIVE = (
    "input.prefetch_frames",
    "matching.lambda_init",
    "matching.descriptor_radius",
    "tracking.lambda_init",
    "tracking.tikhonov_floor",
    "tracking.self_calibration_keyframes",
    "local_solve.pinned_keyframes",
    "local_solve.tikhonov_base",
    "local_solve.tikhonov_retries",
    "local_solve.lm_lambda",
    "verification.covisible_min_confidence",
    "verification.max_within_component",
    "verification.max_decodes_per_batch",
    "verification.max_loop_candidates",
    "verification.workers",
    "verification.link_spacing",
    "gauge.max_correspondences",
    "gauge.focal_max_matches",
    "global_ba.stream_max_matches",
    "global_ba.lm_lambda",
    "global_ba.tikhonov_base",
    "global_ba.tikhonov_retries",
    "global_ba.relinearize_tol",
    "depth.slic_sigma",
    "depth.lambda_smooth",
    "depth.lambda_prior",
    "depth.lambda_lm",
    "depth.alternation_rounds",
    "visualization.voxel_size_m",
    "visualization.map_voxel",
    "session.resident_keyframes",
    "session.team_resident_keyframes",
    "session.disk_reserve_mb",
    "session.encoding_cache",
    "session.encoding_cache_mb",
)
_AT_LEAST_ONE = (
    "input.subsample",
    "matching.max_iters",
    "matching.descriptor_dilation_max",
    "tracking.max_iters",
    "local_solve.max_iters",
    "local_solve.dense_keyframes",
    "retrieval.codebook_size",
    "retrieval.multiple_assignment_build",
    "retrieval.multiple_assignment_query",
    "retrieval.k_nn",
    "gauge.min_correspondences",
    "gauge.min_consistent_edges",
    "global_ba.trigger_interval_edges",
    "global_ba.max_iters_stream",
    "global_ba.max_iters_cleanup",
    "global_ba.cleanup_passes",
    "depth.slic_segments",
    "depth.min_valid_pixels",
    "depth.inner_iters",
    "depth.pose_pass_iters",
)
_FRACTION = (
    "tracking.keyframe_match_fraction",
    "tracking.min_match_fraction",
    "tracking.reloc_match_fraction",
    "tracking.min_inlier_fraction",
    "local_solve.min_match_fraction",
    "verification.tau_inter",
    "verification.min_covisible_ratio",
)
#: keys whose ``inf`` means "off" (the paper's behaviour); every other number must be finite
_MAY_BE_INFINITE = (
    "verification.max_residual_ratio",
    "depth.depth_stall_ratio",
    "gauge.scale_alarm_log",
)
#: MASt3R's patch side: images are cropped to multiples of it (como3r.data.preprocess.PATCH)
_PATCH = 16


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"section.key": value}`` of a nested configuration dict."""
    flat: dict[str, Any] = {}
    for name, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(_flatten(value, f"{prefix}{name}."))
        else:
            flat[f"{prefix}{name}"] = value
    return flat


def validate(config: Config) -> Config:
    """Check every value's range; ``load_config`` and ``apply_overrides`` run it.

    Returns:
        ``config`` unchanged.

    Raises:
        ConfigError: the first out-of-range key, named with its section
            (``tracking.sigma_ray must be > 0, got -1.0``).
    """
    values = _flatten(config_to_dict(config))
    rules = (
        (_POSITIVE, "> 0", lambda v: v > 0),
        (_NON_NEGATIVE, ">= 0", lambda v: v >= 0),
        (_AT_LEAST_ONE, ">= 1", lambda v: v >= 1),
        (_FRACTION, "in [0, 1]", lambda v: 0 <= v <= 1),
    )
    for keys, rule, holds in rules:
        for key in keys:
            if not holds(values[key]):
                raise ConfigError(f"{key} must be {rule}, got {values[key]}")
    if config.verification.max_decodes_per_keyframe < 2:
        raise ConfigError(
            "verification.max_decodes_per_keyframe must be >= 2 (one candidate's "
            f"two decodes), got {config.verification.max_decodes_per_keyframe}"
        )
    long_side = config.input.long_side
    if long_side < _PATCH or long_side % _PATCH:
        raise ConfigError(
            f"input.long_side must be a positive multiple of {_PATCH} (MASt3R's "
            f"patch size), got {long_side}"
        )
    check_decentralized(config.decentralized)
    check_simulated_prior(config.simulated_prior)
    return config


def config_to_dict(config: Any) -> dict[str, Any]:
    """Plain nested dict of a configuration dataclass (YAML-ready)."""
    return dataclasses.asdict(config)


def differing_key(a: Config, b: Config) -> str | None:
    """The first key whose values differ, as ``"section.key: a_value -> b_value"``; None
    when the configurations are equal."""
    flat_a, flat_b = _flatten(config_to_dict(a)), _flatten(config_to_dict(b))
    return next(
        (
            f"{key}: {value!r} -> {flat_b.get(key)!r}"
            for key, value in flat_a.items()
            if flat_b.get(key) != value
        ),
        None,
    )


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Check (and where lossless, convert) ``value`` to the field type ``annotation``."""
    origin = get_origin(annotation)
    if origin is Literal:
        if value not in get_args(annotation):
            raise ConfigError(f"{key}: {value!r} is not one of {list(get_args(annotation))}")
        return value
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping of settings, got {value!r}")
        return config_from_dict(annotation, value, prefix=f"{key}.")
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, str):
            # YAML 1.1 reads exponents without a dot (1e-3) as strings
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{key}: expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if math.isnan(value) or (math.isinf(value) and not (value > 0 and key in _MAY_BE_INFINITE)):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported configuration field type {annotation!r} for {key}")


def config_from_dict(cls: type[C], values: Mapping[str, Any], prefix: str = "") -> C:
    """Build a configuration dataclass from a (partial) nested mapping.

    Missing keys keep their defaults; unknown keys raise :class:`ConfigError`.
    """
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"unknown configuration key {prefix}{unknown[0]!s}")
    kwargs = {name: _coerce(v, hints[name], f"{prefix}{name}") for name, v in values.items()}
    return cls(**kwargs)


def _parse_scalar(text: str) -> Any:
    """Parse the right-hand side of a ``key=value`` override as a YAML scalar."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"cannot parse override value {text!r}: {_yaml_problem(exc)}") from None


def apply_overrides(config: Config, overrides: list[str]) -> Config:
    """Apply dotted ``section.key=value`` overrides, e.g. ``tracking.sigma_ray=0.002``."""
    tree = config_to_dict(config)
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        node = tree
        parts = key.strip().split(".")
        for i, part in enumerate(parts):
            if not isinstance(node, dict) or part not in node:
                raise ConfigError(f"unknown configuration key {'.'.join(parts[: i + 1])}")
            if i == len(parts) - 1:
                if isinstance(node[part], dict):
                    raise ConfigError(f"{key} is a section; override one of its keys")
                node[part] = _parse_scalar(text.strip())
            else:
                node = node[part]
    return validate(config_from_dict(Config, tree))


def load_config(path: str | Path) -> Config:
    """Read a YAML configuration; keys it does not mention keep their defaults."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration ({exc.strerror})") from None
    try:
        values = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        raise ConfigError(f"{where}: not valid YAML: {_yaml_problem(exc)}") from None
    if values is None:
        values = {}
    if not isinstance(values, Mapping):
        raise ConfigError(f"{path}: expected a mapping of configuration sections")
    try:
        return validate(config_from_dict(Config, values))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """A YAML error in one line (PyYAML's own message spans several, with a code excerpt)."""
    problem = getattr(exc, "problem", None)
    context = getattr(exc, "context", None)
    text = "; ".join(str(part) for part in (context, problem) if part) or str(exc)
    return " ".join(text.split())


def dump_config(config: Config, path: str | Path) -> None:
    """Write the full effective configuration as YAML."""
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))
