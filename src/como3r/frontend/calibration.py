"""Self-calibration of an uncalibrated agent: one pinhole camera per agent, first from the
prior's own pointmap of its first frame, then from the multi-view geometry of its first
keyframes (``tracking.self_calibration``, a deviation from the paper's uncalibrated mode).

The paper's uncalibrated mode (C-Eq. 2) takes every canonical pointmap's rays as they come.
A learned prior gets the field of view of every image a little wrong, and differently for
neighbouring images (MUSt3R: 4 deg mean field-of-view error on TUM RGB-D); tracking a frame
whose pointmap believes in one focal length against a keyframe that believes in another
biases the Sim(3) alignment, the forward translation and the scale most. One camera per
agent removes that: every keyframe and frame is locked to the same rays (C-Eq. 16) and
tracked with the calibrated residual (C-Eq. 17), as if ``calib.txt`` had been given with
the estimated focal length.

The focal length is DUSt3R's robust estimate (:func:`como3r.geometry.camera.estimate_focal`)
on the first frame's own prediction, principal point at the image centre (as DUSt3R and
MASt3R-SLAM assume). Measured on the realistic simulated prior (one agent, 40 frames
at 160 px turning 3.6 deg per frame, two scenes x three prior seeds, ATE % of path): the
paper's mode 3.8-8.2 % (mean 5.1), this fixed estimate 0.39-1.35 % (mean 0.91), a running
median over the keyframes 0.44-3.76 % (mean 1.9), the true calibration 0.49 / 0.52 %
(prior seed 0).

One image's belief is one draw of the prior's field-of-view error (8 % RMS in the
realistic simulated prior, as large as MUSt3R's 4 deg): an agent starting on a 14 % draw
tracked at 1.9 % of its path where the true camera gave 0.5 %. Once the agent has
``tracking.self_calibration_keyframes`` keyframes, :func:`refine_focal` re-estimates the
one camera from all their verified pairs (:mod:`como3r.frontend.focal`: the focal length
under which each pair's two pointmaps align best through one Sim(3)), every keyframe moves
to it, and only then do the keyframes leave the agent: the camera stays fixed from there
on, since a camera that changes under a running map makes keyframes disagree again.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from como3r.config import TrackingConfig
from como3r.errors import GeometryError
from como3r.frontend.focal import FocalEstimate, FocalPair, estimate_log_focal, relative_pose
from como3r.frontend.graph import Edge
from como3r.frontend.keyframes import Keyframe
from como3r.geometry.camera import estimate_focal, intrinsics_matrix


def estimate_intrinsics(X: Tensor, C: Tensor) -> Tensor:
    """The camera a prediction implies: robust focal length, principal point at the centre.

    Args:
        X: ``(H, W, 3)`` a view's own pointmap, on the rays the prior believes in.
        C: ``(H, W)`` its confidence (the estimate's weights).

    Returns:
        ``(3, 3)`` intrinsics at the pointmap's resolution, ``X``'s dtype and device.

    Raises:
        GeometryError: no point of the prediction lies in front of the camera.
    """
    focal = float(estimate_focal(X, C))
    if not focal > 0:
        raise GeometryError(
            "self-calibration: the prediction has no point in front of the "
            "camera to estimate the focal length from"
        )
    H, W = X.shape[:2]
    return intrinsics_matrix(
        focal, focal, (W - 1) / 2.0, (H - 1) / 2.0, dtype=X.dtype, device=X.device
    )


def keyframe_pairs(keyframes: Sequence[Keyframe], edges: Sequence[Edge]) -> list[FocalPair]:
    """An agent's verified keyframe pairs (both directions matched) as one-camera pairs.

    Args:
        keyframes: the agent's keyframes by id, with intrinsics.
        edges: its directed edges; ``Edge(i, j).matches`` looks every pixel of j up in i.
    """
    directed = {(e.i, e.j): e.matches for e in edges}
    return [
        FocalPair(
            keyframes[i].X_hat,
            keyframes[j].X_hat,
            keyframes[i].K,
            keyframes[j].K,
            relative_pose(keyframes[i].T_WC, keyframes[j].T_WC),
            ij,
            directed[(j, i)],
            shared=True,
        )
        for (i, j), ij in directed.items()
        if i < j and (j, i) in directed
    ]


def refine_focal(
    keyframes: Sequence[Keyframe], edges: Sequence[Edge], tracking: TrackingConfig, search: float
) -> FocalEstimate | None:
    """The log correction of an agent's one focal length that best aligns its keyframe pairs
    (:func:`~como3r.frontend.focal.estimate_log_focal`, searched within ``search``); None
    without a pair to observe it."""
    pairs = keyframe_pairs(keyframes, edges)
    if not pairs:
        return None
    return estimate_log_focal(pairs, tracking, search=search)
