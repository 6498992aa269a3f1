"""Alternating pose-depth optimisation at cleanup (C-Sec. A.7).

Pose and structure share only the data term, so the coordinator optimises them block-
coordinate-wise once all agents have stopped:

1. global pose passes (depths frozen) of at most ``cleanup_iters`` iterations, at most
   ``cleanup_passes`` of them, until the largest translation update of a pass is below
   ``translation_tol`` (a fraction of the scene depth: 5 mm at the 1 m reference depth);
2. up to R rounds of: a depth step (segments from the current pointmaps, log-scale
   refinement, write-back), in the paper a short pose pass so the poses absorb the depth
   change, and a broadcast of the new poses to the agents.

By default (``round_pose_pass=False``, config ``depth.round_poses = "frozen"``) step 2 is
one depth step at the poses step 1 left: this departs from C-Sec. A.7's step 2d. The depth
step (C-Eq. 21) fits the segments' depths to the poses it is given,
including their error, and the pose pass after it then meets less resistance from the
intra-agent edges where a multi-agent loop pulls the trajectory (with the realistic
simulated prior the inter-agent edges are biased: range errors shared by an image's pairs
and slowly varying along a sequence). The rounds did not converge to a joint minimum: on a
2-agent 320x240 scene (``como3r synth --agents 2 --frames 100``) the merged keyframe ATE
was 21.0 mm after step 1 and 31.6, 41.1 and 49.7 mm after the pose passes of rounds 1-3
(each moving the poses by about 0.006 of the scene depth, above ``translation_tol``) while
the depth steps' ``max |ds|`` fell from 0.125 to 0.009; agent 0's middle grew by 5 %
against the rest of both agents and the rounds ended as "stalled". It is not a keyframe's
overall depth scale (the mean of its C-Eq. 19 log-scales) that slides: no keyframe's
median depth moved by more than 1.7 % over the three steps, and mostly down. Single-agent
components never had the pose pass.
With the poses frozen the trajectories are step 1's and the depth steps still refine the
map. Merged ATE and map accuracy (metrics.json), paper's rounds -> frozen, each pair from
one coordinator state: 320x240 2 x 50 frames seed 0 42.1 -> 20.9 mm, 0.283 -> 0.261 m;
2 x 60 seed 1 12.7 -> 10.6 mm, 0.276 -> 0.269 m; seed 2 10.8 -> 11.5 mm, 0.266 -> 0.266 m;
the demo scene (640x480, 2 x 30) 8.5 -> 7.2 mm, 0.289 -> 0.283 m.

With the poses frozen, step 2 is one depth step ("poses_frozen"): a second round would
solve the same problem (the same poses, matches, segments and base pointmaps ``X_init``;
its warm start the first one's log-scales) for 10 more inner iterations, which C-Sec. A.6
does not ask for. Those rounds (stopped as "stalled" below, after three) took a quarter to a
third of the cleanup and did not make the map better: fused-map F-score at 1 / 3 frozen
rounds (``como3r run --single-process --prior simulated --set depth.alternation_rounds=...``
on ``como3r synth`` scenes, 640x480 unless said): 2 agents x 24 frames seeds 1-3 0.744 /
0.745, 0.723 / 0.722, 0.757 / 0.755; 4 agents x 16 (``benchmarks/coordinator_stages.py``)
0.704 / 0.701; 2 x 30 at 320x240 and ``--scale 10`` 0.700 / 0.697; 3 x 20 at 512x384 and
``--scale 0.1`` 0.645 / 0.644; the same merged ATE in all.

The paper runs step 2 for R rounds and notes that it "converges within a handful of rounds";
with its pose passes a round ends the loop early once both the depth step's ``max |ds|`` and
the pose pass's ``max ||dt||`` are below their tolerances ("converged"), or once the depth
step has stalled: its ``max |ds|`` shrank by less than ``stall_ratio`` from the previous
round ("stalled"). Measured on the simulated prior's scenes, the first rounds remove a sixth
of the prior's depth distortion, after which ``max |ds|`` levels off near 0.5 % per round
while pose and depth keep sliding together and the error grows again, round after round, so
the rounds after the stall only cost time and accuracy.

Without a pose solver (``pose_pass=None``: poses that the caller must not move, e.g. an
agent's own loop-closed chain) step 1 is skipped and step 2 is one depth step whatever
``round_pose_pass`` says.

The solvers enter as callables, so this module knows nothing about graphs or keyframes::

    alternate(pose_pass=lambda iters: ba.run(iters),  # -> max ||delta t|| / scene depth
              depth_step=lambda: refine_keyframes(...).max_change,  # -> max |delta s|
              settings=AlternationSettings.from_config(config.global_ba, config.depth),
              broadcast=coordinator.broadcast_poses)
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from como3r.config import DepthRefinementConfig, GlobalBAConfig
from como3r.errors import ConfigError, SolverError
from como3r.heap import give_back_freed_memory
from como3r.progress import PhaseCallback, report_phase

logger = logging.getLogger(__name__)

__all__ = ["AlternationSettings", "AlternationRound", "AlternationReport", "alternate"]

DEPTH_CONVERGENCE_TOL = DepthRefinementConfig.depth_convergence_tol
"""Default ``max |ds|`` below which a depth step counts as converged (0.5 % in depth)."""


@dataclass(frozen=True)
class AlternationSettings:
    """Schedule of C-Sec. A.7 (defaults: C-Tab. 3).

    Attributes:
        cleanup_iters: iterations of each step-1 pose pass.
        cleanup_passes: maximum number of step-1 pose passes.
        translation_tol: a pose pass whose ``max ||dt||`` is below this fraction of the
            scene depth has converged (unitless, :mod:`como3r.geometry.units`).
        rounds: maximum number R of step-2 rounds (0: no depth step).
        round_pose_pass: each round of step 2 ends with a pose pass (C-Sec. A.7 step 2d);
            False (the default) keeps step 1's poses: one depth step (module docstring).
        pose_pass_iters: iterations of the pose pass of each round.
        depth_convergence_tol: a depth step whose ``max |ds|`` is below this has converged.
        stall_ratio: a depth step whose ``max |ds|`` exceeds this fraction of the previous
            round's has stalled (``inf`` never stalls).
    """

    cleanup_iters: int = 100
    cleanup_passes: int = 5
    translation_tol: float = 5e-3
    rounds: int = 100
    round_pose_pass: bool = False
    pose_pass_iters: int = 50
    depth_convergence_tol: float = DEPTH_CONVERGENCE_TOL
    stall_ratio: float = DepthRefinementConfig.depth_stall_ratio

    def __post_init__(self) -> None:
        for name in ("cleanup_iters", "cleanup_passes", "pose_pass_iters"):
            if getattr(self, name) < 1:
                raise ConfigError(
                    f"alternation: {name} must be at least 1, got {getattr(self, name)}"
                )
        if self.rounds < 0:
            raise ConfigError(f"alternation: rounds must be non-negative, got {self.rounds}")
        for name in ("translation_tol", "depth_convergence_tol", "stall_ratio"):
            if not getattr(self, name) >= 0:
                raise ConfigError(
                    f"alternation: {name} must be non-negative, got {getattr(self, name)}"
                )

    @classmethod
    def from_config(
        cls, global_ba: GlobalBAConfig, depth: DepthRefinementConfig
    ) -> AlternationSettings:
        """The schedule of a run's configuration."""
        return cls(
            cleanup_iters=global_ba.max_iters_cleanup,
            cleanup_passes=global_ba.cleanup_passes,
            translation_tol=global_ba.cleanup_stop_translation,
            rounds=depth.alternation_rounds,
            round_pose_pass=depth.round_poses == "pose_pass",
            pose_pass_iters=depth.pose_pass_iters,
            depth_convergence_tol=depth.depth_convergence_tol,
            stall_ratio=depth.depth_stall_ratio,
        )


@dataclass(frozen=True)
class AlternationRound:
    """One round of step 2.

    Attributes:
        max_depth_change: ``max |ds|`` of the depth step.
        max_translation: ``max ||dt||`` of the pose pass over the scene depth (0 without
            one).
    """

    max_depth_change: float
    max_translation: float


@dataclass
class AlternationReport:
    """What the alternation did and where the time went.

    Attributes:
        cleanup_translations: ``max ||dt||`` of every step-1 pose pass.
        rounds: every step-2 round.
        converged: the last round met both tolerances (step 2), or, with ``rounds = 0``,
            the last step-1 pass met the translation tolerance.
        reason: ``"converged"``, ``"stalled"``, ``"max_rounds"``, ``"poses_frozen"`` (one
            depth step at frozen poses) or, with ``rounds = 0``, ``"pose_converged"`` /
            ``"max_passes"``.
        pose_seconds: time in pose passes (both steps).
        depth_seconds: time in depth steps.
        broadcast_seconds: time in the broadcast callback.
        seconds: total wall-clock time.
    """

    cleanup_translations: list[float] = field(default_factory=list)
    rounds: list[AlternationRound] = field(default_factory=list)
    converged: bool = False
    reason: str = "max_rounds"
    pose_seconds: float = 0.0
    depth_seconds: float = 0.0
    broadcast_seconds: float = 0.0
    seconds: float = 0.0

    def to_json(self) -> dict[str, object]:
        """JSON-ready summary (``metrics.json``)."""
        return {
            "converged": self.converged,
            "reason": self.reason,
            "cleanup_passes": len(self.cleanup_translations),
            "cleanup_max_translation": list(self.cleanup_translations),
            "rounds": len(self.rounds),
            "round_max_depth_change": [r.max_depth_change for r in self.rounds],
            "round_max_translation": [r.max_translation for r in self.rounds],
            "pose_seconds": self.pose_seconds,
            "depth_seconds": self.depth_seconds,
            "broadcast_seconds": self.broadcast_seconds,
            "seconds": self.seconds,
        }


def _timed(fn: Callable[..., float], *args: int) -> tuple[float, float]:
    """``(fn(*args), seconds)``, with the result checked to be a finite number; what the
    step let go of is given back to the system (:mod:`como3r.heap`), so the next step's
    arrays do not come on top of it."""
    start = time.perf_counter()
    value = float(fn(*args))
    give_back_freed_memory()
    seconds = time.perf_counter() - start
    if not math.isfinite(value):
        raise SolverError(
            f"alternation: {getattr(fn, '__name__', 'callback')} returned "
            f"{value}, expected a finite step size"
        )
    return value, seconds


def _previous(label: str, values: list[float]) -> str:
    """The previous step's size for a progress line (empty before the first step)."""
    return f"previous {label} {values[-1]:.3g}" if values else ""


def alternate(
    pose_pass: Callable[[int], float] | None,
    depth_step: Callable[[], float],
    settings: AlternationSettings | None = None,
    broadcast: Callable[[], None] | None = None,
    progress: PhaseCallback | None = None,
) -> AlternationReport:
    """Run the cleanup schedule of C-Sec. A.7.

    Args:
        pose_pass: runs the global pose LM-IRLS (C-Eq. 5) for the given number of iterations
            with the depths frozen; returns the largest translation update ``max_i ||dt_i||``
            of the pass over the scene depth (unitless). None: poses frozen, depth steps
            only.
        depth_step: builds segments, refines the log-scales at frozen poses and writes the
            pointmaps back (C-Eq. 19-24); returns ``max |ds|``.
        settings: the schedule; default :class:`AlternationSettings`.
        broadcast: called after every round to push the new poses to the agents (step 2e).
        progress: called before every pose pass of step 1 (``"cleanup pass"``) and every
            round of step 2 (``"alternation round"``), with the previous one's step size.

    Returns:
        The report.

    Raises:
        SolverError: a callback returned a non-finite step size.
    """
    settings = AlternationSettings() if settings is None else settings
    report = AlternationReport()
    start = time.perf_counter()

    for k in range(settings.cleanup_passes if pose_pass is not None else 0):
        report_phase(
            progress,
            "cleanup pass",
            _previous("max ||dt||/depth", report.cleanup_translations),
            k,
            settings.cleanup_passes,
        )
        translation, seconds = _timed(pose_pass, settings.cleanup_iters)
        report.pose_seconds += seconds
        report.cleanup_translations.append(translation)
        if translation < settings.translation_tol:
            break
    if settings.rounds == 0:
        report.converged = (
            not report.cleanup_translations
            or report.cleanup_translations[-1] < settings.translation_tol
        )
        report.reason = "pose_converged" if report.converged else "max_passes"

    alternating = pose_pass is not None and settings.round_pose_pass
    rounds = settings.rounds if alternating else min(settings.rounds, 1)
    for r in range(rounds):
        report_phase(
            progress,
            "alternation round",
            _previous("max |ds|", [step.max_depth_change for step in report.rounds]),
            r,
            rounds,
        )
        depth_change, seconds = _timed(depth_step)
        report.depth_seconds += seconds
        translation = 0.0
        if alternating:
            translation, seconds = _timed(pose_pass, settings.pose_pass_iters)
            report.pose_seconds += seconds
        if broadcast is not None:
            broadcast_start = time.perf_counter()
            broadcast()
            report.broadcast_seconds += time.perf_counter() - broadcast_start
        report.rounds.append(AlternationRound(depth_change, translation))
        logger.debug(
            "alternation round %d: max |ds| = %.3g, max ||dt|| = %.3g depth",
            r + 1,
            depth_change,
            translation,
        )
        if depth_change < settings.depth_convergence_tol and translation < settings.translation_tol:
            report.converged, report.reason = True, "converged"
            break
        if not alternating:
            report.reason = "poses_frozen"  # a next round would repeat this depth solve
            break
        if r > 0 and depth_change > settings.stall_ratio * report.rounds[-2].max_depth_change:
            report.reason = "stalled"
            break
    report.seconds = time.perf_counter() - start
    logger.info(
        "alternation: %d cleanup passes, %d rounds (%s), pose %.2fs, depth %.2fs",
        len(report.cleanup_translations),
        len(report.rounds),
        report.reason,
        report.pose_seconds,
        report.depth_seconds,
    )
    return report
