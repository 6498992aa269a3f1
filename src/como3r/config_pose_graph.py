"""The multi-robot pose graph's section of the decentralized mode's configuration
(``decentralized.pose_graph``, :mod:`como3r.config_decentralized`, which re-exports it):
the formulations and solvers of F-Sec. III-C, the odometry and loop factors' noise, pairwise
consistency and the scale-collapse alarm. Like the rest of that configuration, no setting is
a length: translations are fractions of the keyframe spacing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Formulation = Literal["base", "independent", "smoothed", "shared"]
Solver = Literal["lm", "gnc"]
FORMULATIONS: tuple[str, ...] = ("base", "independent", "smoothed", "shared")
SOLVERS: tuple[str, ...] = ("lm", "gnc")


@dataclass(frozen=True)
class PoseGraphConfig:
    """Multi-robot pose graph (F-Sec. III-C) and its solvers.

    Attributes:
        formulation: ``base`` (loop scale from odometry, F-Eq. 6), ``independent`` (one
            scale per loop, F-Eq. 7-8), ``smoothed`` (scales tied within clusters,
            F-Sec. III-C-c) or ``shared`` (one scale for all loops).
        solver: ``lm`` (Levenberg-Marquardt) or ``gnc`` (graduated non-convexity over LM).
            ``gnc``: behind pairwise consistency it equals LM where LM is right (the clean
            and 5-20 % rows of ``benchmarks/wrong_loops.py``, the scenes of
            ``tests/decentralized``) and is better where wrong loops survive it (50 % wrong:
            merged ATE 0.12 % of the path against LM's 0.39 %); on a held-out scene without
            it, smoothed/GNC 0.032 m against smoothed/LM 0.100 m. It costs a few LM solves
            more only when some loop's residual is beyond the inlier threshold.
        scale_init: initial loop scale: ``odometry`` (F-Eq. 6) or ``prior`` (raw prior).
        odom_sigma_rot_deg: odometry factor rotation noise per keyframe step [deg].
        odom_sigma_trans_ratio: odometry factor translation noise per keyframe step, as a
            fraction of the keyframe spacing (median odometry distance between consecutive
            keyframes of the graph,
            :func:`~como3r.decentralized.initial_estimate.keyframe_spacing`); 0.04: 2 cm at
            the default 0.5 m spacing of the synthetic scene, 5 cm at a 1.2 m outdoor spacing
            (the paper states no noise values).
        odom_scale_walk: with ``> 0``, a scale per odometry step
            (:mod:`~como3r.decentralized.pose_graph`): the random walk tying consecutive
            steps' scales, per square root of the keyframe spacings travelled; 0: the
            paper's metric odometry (F-Sec. III). Off by default: it fits the scenes it was
            tuned on and fails held-out ones. Re-solving the final graphs of
            ``benchmarks/robustness.py --mode decentralized`` (prior ``v2``, 3 robots,
            ``vio`` odometry, tabletop / room / aerial = 0.1 / 1 / 20x; keyframe merged ATE
            % of one robot's path) with 0.1 (and ``odom_scale_prior`` 0.5,
            ``loop_sigma_trans_floor_ratio`` 1, ``scale_smoothing_sigma`` 0.02): seed 0 3.30
            / 3.17 / 3.16 -> 2.16 / 2.12 / 2.96 (with true loops 2.34 / 2.33 / 2.35 -> 1.05
            / 1.06 / 1.21), but held-out seed 1 2.06 / 2.45 / 2.19 -> 2.60 / 3.91 / 3.03
            (the full run of seed 1's tabletop 1.96 -> 2.76) and a ``lio`` odometry (the
            preset simulated on the keyframes) bent 1.97 / 1.65 / 1.98 -> 2.00 / 1.88 /
            2.85: the measured loops' free scales and direction errors pull the scales where
            they please. Alone (0.1, prior 0.3) seed 0's room gave 2.90.
        odom_scale_prior: standard deviation of the prior holding each odometry step's scale
            near 1 (with ``odom_scale_walk > 0``).
        odom_start_scale_sigma: scale uncertainty of the odometry at its start, as a fraction
            of each step's length along the step, decaying as ``exp(-d /
            odom_start_spacings)`` with the distance ``d`` travelled
            (:func:`~como3r.decentralized.factor_noise.odometry_noise`; pairwise consistency
            counts it too), of a robot whose odometry's kind is undeclared (a declared
            robot's is its own, ``PoseGraphProblem.starts``:
            ``DecentralizedConfig.vio_start_scale_error`` for a ``vio`` robot, none for a
            ``metric`` one; :mod:`~como3r.decentralized.odometry_kind`). 0: the paper's
            metric odometry (F-Sec. III), the behaviour before declarations.
        odom_start_spacings: the distance, in keyframe spacings, over which that uncertainty
            falls by ``e`` (an undeclared robot's; a declared ``vio`` robot's is
            ``DecentralizedConfig.vio_start_depths`` in keyframe spacings).
        loop_sigma_rot_deg: loop factor rotation noise at confidence p = 1 [deg]; the
            information is multiplied by p (F-Eq. 3).
        loop_sigma_trans_ratio: loop factor translation noise at p = 1, as a fraction of
            the keyframe spacing; 0.2: 10 cm at a 0.5 m spacing, 24 cm at 1.2 m (the prior's
            relative-translation error grows with the scene depth, as the spacing does).
        loop_sigma_trans_floor_ratio: floor of a loop's translation noise, in keyframe
            spacings, that the confidence p does not lower (F-Eq. 3 divides the loop's
            variances by p alone; :mod:`~como3r.decentralized.pose_graph`). 0 here; a
            decentralized run sets it from ``DecentralizedConfig.loop_lever_arm_depths``
            (:meth:`DecentralizedConfig.pose_graph_config`).
        loop_scene_depth_ratio: with ``> 0``, a loop's noise is a full ``(6, 6)``
            covariance in which its rotation error turns camera b about the scene this many
            keyframe spacings in front of camera a (the registering one), plus the isotropic
            sigmas (:func:`~como3r.decentralized.factor_noise.loop_covariance`), in the solve
            and in pairwise consistency; 0: the isotropic sigmas alone. 0 here; a
            decentralized run sets it from ``DecentralizedConfig.loop_covariance``.
        scale_prior_sigma: weak prior on every scale variable, relative to its initial
            value; makes a single loop between two robots well posed.
        scale_smoothing_sigma: noise of the scale-difference factors of F-Sec. III-C-c: the
            scatter allowed between the scales of loops in one cluster (0.2: the prior's
            pair-to-pair scale inconsistency is of that order).
        cluster_window: loops whose endpoints on both robots are fewer than this many
            keyframes apart share a cluster (F-Sec. III-C-c: ten).
        lm_max_iterations: Levenberg-Marquardt iterations per solve.
        gnc_loss: ``tls`` (truncated least squares) or ``gm`` (Geman-McClure, GTSAM's default).
        gnc_inlier_probability: chi-square quantile (6 dof) of the inlier threshold.
        gnc_mu_step: factor of the GNC control parameter per outer iteration.
        gnc_max_iterations: GNC outer iterations.
        consistency: ``pcm``: before a solve, keep the largest set of pairwise-consistent
            loops of each robot pair (:mod:`~como3r.decentralized.consistency`); ``none``:
            every loop.
        consistency_probability: chi-square quantile (6 dof) under which two loops'
            odometry cycle counts as consistent.
        scale_alarm_log: a solve that changes a robot's scale (its path length over its
            metric odometry's) or the merged map's (solved over measured loop lengths) by
            more than this in ``|log|`` is held back and reported (scale-collapse alarm;
            ``.inf``: off). 0.2: clean missions of ``benchmarks/wrong_loops.py`` change it
            by at most 0.004 and a correct solve of the aliasing scene of
            ``tests/decentralized`` by 0.002; uncaught wrong loops by 0.3-1.2.
    """

    formulation: Formulation = "smoothed"
    solver: Solver = "gnc"
    scale_init: Literal["odometry", "prior"] = "odometry"
    odom_sigma_rot_deg: float = 0.5
    odom_sigma_trans_ratio: float = 0.04
    odom_scale_walk: float = 0.0
    odom_start_scale_sigma: float = 0.0
    odom_start_spacings: float = 0.0
    odom_scale_prior: float = 0.5
    loop_sigma_rot_deg: float = 2.0
    loop_sigma_trans_ratio: float = 0.2
    loop_sigma_trans_floor_ratio: float = 0.0
    loop_scene_depth_ratio: float = 0.0
    scale_prior_sigma: float = 1.0
    scale_smoothing_sigma: float = 0.2
    cluster_window: int = 10
    lm_max_iterations: int = 100
    gnc_loss: Literal["tls", "gm"] = "tls"
    gnc_inlier_probability: float = 0.99
    gnc_mu_step: float = 1.4
    gnc_max_iterations: int = 100
    consistency: Literal["pcm", "none"] = "pcm"
    consistency_probability: float = 0.99
    scale_alarm_log: float = 0.2
