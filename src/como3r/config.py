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
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml

from como3r.decentralized.config import DecentralizedConfig
from como3r.decentralized.config import check_config as check_decentralized
from como3r.errors import ConfigError


@dataclass(frozen=True)
class InputConfig:
    """Front-end input (C-Tab. 3, "Front-end input")."""

    long_side: int = 512
    frame_rate_hz: float = 30.0
    subsample: int = 2
    # layout of the --agent inputs (como3r addition; `como3r run --format`): auto detects
    # each folder's layout (como3r.data.readers), the others force one
    format: Literal["auto", "agent", "tum", "7scenes", "euroc", "kitti", "tanks", "rosbag"] = "auto"
    # image topic of ROS log inputs (`como3r run --topic`); empty: each log's only one
    topic: str = ""
    # frames read and encoded ahead on a worker thread while the front-end works on the
    # current one (runtime.prefetch); 0 encodes each frame in line
    prefetch_frames: int = 2


@dataclass(frozen=True)
class MatchingConfig:
    """Projective matching of C-Eq. 1 (values of MASt3R-SLAM's released configuration).

    Attributes:
        occlusion_ratio: a match is occluded when its two 3-D points are further apart than
            this fraction of the query point's range (unitless, so it holds from a tabletop
            to a street, where MASt3R-SLAM's absolute 0.1 m rejected every match of a 3 %
            depth error at 30 m). 0.1 m is 3-10 % of MASt3R-SLAM's indoor depths (1-3 m).
            Measured: 0.02-0.03 rejected the agents' true meeting on the aliasing façades
            (tests/coordination/test_association.py); 0.07 made 8 keyframes of 12 frames on
            tests/frontend/test_agent.py's scene, 0.1 and 0.2 six.
        descriptor_radius, descriptor_dilation_max: window radius and largest dilation of the
            descriptor search in pixels of a 512-pixel-long image; scaled with the long side
            of the pointmaps matched (:func:`como3r.geometry.units.pixels_at`).
    """

    max_iters: int = 10
    lambda_init: float = 1e-8
    convergence_tol: float = 1e-6
    occlusion_ratio: float = 0.1
    descriptor_radius: int = 3
    descriptor_dilation_max: int = 5


@dataclass(frozen=True)
class TrackingConfig:
    """Frame-to-keyframe tracking, C-Eq. 2 and C-Eq. 17; keyframing (C-Tab. 3)."""

    # sigma_dist: range noise as a fraction of keyframe i's median range; sigma_ray is an
    # angle and needs no scale. C-Tab. 3's 10 m is 10 at the 1 m reference depth of
    # geometry.units (set tracking.sigma_dist=10 to restore it): a range term that weak
    # leaves each edge's joint (s, t) scaling to the rays alone. Measured on the realistic
    # simulated prior (one agent, 40 frames at 128 px, seeds 1 and 2, ATE % of path):
    # 10 -> 11.7 / 12.0 %, 1 -> 6.9 / 8.2, 0.3 -> 5.5 / 6.0, 0.1 -> 2.1 / 4.0 (independent
    # per-image errors); with sequence-correlated errors 0.1 -> 1.7 / 2.7, 0.05 -> 1.7 / 2.5,
    # 0.02 -> 1.6 / 2.5: 0.1, about twice the prior's 5 % relative depth error.
    # sigma_depth (C-Eq. 17, log-depth, so already relative): C-Tab. 3's 10 leaves the
    # calibrated residual to pixel parallax alone, which cannot tell forward motion from the
    # Sim(3) scale; measured on the realistic prior (one agent, true calibration, 40 frames at
    # 160 px, ATE % of path): 20 deg per frame 12.1 % (10) -> 1.4 % (0.1), 1.7 % (0.03);
    # 3.6 deg per frame 0.52 % (10) -> 0.49 % (0.1)
    sigma_ray: float = 3e-3
    sigma_dist: float = 0.1
    sigma_pixel: float = 1.0
    sigma_depth: float = 0.1
    huber_k: float = 1.345
    max_iters: int = 50
    rel_cost_tol: float = 1e-3
    # ||tau||_2 that ends the solve, its translation in units of the keyframe's median range
    # (geometry.units: C-Tab. 3's 1e-3 at the 1 m reference depth). Absolute, it stopped 14
    # of 25 solves at 1/100 of a room's scale and none at 100 times (3 of 24 at 1); relative
    # 14-16 at all three, ATE within 0.0002 of the path length of the absolute stop's
    step_tol: float = 1e-3
    lambda_init: float = 1e-6
    lambda_max: float = 1e3
    tikhonov_floor: float = 1e-9
    keyframe_match_fraction: float = 0.333
    q_min: float = 1.5
    min_match_fraction: float = 0.05  # MASt3R-SLAM: below this the frame is lost
    reloc_match_fraction: float = 0.3  # MASt3R-SLAM relocalization acceptance
    # Not in the paper (0 restores it): a solved frame pose is accepted only if this share
    # of its valid matches agree with it (ray angle below inlier_angle_deg, range within
    # sigma_dist of the keyframe's). The prior's gross failures (a confident wrong pair pose)
    # otherwise pass as tracked and become keyframes. Measured on the realistic prior:
    # accepted tracks 0.63-0.99 (96-512 px, rotation errors up to 4 deg), a gross failure
    # 0.26 (14.7 deg rotation error, which cost the low-texture family 19 % ATE). A new
    # keyframe's sequential edge direction (kf - 1, kf), decoded apart from tracking, takes
    # the same test (frontend.agent AgentFrontend._checked_direction)
    min_inlier_fraction: float = 0.5
    # at the input's own resolution: an input enlarged by s to input.long_side gets s times
    # the angle (frontend.tracker.FrameTracker). 320x240 aerial input at 512: agreement of
    # good tracks 0.39-0.49 at 1 deg (3 of 12 frames rejected, ATE 0.90 % of the path)
    inlier_angle_deg: float = 1.0
    # C-Eq. 3 on "ranges" along the keyframe's own rays (default) or on 3-D "points" (the
    # paper); see frontend.keyframes.Keyframe.fuse
    fusion: Literal["ranges", "points"] = "ranges"
    # uncalibrated runs estimate one pinhole camera per agent and track as calibrated runs
    # do (C-Eq. 16-17); False: the paper's uncalibrated mode (C-Eq. 2 on each canonical
    # pointmap's own rays). See frontend.calibration
    self_calibration: bool = True
    # keyframes whose pairs re-estimate the self-calibrated camera (frontend.calibration
    # refine_focal); they wait for it before they are sent. 0 keeps the first frame's
    # estimate. Measured on the realistic prior (640x480 -> 512, loop of 100 frames, agents
    # whose first frames believed 309.8 and 292.1 px, true 333.6): settled on 2 keyframes
    # 331.9 / 331.8 px, on 3 332.5 / 331.7, on 4 332.2 / 331.3; 3 keeps a second pair
    # against one bad decode and holds an agent's first keyframes briefly
    self_calibration_keyframes: int = 3


@dataclass(frozen=True)
class LocalSolveConfig:
    """Per-agent local keyframe-graph solve (C-Tab. 3, C-Sec. B.2)."""

    max_iters: int = 10
    pinned_keyframes: int = 1
    # ||tau||_2 with translations in units of the newest keyframe's median depth, as
    # global_ba.step_tol (see there): C-Tab. 3's absolute 1e-8 runs every solve to max_iters.
    # Demo scene (2 agents x 15 frames at 512x384): local solves 16.5 + 27.5 s -> 9.8 + 21.2 s,
    # agent ATE 3.29 / 9.42 mm and merged 14.5 mm unchanged
    step_tol: float = 1e-4
    tikhonov_base: float = 1e-6
    tikhonov_retries: int = 6
    lm_lambda: float = 0.0
    min_match_fraction: float = 0.1  # MASt3R-SLAM: intra-agent loop-closure acceptance
    # not in the paper (bounded memory, issue 14): the solve keeps every edge, but an edge
    # with both keyframes older than the newest dense_keyframes enters by the quadratic model
    # of its dense energy in its relative pose (optim.factors.QuadraticEdges), made again
    # when an endpoint's pointmap changes or its relative pose moves more than
    # relinearize_tol (radians, nepers, keyframe i's median range)
    dense_keyframes: int = 8
    relinearize_tol: float = 1e-3


@dataclass(frozen=True)
class RetrievalConfig:
    """Cross-agent retrieval with binary ASMK (C-Tab. 3, C-Sec. B.3)."""

    codebook_size: int = 65536
    binary: bool = True
    use_idf: bool = False
    alpha: float = 3.0
    similarity_threshold_asmk: float = 0.0
    multiple_assignment_build: int = 1
    multiple_assignment_query: int = 5
    k_nn: int = 3
    min_similarity: float = 5e-3


@dataclass(frozen=True)
class VerificationConfig:
    """Inter-agent geometric verification, C-Eq. 12.

    The fields after ``tau_inter`` are not in the paper (como3r additions, see
    :mod:`como3r.coordination.association`):

    * ``min_covisible_ratio``: of the pixels of one view that the pair's own predicted
      geometry places inside the other view, onto a pixel whose confidence is at least
      ``covisible_min_confidence``, at least this share must be validly matched, in both
      directions. A prior that hallucinates a pose from repeated façades predicts overlap
      it cannot match. 0 restores the paper's single test. Measured on the aliasing
      façades (tests/coordination/test_association.py, occlusion_ratio 0.1): true pairs
      0.87-0.97, hallucinated ones 0.15-0.55; 0.7 sits between them.
    * ``max_residual_ratio``: an edge between agents that already share a gauge must
      agree with their poses: the median distance of its matched points lifted into the
      shared world at most this fraction of their median range (about the relative
      rotation error in radians). ``inf`` admits every such edge, as the paper does.
    * ``max_decodes_per_keyframe``: the prior decodes one keyframe's verification may
      cost, over ALL other agents: the retrieval hits (``retrieval.k_nn`` over all other
      agents' keyframes, best first) are verified while their worst case (two decodes
      each, C-Eq. 12 is symmetric) fits, so the coordinator's work per keyframe does not
      grow with the team (the paper verifies every hit: with its ``k_NN = 3`` that is at
      most 6, the default, which so leaves the paper's behaviour unchanged).
    * ``max_within_component``: of those hits, at most this many whose agent already
      shares the keyframe's gauge component are verified (best first). Such an edge no
      longer synchronises a gauge (C-Sec. A.4: only the first edge between two
      components transports one); it only adds a loop constraint to the global BA, and
      one per keyframe keeps every meeting keyframe tied to the others, while the
      verifications that decide a merge are not spent on agents already merged. Measured
      on a 4-agent synthetic scene (320x240, 16 frames each, overlap 0.5, simulated
      prior, seed 0): the coordinator's decodes per keyframe 2.95 -> 1.58 (56 -> 30),
      admitted inter-agent edges 23 -> 12, the same three gauge merges, merged ATE
      10.5 -> 8.4 mm; 3 agents: 2.56 -> 1.39 (46 -> 25), merged ATE 9.6 -> 6.3 mm;
      8 agents: 3.93 -> 2.78 (106 -> 75), edges 30 -> 20, merged ATE 12.1 -> 15.2 mm
      (fewer loop constraints cost accuracy there). One seed each, and a loss at 8 agents:
      the default is 3 (``retrieval.k_nn``'s default), the paper's behaviour, until it is
      measured over seeds and team sizes; ``k_nn`` or more is the paper.
    """

    tau_inter: float = 0.1
    min_covisible_ratio: float = 0.7
    covisible_min_confidence: float = 1.5
    max_residual_ratio: float = 0.25
    max_decodes_per_keyframe: int = 6
    max_within_component: int = 3


@dataclass(frozen=True)
class GaugeConfig:
    """Gauge synchronization, C-Eq. 14-15.

    ``min_consistent_edges`` is not in the paper (como3r addition): two gauge components
    merge once this many verified edges between them agree on the aligning transform
    (each within ``verification.max_residual_ratio`` under it). The default 1 is the
    paper's synchronization on the first verified edge.

    ``align_focal`` (como3r addition, self-calibrated runs only): at a merge the moving
    component's focal length is corrected to agree with the anchor's on the supporting
    keyframe pairs (:mod:`como3r.frontend.focal`), searched within
    ``focal_search`` in log focal. Measured on a two-agent simulated scene (160 px,
    2 x 30 frames, realistic prior, merged ATE % of mean agent path): agents' estimates
    +1.2 % and -8.7 % off give 3.8 % without it; both on one focal length 0.72 %.
    The terminal cleanup re-aligns every agent of a component on up to four of its
    admitted edges to the agents settled before it (anchor first,
    ``Coordinator._refine_focals``): a merge often rests on one pair. Measured on a 3-agent
    room (320x240 -> 512, 12 processed frames each, seed 0): merged ATE 2.7 -> 1.07 % of
    path (calibrated: 0.38 %); seed 1: 0.72 -> 0.85 % (one focal length, but the single
    edge between agents 0 and 1 leaves a 3 % scale offset the focal errors had hidden).

    ``scale_alarm_log`` (como3r addition): the scale watch of wrong links. An edge between
    agents that already share a gauge whose own similarity (Umeyama on its lifted points)
    would rescale the map by more than this in ``|log s|`` is held back (status
    ``inconsistent``, counted in ``edges_scale_inconsistent`` and logged); at a merge over
    several agreeing edges, an edge whose own ``T*`` scale differs from the joint one by
    more than this does not count as support (``gauge_scale_held``). A single first edge
    has nothing to be compared with: ``min_consistent_edges`` > 1 makes the merge watch it.
    """

    min_correspondences: int = 64
    min_consistent_edges: int = 1
    align_focal: bool = True
    focal_search: float = 0.3
    scale_alarm_log: float = 0.2


@dataclass(frozen=True)
class GlobalBAConfig:
    """Global Sim(3) bundle adjustment, C-Eq. 5 and C-Eq. 25 (C-Tab. 3)."""

    trigger_interval_edges: int = 1
    max_iters_stream: int = 50
    max_iters_cleanup: int = 100
    cleanup_passes: int = 5
    # cleanup stops when no keyframe moved more than this fraction of the component's median
    # keyframe depth (C-Sec. A.7's 5 mm at the 1 m reference depth of geometry.units)
    cleanup_stop_translation: float = 5e-3
    # a solve stops when ||tau||_2 < step_tol, its translations in units of the component's
    # median keyframe depth (optim.optimizer, length_scale). C-Sec. B.2 prints 1e-8; below
    # about 1e-6 float32 factors cannot resolve the step, and Huber IRLS converges linearly
    # (|tau| shrinks x0.6-0.8 per iteration), so 1e-8 runs nearly every solve to max_iters.
    # Demo scene (2 agents x 15 frames, long side 256, scene depth 4.6 m), absolute
    # tolerance 1e-8 / 1e-5 / 1e-4 / 1e-3: in-stream BA 154 / 100 / 73 / 47 iterations,
    # cleanup 129 / 58 / 37 / 20, coordinator 71 / 41 / 33 / 23 s; merged ATE 4.180 / 4.180 /
    # 4.179 / 4.175 cm, map accuracy 33.42 cm and F-score 0.5735 in all four. 1e-4 of the
    # scene depth (4.6e-4 there) keeps a margin; 1e-8 restores the paper at 1 m.
    step_tol: float = 1e-4
    # not in the paper: an edge's matches are linearized again only when its relative pose
    # moved more than this (radians, nepers, the component's median keyframe depth) since
    # they last were, in this solve or an earlier one, or an endpoint's pointmap changed;
    # in between, its blocks come from the quadratic model of that linearization
    # (optim.relinearization; iSAM2's relinearization threshold). 0: every edge at every
    # iteration, as the paper
    relinearize_tol: float = 1e-3
    lm_lambda: float = 0.0
    tikhonov_base: float = 1e-6
    tikhonov_retries: int = 6
    # backend of the C-Eq. 25 solve (como3r.optim.linear.solve): "auto" takes a dense
    # Cholesky up to 60 free keyframes and above it "band" (conjugate gradients with a band
    # + coarse two-level preconditioner, como3r.optim.band), whose cost grows about linearly
    # with and without many loop closures: at 2,000 keyframes 0.25x SuperLU's solve time
    # with a loop edge every 4 keyframes, 0.9-1.6x with one every 50. "sparse" (SuperLU)
    # and "pcg" (block-Jacobi conjugate gradients, 40x SuperLU on chain-like graphs) stay
    # selectable
    linear_solver: Literal["auto", "dense", "sparse", "pcg", "band"] = "auto"


@dataclass(frozen=True)
class DepthRefinementConfig:
    """Segment-level depth refinement and alternation, C-Eq. 19-24, C-Sec. A.6-A.7."""

    variant: Literal["segment", "pixel", "pixel_laplacian"] = "segment"
    slic_segments: int = 200
    slic_compactness: float = 8.0
    slic_sigma: float = 1.0
    slic_min_confidence: float = 1.5
    min_valid_pixels: int = 16
    # C-Eq. 21 point noise as a fraction of keyframe i's median range (C-Tab. 3's 0.05 m at
    # the 1 m reference depth of geometry.units)
    sigma_point: float = 0.05
    lambda_smooth: float = 1.0
    lambda_prior: float = 1.0
    lambda_lm: float = 0.05
    step_clip: float = 0.5
    inner_iters: int = 10
    alternation_rounds: int = 100
    # what the poses do in the rounds of C-Sec. A.7 step 2 in a multi-agent component:
    # "frozen" = one depth step at the poses of step 1's passes (departs from the paper, see
    # backend.alternation; alternation_rounds then only allows or, at 0, skips it),
    # "pose_pass" = the paper's rounds, a short pose pass after each depth step
    round_poses: Literal["frozen", "pose_pass"] = "frozen"
    pose_pass_iters: int = 50
    depth_convergence_tol: float = 5e-3  # max |delta s| that ends the alternation (A.7)
    # C-Eq. 19's base pointmap: "insertion" = the keyframe's first prediction (the paper),
    # "fused" = its fused pointmap (C-Eq. 3) when the cleanup starts; see backend.global_graph
    refine_from: Literal["fused", "insertion"] = "fused"
    # boundary residual of C-Eq. 22: "jump_change" = (s_a - s_b), the refinement may not
    # change the prior's depth jump between adjacent segments; "log_depth" = the paper's
    # (s_a - s_b) + Delta_ab, refined log-depths pulled together (see backend.depth_refinement)
    boundary_residual: Literal["jump_change", "log_depth"] = "jump_change"
    # a round whose max |delta s| exceeds this fraction of the previous round's has stalled
    # and ends the alternation (later rounds drift the map; inf disables)
    depth_stall_ratio: float = 0.5


@dataclass(frozen=True)
class VisualizationConfig:
    """Map export and mesh visualisation (C-Tab. 3)."""

    tau_slant: float = 0.1
    map_min_confidence: float = 1.5
    voxel_size_m: float = 0.0


@dataclass(frozen=True)
class SessionConfig:
    """The coordinator's memory and its session store (not in C-Tab. 3; README, "Run
    output").

    ``resident_keyframes``: per agent, how many of its newest keyframes the coordinator keeps
    whole in memory (a count). The others' encodings, images and pointmaps, and the matches
    of the sequential edges between them, are paged out to the session store after every
    message and read back while a verification or a solve needs them
    (:mod:`como3r.store.paging`), so the coordinator's memory does not grow with
    the sequence. Each agent's front-end keeps as many of its own keyframes whole and pages
    the others, and the matches of the edges between them, out to a private spill folder
    after every frame (:class:`como3r.frontend.paging.AgentPaging`). The results are the
    same for every value.

    ``spill_dir``: the folder in which each agent makes its spill folder (removed when the
    agent ends); empty: the system's temporary folder.
    """

    resident_keyframes: int = 8
    spill_dir: str = ""


@dataclass(frozen=True)
class SimulatedPriorConfig:
    """Error model of the simulated prior (README, "Python API").

    ``model`` selects it: ``"realistic"`` (default) imitates MASt3R's failure modes,
    ``"easy"`` is the near-oracle of round 1 for tests that need precision, ``"v2"`` (in
    progress, not yet the default) adds to the realistic model what the image reveals
    (descriptors, retrieval and confidence from local contrast; a confidence blind to the
    low-frequency error; per-pair rays); the keys from ``focal_error`` on are used by the
    realistic and v2 models only. Units and sources of every key:
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


C = TypeVar("C")

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
    "session.resident_keyframes",
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
    # the simulated prior owns its error model's ranges; imported here because it needs torch
    from como3r.prior.simulated_errors import check_config as check_simulated_prior

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
    if dataclasses.is_dataclass(annotation):
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
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
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
