"""Where a learned matcher would place view j in camera i: key-cell matches and a robust
similarity fit between the true depth points of two views (manual: docs/api/index.md).

Part of the simulated prior (:mod:`como3r.prior.simulated`): truly overlapping views with
unique textures get the true relative pose, aliased views the wrong one, views without
enough common keys none (``None``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from como3r.errors import GeometryError
from como3r.geometry.lie import matrix_to_quat, quat_to_matrix, sim3_act, so3_exp
from como3r.geometry.umeyama import umeyama_sim3, umeyama_sim3_batched
from como3r.prior.simulated_encoding import SimulatedConstants, SimulatedEncoding, normalize
from como3r.prior.simulated_keys import (
    KeyMatches,
    key_jacobians,
    match_key_cells,
    reproducible_matmul,
)


def match_keys(
    enc_i: SimulatedEncoding, enc_j: SimulatedEncoding, c: SimulatedConstants, gen: torch.Generator
) -> KeyMatches:
    """Key-cell matches of the pair; the cell is ``cell_per_footprint`` times the coarser
    of the two median footprints, so both views sample almost every cell they share."""
    cell = c.cell_per_footprint * max(enc_i.median_footprint, enc_j.median_footprint, 1e-6)
    return match_key_cells(
        enc_i.key_ids, enc_i.key_coords, enc_j.key_ids, enc_j.key_coords, cell, gen
    )


def robust_fit(
    enc_i: SimulatedEncoding,
    enc_j: SimulatedEncoding,
    matches: KeyMatches,
    c: SimulatedConstants,
    gen: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor] | None:
    """RANSAC similarity ``x_i = s R x_j + t`` from the key matches, None if unsupported.

    Hypotheses are minimal 3-point similarities scored by their inliers (distance below
    ``ransac_inlier_cells`` key cells). The best is refined by :func:`umeyama_sim3` on its
    inliers under shrinking thresholds (``refine_inlier_cells``): matches on planar
    surfaces are exact (:func:`_point_at_key`), while matches across curved or
    self-similar surfaces of an object are off by up to a cell and must not bias the fit.
    The fit is accepted when the final pose explains enough matches within
    ``ransac_inlier_cells`` cells.
    """
    needed = max(c.min_inliers, c.min_overlap_fraction * enc_j.valid.numel())
    total = matches.pixels_j.numel()
    if total < needed:
        return None
    keep = torch.randperm(total, generator=gen)[: c.ransac_max_correspondences]
    keep = keep.to(matches.pixels_j.device)
    pixels_i, pixels_j = matches.pixels_i[keep], matches.pixels_j[keep]
    src = true_points(enc_j).reshape(-1, 3)[pixels_j].double()
    dst = _point_at_key(enc_i, pixels_i, enc_j.key_coords.reshape(-1, 3)[pixels_j], c.newton_steps)
    # Hypotheses are scored on a subset; the refinement below uses every correspondence.
    scored = slice(0, c.ransac_scored_correspondences)
    samples = torch.randint(0, src.shape[0], (c.ransac_hypotheses, 3), generator=gen)
    R, t, s = (x.to(torch.float32) for x in umeyama_sim3_batched(src[samples], dst[samples]))
    # s R x + t of every scored point under every hypothesis, (n, B, 3), reproducibly: a
    # one-ulp change flips an inlier at the threshold and with it the chosen hypothesis
    rotated = reproducible_matmul(src[scored, None, :].float(), R.transpose(1, 2))
    residual_sq = (s[None, :, None] * rotated + t[None] - dst[scored, None].float()).square()
    threshold = c.ransac_inlier_cells * matches.cell
    support = (residual_sq.sum(-1) < threshold**2).sum(0)
    best = int(support.argmax())
    T = torch.cat([t[best], matrix_to_quat(R[best]), s[best, None]]).double()
    inliers = (sim3_act(T, src) - dst).norm(dim=-1) < threshold
    for fraction in c.refine_inlier_cells:
        refined = _refit(src, dst, inliers, fraction * matches.cell, c.min_inliers)
        if refined is None:
            break
        T, inliers = refined
    supported = (sim3_act(T, src) - dst).norm(dim=-1) < threshold
    if float(supported.float().mean()) * total < needed:
        return None
    T = T.to(torch.float32)
    return quat_to_matrix(T[3:7]), T[:3], T[7]


def _point_at_key(
    enc: SimulatedEncoding, pixels: Tensor, keys: Tensor, newton_steps: int
) -> Tensor:
    """``(M, 3)`` float64 points of ``enc`` at exactly ``keys`` ``(M, 3)``, starting from
    pixels of the same key cell.

    A learned matcher localises correspondences to sub-pixel accuracy; a pixel of the
    same cell is off by up to a cell, with a bias that depends on the perspective
    sampling of the two views. Newton steps in the image (``d (u, v) / d key``) move to
    the pixel of the nearest key, whose point is then corrected to first order
    (``d point / d key``, :func:`~como3r.prior.simulated_keys.key_jacobians`); on
    planar surfaces the result is exact.
    """
    H, W = enc.shape
    ids, coords = enc.key_ids.reshape(-1), enc.key_coords.reshape(-1, 3)
    points = true_points(enc)
    key_to_pixel, jacobian = key_jacobians(enc.key_ids, enc.key_coords, points, pixels)
    for _ in range(newton_steps):
        offset = (keys - coords[pixels])[:, :, None]
        step = torch.round((key_to_pixel @ offset)[..., 0]).long()
        u = (pixels % W + step[:, 0]).clamp(0, W - 1)
        v = (pixels // W + step[:, 1]).clamp(0, H - 1)
        candidate = v * W + u
        candidate_to_pixel, candidate_jacobian = key_jacobians(
            enc.key_ids, enc.key_coords, points, candidate
        )
        better = (ids[candidate] == ids[pixels]) & (candidate_to_pixel.abs().sum((1, 2)) > 0)
        pixels = torch.where(better, candidate, pixels)
        key_to_pixel = torch.where(better[:, None, None], candidate_to_pixel, key_to_pixel)
        jacobian = torch.where(better[:, None, None], candidate_jacobian, jacobian)
    offset = (keys - coords[pixels]).double()
    return points.reshape(-1, 3)[pixels].double() + (jacobian.double() @ offset[:, :, None])[..., 0]


def _refit(
    src: Tensor, dst: Tensor, inliers: Tensor, threshold: float, min_inliers: int
) -> tuple[Tensor, Tensor] | None:
    """Umeyama fit on ``inliers`` and its inliers within ``threshold``; None if the fit
    is degenerate or keeps too few inliers (then the previous fit stands)."""
    if int(inliers.sum()) < min_inliers:
        return None
    try:
        T = umeyama_sim3(src[inliers], dst[inliers])
    except GeometryError:
        return None
    refined = (sim3_act(T, src) - dst).norm(dim=-1) < threshold
    if int(refined.sum()) < min_inliers:
        return None
    return T, refined


def true_points(enc: SimulatedEncoding) -> Tensor:
    """``(H, W, 3)`` true camera-frame points (0 where invalid)."""
    return enc.rays * enc.ranges[..., None]


def random_pose(
    enc_i: SimulatedEncoding, c: SimulatedConstants, gen: torch.Generator
) -> tuple[Tensor, Tensor, Tensor]:
    """A plausible wrong pose for views without common keys: near camera i, turned."""
    axis = normalize(torch.randn(3, generator=gen))
    angle = math.radians(c.random_pose_max_angle_deg) * float(torch.rand((), generator=gen))
    direction = normalize(torch.randn(3, generator=gen))
    low, high = c.random_pose_distance
    distance = enc_i.median_range * (low + (high - low) * float(torch.rand((), generator=gen)))
    device = enc_i.rays.device
    R = quat_to_matrix(so3_exp(axis * angle)).to(device)
    return R, (direction * distance).to(device), torch.ones((), device=device)
