"""Configuration sections of the per-agent front-end: input, matching, tracking and
keyframing, the local keyframe-graph solve (C-Tab. 3's front-end rows). Sections of
:class:`como3r.config.Config`, imported from :mod:`como3r.config`, whose docstring says
where the defaults come from.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


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
        descriptor_radius, descriptor_dilation_max: window radius (in samples) and largest
            dilation (in pixels) of the descriptor search, at a 512-pixel-long image; scaled
            with the long side of the pointmaps matched
            (:func:`como3r.geometry.units.pixels_at`), the radius never below its value
            here. Below 512 px the paper's 7x7 window scaled to 3x3 (160 px: radius 1,
            dilations 2, 1, a reach of 3 px or 2 % of the image, 9 % at 512) could not
            pull back the v2 prior's zoomed matches (its two heads' focal lengths apart by
            up to 6 %, matches up to 5 px off at 160 px, which the tracking solve explains
            as forward motion); radius 3 and dilations 2, 1 reach 9 px (5.6 %).
        descriptor_consensus: not in the paper (False restores its search at every size);
            below 512 px each match's move by the search is replaced by the median move of
            the matches of a window of query pixels around it, the smallest odd number at
            least ``512 / long_side`` (5 at 160 px, 3 at 256, 1 at 512: the paper's search
            unchanged there), unless its own pixel is within a pixel of that
            (:func:`como3r.frontend.match_consensus.displacement_consensus`). Why: where the
            descriptors cannot tell pixels apart (flat paint: the v2 prior's descriptors
            there are per-pixel noise around one colour) the search follows the noise.
            Measured on the v2 low-texture family at 160 px (seed 0, 8 tracked frames,
            error to the true correspondence from the scene's depth and poses; agreement
            of the pose solved from the matches, ``tracking.min_inlier_fraction`` 0.5):
            projection alone 1.54 px, agreement 0.96; the scaled paper window 1.87 px,
            0.60; radius 3 and dilations 2, 1 3.06 px, 0.37; the same with the median of
            5x5 1.12 px, 0.80. The search moves these matches as far at 512 px (8.7 px
            of 512 against 5.5 for the projection: 1.7 % of the image, 1.9 % at 160), but
            the scene's 160-px images are enlarged 3.2 times there, and tracking's
            agreement angle with them (3.2 deg), so they pass (agreement 0.89; an input
            of 512 px or more keeps 1 deg: not measured). No test of a single match
            separates the moves: on this family moves that raised the descriptor score
            by 0.05-0.1 made 57-74 % of the matches worse, on the room
            family 88 % better, and the descriptor confidence of the worse ones (median
            3.1, room 7.3) overlaps the room's. The prior's geometric error that the
            search corrects (pose, the heads' focal and principal point) varies slowly
            over the image; the noise does not. Single-agent cells of
            benchmarks/robustness.py (v2, 160 px, seeds 0 / 1; tracked, ATE % of path):
            low-texture before 1.00 1.09 / 0.85 2.18, room 1.00 0.68 / 1.00 0.74; radius 3
            with a median of 3 low-texture seed 1 0.82 tracked, of 5 without keeping the
            search's own pixel 1.00 1.03 / 1.00 1.16 and room 0.59 / 0.27, of 9 1.51 / 1.02
            and 0.61 / 0.34; dilations 3, 2, 1 with a median of 5 lost 39 of 40 frames of
            low-texture seed 1. Keeping the search's own pixel within a pixel of the
            median (the default), every cell of both seeds tracked (before: all but
            low-texture seed 1), ATE % of path before -> after, seed 0 / 1: low-texture
            1.09 / 2.18 -> 1.17 / 1.23, room 0.68 / 0.74 -> 0.263 / 0.375, tabletop
            0.78 / 0.56 -> 0.210 / 0.264, street 0.85 / 0.79 -> 0.288 / 0.358, aerial
            0.76 / 0.70 -> 0.241 / 0.306, aliasing 1.02 / 0.99 -> 0.206 / 0.365, forward
            0.38 / 0.31 -> 0.264 / 0.193, fast 0.44 / 0.27 -> 0.098 / 0.155, covered
            0.89 / 0.78 -> 0.120 / 0.306, revisit 0.48 / 0.56 -> 0.100 / 0.143, rotation
            RPE 0.24 / 0.25 -> 0.072 / 0.059 deg; 2 agents merged (tabletop, room,
            aerial; before as in benchmarks/robustness.py) 0.71 / 1.05, 0.82 / 0.93,
            0.69 / 1.01 -> 0.235 / 0.266, 0.160 / 0.256, 0.183 / 0.185. Real excerpts
            at 256 px (tests/test_real_data.py): 7-Scenes 2.33 -> 2.56 mm (2 -> 1
            keyframes), TUM teddy 2.81 -> 2.12 mm (4 -> 3). With a noise-free prior the
            median without that exception turned a 10 deg yaw 1.005e-3 rad off
            (tests/frontend/test_tracker.py, bound 1e-3).
    """

    max_iters: int = 10
    lambda_init: float = 1e-8
    convergence_tol: float = 1e-6
    occlusion_ratio: float = 0.1
    descriptor_radius: int = 3
    descriptor_dilation_max: int = 5
    descriptor_consensus: bool = True


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
