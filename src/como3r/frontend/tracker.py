"""Frame-to-keyframe tracking with the ray-and-range residual (C-Eq. 2, C-Sec. 3.3).

For an incoming frame f and the current keyframe k the prior decodes (f, k): the frame's
pointmap ``X_ff`` and the keyframe's pixels predicted in the frame ``X_kf``. Projective
matching finds, for every keyframe pixel m, the frame pixel n whose ray is closest to
``X_kf[m]`` (C-Eq. 1). The relative pose ``T_kf`` then minimises C-Eq. 2 over the matches,
with the keyframe's fused canonical pointmap ``X_hat`` as the target, by Levenberg-Marquardt
inside IRLS (C-Sec. B.2, the tracker path). The keyframe's pointmap absorbs the frame's
prediction (C-Eq. 3), and a new keyframe is due when ``min(nu, nu_uniq) < 0.333``.

Failure is detected, never silent: too few valid matches, non-finite values, or a solve
that could not produce a finite pose give ``ok=False`` with the reason.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from como3r.config import Config, TrackingConfig
from como3r.frontend.graph import make_factors
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.pairs import DirectedMatches, directed_matches, gather_points
from como3r.frontend.timing import StageTimer
from como3r.geometry.camera import lock_to_rays
from como3r.geometry.lie import sim3_act, sim3_identity
from como3r.geometry.units import median_range
from como3r.optim.optimizer import SolveReport, levenberg_marquardt_irls
from como3r.optim.values import PoseValues
from como3r.prior.base import Encoding, Prior

logger = logging.getLogger(__name__)

#: the keyframe pixels (every n-th row and column) whose median range scales the tracker's
#: step tolerance
_RANGE_STRIDE = 4

#: solver exits that mean no usable pose was found
_FAILED_REASONS = frozenset({"solve_failed", "non_finite_cost", "diverged"})


@dataclass(frozen=True)
class TrackResult:
    """Outcome of tracking one frame against one keyframe.

    Attributes:
        ok: a finite pose was estimated from enough matches.
        reason: ``"ok"`` or why tracking failed.
        T_kf: ``(8,)`` pose of the frame in the keyframe's camera.
        match_fraction: ``nu``, share of keyframe pixels with a valid match.
        unique_fraction: ``nu_uniq``, distinct frame pixels matched per keyframe pixel.
        new_keyframe: ``min(nu, nu_uniq)`` fell below the keyframe threshold.
        X_ff: ``(H, W, 3)`` the frame's own pointmap (its canonical map if it becomes a
            keyframe), on the keyframe's calibrated rays when it has intrinsics.
        C_ff: ``(H, W)`` confidence of ``X_ff``.
        solve: the solver's report (None when no solve ran).
        matches: every keyframe pixel looked up in the frame: if the frame becomes a
            keyframe, the matches of its sequential edge (frame, keyframe).
    """

    ok: bool
    reason: str
    T_kf: Tensor
    match_fraction: float
    unique_fraction: float
    new_keyframe: bool
    X_ff: Tensor
    C_ff: Tensor
    solve: SolveReport | None = None
    matches: DirectedMatches | None = None


class FrameTracker:
    """Tracks frames of one agent against its keyframes, warm-starting the matching.

    Args:
        prior: the two-view prior.
        config: the run's configuration.
        timer: charged with the stages ``matching``, ``tracking`` and ``fusion``.
        upsampling: network pixels per pixel of the agent's input (> 1 when the input was
            enlarged to ``input.long_side``): the pose-agreement angle
            ``tracking.inlier_angle_deg`` is given at the input's own resolution and grows
            with it, as an enlarged image cannot place a match finer than its own pixels.
    """

    def __init__(
        self, prior: Prior, config: Config, timer: StageTimer | None = None, upsampling: float = 1.0
    ) -> None:
        self.prior = prior
        self.config = config
        self.timer = StageTimer() if timer is None else timer
        self.inlier_angle_deg = config.tracking.inlier_angle_deg * max(1.0, upsampling)
        self._warm: tuple[int, Tensor] | None = None  # (keyframe id, (1, P, 2) pixels)

    def track(
        self, enc_f: Encoding, keyframe: Keyframe, T_kf_init: Tensor, fuse: bool = True
    ) -> TrackResult:
        """Estimate ``T_kf`` of a frame and (if ``fuse``) fuse it into the keyframe.

        Args:
            enc_f: the frame's encoding.
            keyframe: the keyframe to track against.
            T_kf_init: ``(8,)`` initial guess (the previous frame's relative pose).
            fuse: update the keyframe's canonical pointmap on success (C-Eq. 3).
        """
        pred = self.prior.decode(enc_f, keyframe.encoding)
        # matching pairs X_ji with X_ii as predicted together (the same believed camera i);
        # only the pose solve and the fusion see the frame's points on the calibrated rays
        with self.timer.stage("matching"):
            matches = directed_matches(
                pred, self.config.matching, self.config.tracking.q_min, self._warm_start(keyframe)
            )
            self._remember(keyframe, matches, pred.X_ii.shape[1])
            nu = matches.match_fraction
            nu_unique = _unique_fraction(matches, pred.X_ii.shape[0] * pred.X_ii.shape[1])
        if keyframe.K is not None:  # the frame's own pointmap on the calibrated rays (C-Eq. 16)
            pred = replace(pred, X_ii=lock_to_rays(pred.X_ii, keyframe.K))
        tracking = self.config.tracking
        base = dict(
            match_fraction=nu,
            unique_fraction=nu_unique,
            X_ff=pred.X_ii,
            C_ff=pred.C_ii,
            matches=matches,
        )
        if nu < tracking.min_match_fraction:
            logger.info(
                "tracking failed against keyframe %d: %.2f of the pixels matched (minimum %.2f)",
                keyframe.kf_id,
                nu,
                tracking.min_match_fraction,
            )
            return TrackResult(False, "too_few_matches", T_kf_init, new_keyframe=True, **base)
        with self.timer.stage("tracking"):
            T_kf, report = self.solve(pred.X_ii, keyframe, matches, T_kf_init)
        if not solved(T_kf, report):
            logger.info("tracking failed against keyframe %d: %s", keyframe.kf_id, report.reason)
            return TrackResult(
                False, report.reason, T_kf_init, new_keyframe=True, solve=report, **base
            )
        inliers = inlier_fraction(
            T_kf, pred.X_ii, keyframe.X_hat, matches, tracking, self.inlier_angle_deg
        )
        if inliers < tracking.min_inlier_fraction:
            logger.info(
                "tracking against keyframe %d rejected: %.2f of the matches agree with the pose",
                keyframe.kf_id,
                inliers,
            )
            return TrackResult(
                False, "inconsistent", T_kf_init, new_keyframe=True, solve=report, **base
            )
        if fuse:
            with self.timer.stage("fusion"):
                keyframe.fuse(
                    T_kf, pred.X_ji, pred.C_ji, ranges_only=self.config.tracking.fusion == "ranges"
                )
        new_kf = min(nu, nu_unique) < tracking.keyframe_match_fraction
        return TrackResult(True, "ok", T_kf, new_keyframe=new_kf, solve=report, **base)

    def reset_warm_start(self) -> None:
        """Forget the previous matches (after relocalization)."""
        self._warm = None

    def solve(
        self, X_ff: Tensor, keyframe: Keyframe, matches: DirectedMatches, T_kf_init: Tensor
    ) -> tuple[Tensor, SolveReport]:
        """LM-IRLS on C-Eq. 2 (C-Eq. 17 when calibrated), keyframe pinned at the identity.

        The frame's matched points ``X_ff[n]`` move onto the keyframe's canonical points
        ``X_hat[m]`` (every keyframe pixel m is a match, validity aside).
        """
        K = None if keyframe.K is None else keyframe.K[None].to(X_ff)
        factors = make_factors(
            torch.tensor([0]),
            torch.tensor([1]),
            keyframe.X_hat.reshape(1, -1, 3),
            gather_points(X_ff, matches.idx)[None],
            matches.q[None],
            matches.valid[None],
            self.config.tracking,
            K,
        )
        identity = sim3_identity(dtype=T_kf_init.dtype, device=T_kf_init.device)
        values = PoseValues(
            torch.stack([identity, T_kf_init]), torch.tensor([True, False], device=T_kf_init.device)
        )
        # tracking.step_tol is a fraction of the scene depth (geometry.units): the keyframe's
        # median range, read off every 4th pixel (1.7 ms at 512x384 instead of 5)
        depth = float(median_range(keyframe.X_hat[::_RANGE_STRIDE, ::_RANGE_STRIDE]))
        solved, report = levenberg_marquardt_irls(
            factors, values, self.config.tracking, backend="dense", length_scale=depth
        )
        return solved.poses[1], report

    def _warm_start(self, keyframe: Keyframe) -> Tensor | None:
        if self._warm is not None and self._warm[0] == keyframe.kf_id:
            return self._warm[1]
        return None

    def _remember(self, keyframe: Keyframe, matches: DirectedMatches, width: int) -> None:
        pixels = torch.stack([matches.idx % width, matches.idx // width], dim=-1)
        self._warm = (keyframe.kf_id, pixels[None].to(keyframe.X_hat.dtype))


def solved(T_kf: Tensor, report: SolveReport) -> bool:
    """Whether a tracking solve gave a usable pose ``T_kf`` ``(8,)``."""
    return report.reason not in _FAILED_REASONS and bool(torch.isfinite(T_kf).all())


def _unique_fraction(matches: DirectedMatches, searched_pixels: int) -> float:
    """Distinct matched pixels of the searched view per query pixel (``nu_uniq``).

    Args:
        matches: the matches, indices into the searched view's ``searched_pixels`` pixels.
        searched_pixels: pixel count of the searched view.
    """
    if matches.idx.numel() == 0:
        return 0.0
    hit = torch.zeros(searched_pixels, dtype=torch.bool, device=matches.idx.device)
    hit[matches.idx[matches.valid]] = True  # a mark per distinct pixel, no sort
    return float(hit.sum() / matches.idx.numel())


def inlier_fraction(
    T_kf: Tensor,
    X_ff: Tensor,
    X_hat: Tensor,
    matches: DirectedMatches,
    tracking: TrackingConfig,
    angle_deg: float,
) -> float:
    """Share of the valid matches that agree with a solved frame pose.

    A match agrees when the frame's point moved by ``T_kf`` lies within ``angle_deg`` of the
    keyframe point's ray and its range within ``tracking.sigma_dist`` (relative) of the
    keyframe point's range.

    Args:
        T_kf: ``(8,)`` frame pose in the keyframe's camera.
        X_ff: ``(H, W, 3)`` the frame's pointmap; X_hat: ``(H, W, 3)`` the keyframe's.
        matches: keyframe pixels looked up in the frame.
        tracking: the range threshold.
        angle_deg: the ray threshold (:attr:`FrameTracker.inlier_angle_deg`).
    """
    if not bool(matches.valid.any()):
        return 0.0
    X_f = sim3_act(T_kf.to(X_ff.dtype)[None], gather_points(X_ff, matches.idx)[matches.valid])
    X_k = X_hat.reshape(-1, 3)[matches.valid]
    cosine = (F.normalize(X_f, dim=-1) * F.normalize(X_k, dim=-1)).sum(-1)
    close_ray = cosine > math.cos(math.radians(angle_deg))
    range_k = X_k.norm(dim=-1)
    close_range = (X_f.norm(dim=-1) - range_k).abs() < tracking.sigma_dist * range_k
    return float((close_ray & close_range).float().mean())
