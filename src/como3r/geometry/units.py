"""Scene units: lengths relative to the scene's depth, pixels relative to the image size.

A threshold in metres is right for one kind of scene only: 0.1 m is a generous occlusion
gap on a tabletop and a fraction of the depth noise of a street. como3r's configuration
therefore states lengths as fractions of a reference depth (the median valid range of the
keyframe or view they act on) and pixel quantities at the paper's input size (long side
512, C-Tab. 3), converted here at the size a run actually uses.

Where a paper value was given in metres for its scenes, the configuration keeps its meaning
at :data:`PAPER_REFERENCE_DEPTH_M`: MASt3R-SLAM's and CoMo3R-SLAM's indoor sequences (TUM
RGB-D, 7-Scenes, Tanks and Temples at MASt3R's metric scale) have median depths of about
1-3 m, so a paper length ``L`` metres becomes the ratio ``L / 1 m``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

#: Reference depth (metres) at which the paper's metric values keep their meaning.
PAPER_REFERENCE_DEPTH_M = 1.0

#: Input long side (pixels) of the paper's pixel quantities (C-Tab. 3, "Front-end input").
PAPER_LONG_SIDE = 512


def median_point_range(points: Tensor, valid: Tensor | None = None) -> Tensor:
    """Median distance to the camera centre of finite, non-zero points.

    Args:
        points: ``(..., N, 3)`` points in a camera frame.
        valid: optional ``(..., N)`` bool mask of usable points.

    Returns:
        ``(...)`` median range per set, in the points' unit; 1 for a set without any usable
        point (so a ratio times it stays finite).
    """
    return median_of_ranges(torch.linalg.vector_norm(points, dim=-1), valid)


def median_of_ranges(ranges: Tensor, valid: Tensor | None = None) -> Tensor:
    """Median of the finite, positive ``ranges`` ``(..., N)`` (where ``valid``, ``(..., N)``)
    -> ``(...)``; 1 for a set without any, so a ratio times it stays finite."""
    usable = torch.isfinite(ranges) & (ranges > 0)
    if valid is not None:
        usable = usable & valid
    masked = torch.where(usable, ranges, torch.full_like(ranges, float("nan")))
    median = torch.nanmedian(masked, dim=-1).values
    return torch.where(torch.isfinite(median), median, torch.ones_like(median))


def median_range(X: Tensor, valid: Tensor | None = None) -> Tensor:
    """:func:`median_point_range` of pointmaps ``X`` ``(..., H, W, 3)`` (mask
    ``(..., H, W)``) -> ``(...)``."""
    flat_valid = None if valid is None else valid.flatten(-2)
    return median_point_range(X.flatten(-3, -2), flat_valid)


def pixels_at(value_at_paper_size: float, long_side: int, minimum: int = 1) -> int:
    """A pixel count given at the paper's long side (512), scaled to ``long_side``.

    Args:
        value_at_paper_size: the quantity in pixels of a 512-pixel-long image.
        long_side: the long side of the images the run processes.
        minimum: smallest value returned (a window of 0 pixels would switch a search off).
    """
    return max(minimum, round(value_at_paper_size * long_side / PAPER_LONG_SIDE))


def scene_depth(T_WC: Sequence[Tensor], X: Sequence[Tensor]) -> float:
    """The scene's length in world units: the median over keyframes of their pointmap's
    median range times their pose's scale.

    Args:
        T_WC: per keyframe its ``(8,)`` Sim(3) pose (scale ``s`` last).
        X: per keyframe its ``(H, W, 3)`` canonical pointmap in its camera frame.

    Returns:
        The median, or 1 without keyframes (so a ratio times it stays finite).
    """
    return median_depth([float(T[7]) for T in T_WC], [float(median_range(p)) for p in X])


def median_depth(scales: Sequence[float], ranges: Sequence[float]) -> float:
    """:func:`scene_depth` from each keyframe's pose scale and its pointmap's median range
    (for a caller that keeps the ranges): the median of their products, 1 without any."""
    depths = [scale * range_ for scale, range_ in zip(scales, ranges)]
    return float(torch.tensor(depths).median()) if depths else 1.0
