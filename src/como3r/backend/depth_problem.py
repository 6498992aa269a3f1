"""The depth refinement's problem, flattened (C-Sec. A.6; C-Eq. 19-23): every keyframe's
pixels as rows (their ranges, rays and log-scales), every edge's matches that enter the data
term of C-Eq. 21 (valid, ``q > 0``, both pixels usable, one free) with what the residual
needs per match, and the boundary pairs of C-Eq. 22.

:func:`build_problem` makes the :class:`Problem` the Newton iterations of
:mod:`como3r.backend.depth_refinement` read (any device); on CPU the compiled data term reads
the matches as :class:`~como3r.backend.cpu_kernels.MatchStreams`, which
:func:`match_streams` lays out from a problem and :func:`chunk_streams` writes directly (the
working sets of :mod:`como3r.backend.paged_refinement`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from como3r.backend import cpu_kernels
from como3r.backend.segments import MIN_RANGE
from como3r.config import DepthRefinementConfig
from como3r.errors import InputError
from como3r.frontend.graph import Edge
from como3r.geometry.lie import quat_to_matrix, sim3_compose, sim3_inverse
from como3r.geometry.residuals import psi
from como3r.geometry.units import median_range

__all__ = [
    "RefinableKeyframe",
    "Problem",
    "build_problem",
    "chunk_streams",
    "match_streams",
    "mean_log_ratio",
]


class RefinableKeyframe(Protocol):
    """What the refinement needs of a keyframe (:class:`~como3r.frontend.keyframes.Keyframe`).

    Attributes:
        X_hat: ``(H, W, 3)`` current canonical pointmap in the keyframe's camera frame.
        X_init: ``(H, W, 3)`` frozen snapshot of C-Eq. 19.
    """

    X_hat: Tensor
    X_init: Tensor


@dataclass
class Problem:
    """The refinement problem on flat pixel arrays over all keyframes.

    ``P`` pixels (every keyframe's ``H W`` pixels, concatenated), ``M`` free log-scales,
    ``K`` matches, ``B`` boundary pairs.
    """

    depth0: Tensor  # (P,) range the log-scale multiplies: ||X_init|| (free) or ||X_hat|| (pinned)
    rays: Tensor  # (P, 3) unit rays psi(X_init) (free) or psi(X_hat) (pinned)
    param: Tensor  # (P,) int64 free log-scale of the pixel, -1 for none (pinned or invalid)
    match_a: Tensor  # (K,) pixel m of keyframe i (frame of the residual)
    match_b: Tensor  # (K,) pixel n of keyframe j
    rays_b_in_a: Tensor  # (K, 3) s_ij R_ij psi_j,n: ray of j's pixel rotated into frame i
    t_ab: Tensor  # (K, 3) translation of T_ij
    sqrt_w: Tensor  # (K,) sqrt(q_mn) / (sigma_point d_i) (C-Eq. 21 whitening)
    bnd_a: Tensor  # (B,) log-scale a of each unique adjacent pair, a < b
    bnd_b: Tensor  # (B,)
    delta: Tensor  # (B,) Delta_ab of C-Eq. 22
    s_start: Tensor  # (M,) warm start


def mean_log_ratio(X_hat: Tensor, d_init: Tensor, labels: Tensor, count: int) -> Tensor:
    """``(count,)`` mean over each label's pixels of ``log(||X_hat|| / d_init)`` (0 if none)."""
    d_hat = X_hat.reshape(-1, 3).norm(dim=-1)
    flat = labels.reshape(-1)
    ok = (flat >= 0) & torch.isfinite(d_hat) & (d_hat > MIN_RANGE) & (d_init > MIN_RANGE)
    ratio = torch.log(d_hat[ok] / d_init[ok])
    sums = torch.zeros(count, dtype=ratio.dtype, device=ratio.device).index_add_(0, flat[ok], ratio)
    counts = torch.zeros(count, dtype=ratio.dtype, device=ratio.device).index_add_(
        0, flat[ok], torch.ones_like(ratio)
    )
    return sums / counts.clamp_min(1.0)


def _adjacent_pairs(labels: Tensor, log_depth: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """4-adjacent pixel pairs with different valid labels.

    Returns:
        ``(label_p, label_q, log d_p - log d_q)`` over all such pairs, each ``(B_pix,)``.
    """
    log_depth = log_depth.reshape(labels.shape)
    pairs = []
    for lp, lq, dp, dq in (
        (labels[:, :-1], labels[:, 1:], log_depth[:, :-1], log_depth[:, 1:]),
        (labels[:-1, :], labels[1:, :], log_depth[:-1, :], log_depth[1:, :]),
    ):
        cut = (lp >= 0) & (lq >= 0) & (lp != lq)
        pairs.append((lp[cut], lq[cut], dp[cut] - dq[cut]))
    return tuple(torch.cat(parts) for parts in zip(*pairs))


def _boundary_terms(
    label_p: Tensor, label_q: Tensor, diff: Tensor, num_params: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Unique unordered pairs ``(a, b)``, ``a < b``, with ``Delta_ab`` averaged over the
    shared boundary pixels (C-Eq. 22)."""
    swap = label_p > label_q
    a = torch.where(swap, label_q, label_p)
    b = torch.where(swap, label_p, label_q)
    diff = torch.where(swap, -diff, diff)
    keys, inverse = torch.unique(a * num_params + b, return_inverse=True)
    sums = torch.zeros(keys.numel(), dtype=diff.dtype, device=diff.device).index_add_(
        0, inverse, diff
    )
    counts = torch.zeros_like(sums).index_add_(0, inverse, torch.ones_like(diff))
    return keys // num_params, keys % num_params, sums / counts


@dataclass
class _Pixels:
    """Every keyframe's pixels, flat and concatenated (``P`` in all), as the problem's rows.

    Attributes:
        depth0: ``(P,)`` the range a log-scale multiplies: ``||X_init||`` (free) or
            ``||X_hat||`` (pinned), 0 where not finite.
        rays: ``(P, 3)`` unit rays ``psi`` of the same points.
        param: ``(P,)`` int64 a pixel's log-scale, -1 for none (invalid), -2 valid and fixed.
        pixel_offsets, param_offsets: each keyframe's first pixel and first log-scale.
        s_start: per free keyframe its warm start ``(M_k,)`` (empty with ``data_only``).
        boundary: per free keyframe its adjacent label pairs and log-depth differences
            (empty with ``data_only`` or the "pixel" variant).
    """

    depth0: Tensor
    rays: Tensor
    param: Tensor
    pixel_offsets: list[int]
    param_offsets: list[int]
    s_start: list[Tensor]
    boundary: list[tuple[Tensor, Tensor, Tensor]]


def _pixels(
    keyframes: Sequence[RefinableKeyframe],
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
    pinned: set[int],
    data_only: bool,
) -> _Pixels:
    """The keyframes' pixels as :class:`_Pixels` (``data_only``: without warm start and
    boundary pairs)."""
    dtype, device = keyframes[0].X_init.dtype, keyframes[0].X_init.device
    depth0, rays, param, s_start = [], [], [], []
    bnd = []
    pixel_offsets, param_offsets = [], []
    num_pixels = num_params = 0
    for k, (kf, lab) in enumerate(zip(keyframes, labels)):
        lab = lab.to(device=device, dtype=torch.int64).reshape(-1)
        count = int(lab.max()) + 1 if lab.numel() else 0
        X_base = (kf.X_hat if k in pinned else kf.X_init).to(dtype).reshape(-1, 3)
        d = torch.nan_to_num(X_base, nan=0.0, posinf=0.0, neginf=0.0).norm(dim=-1)
        lab = torch.where(torch.isfinite(X_base).all(-1) & (d > MIN_RANGE), lab, -1)
        pixel_offsets.append(num_pixels)
        param_offsets.append(num_params)
        depth0.append(d)
        rays.append(psi(torch.nan_to_num(X_base)))
        if k in pinned:
            # Constant points: usable (label >= 0) but no unknown; -2 marks "valid, fixed".
            param.append(torch.where(lab >= 0, -2, -1))
        else:
            param.append(torch.where(lab >= 0, lab + num_params, -1))
            if not data_only:
                s_start.append(mean_log_ratio(kf.X_hat.to(dtype), d, lab.reshape(-1), count))
            if config.variant != "pixel" and not data_only:
                lp, lq, diff = _adjacent_pairs(
                    lab.reshape(kf.X_hat.shape[:2]), d.clamp_min(MIN_RANGE).log()
                )
                bnd.append((lp + num_params, lq + num_params, diff))
            num_params += count
        num_pixels += lab.numel()
    return _Pixels(
        torch.cat(depth0),
        torch.cat(rays),
        torch.cat(param),
        pixel_offsets,
        param_offsets,
        s_start,
        bnd,
    )


def build_problem(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    index_of: Callable[[int], int],
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
    pinned: set[int],
    data_only: bool = False,
    ranges: Sequence[float] | None = None,
) -> tuple[Problem, list[int], list[int]]:
    """Flatten keyframes, matches and boundary pairs.

    ``ranges`` are the keyframes' median ranges (:func:`median_range` of ``X_hat``) that
    whiten C-Eq. 21, when the caller has them; None computes them.
    ``data_only`` leaves the warm start and the boundary pairs out (empty): what a chunk of
    the data term needs (:mod:`como3r.backend.paged_refinement`).

    Returns:
        the problem, the first pixel of each keyframe, the first log-scale of each keyframe.
    """
    dtype, device = keyframes[0].X_init.dtype, keyframes[0].X_init.device
    px = _pixels(keyframes, labels, config, pinned, data_only)
    match_a, match_b, rays_b_in_a, t_ab, sqrt_w = _flatten_matches(
        keyframes,
        poses.to(dtype),
        edges,
        index_of,
        px.pixel_offsets,
        px.param,
        px.rays,
        config.sigma_point,
        ranges,
    )
    num_params = sum(int(s.numel()) for s in px.s_start) if not data_only else 0
    if px.boundary:
        bnd_a, bnd_b, delta = _boundary_terms(
            *(torch.cat(p) for p in zip(*px.boundary)), max(num_params, 1)
        )
        if config.boundary_residual == "jump_change":
            delta = torch.zeros_like(delta)
    else:
        bnd_a = bnd_b = torch.zeros(0, dtype=torch.int64, device=device)
        delta = torch.zeros(0, dtype=dtype, device=device)
    s0 = torch.cat(px.s_start) if px.s_start else torch.zeros(0, dtype=dtype, device=device)
    problem = Problem(
        px.depth0,
        px.rays,
        px.param.clamp_min(-1),
        match_a,
        match_b,
        rays_b_in_a,
        t_ab,
        sqrt_w,
        bnd_a,
        bnd_b,
        delta,
        s0,
    )
    return problem, px.pixel_offsets, px.param_offsets


def _edge_rows(
    edge: Edge, index_of: Callable[[int], int], keyframes: Sequence[RefinableKeyframe]
) -> tuple[int, int, int]:
    """An edge's endpoints as positions ``(ki, kj)`` in ``keyframes`` and keyframe i's pixel
    count, its matches checked to be one per pixel of keyframe j.

    Raises:
        InputError: an endpoint not in ``index_of`` or out of range, or matches that are not
            one per pixel of j.
    """
    try:
        ki, kj = index_of(edge.i), index_of(edge.j)
    except (KeyError, IndexError):
        raise InputError(
            f"refine_depths: edge ({edge.i}, {edge.j}) names a keyframe key "
            f"that is not in key_to_index"
        ) from None
    if not (0 <= ki < len(keyframes) and 0 <= kj < len(keyframes)):
        raise InputError(
            f"refine_depths: edge ({edge.i}, {edge.j}) maps to keyframe "
            f"indices ({ki}, {kj}) outside 0..{len(keyframes) - 1}"
        )
    m = edge.matches
    P_i = keyframes[ki].X_hat.shape[0] * keyframes[ki].X_hat.shape[1]
    P_j = keyframes[kj].X_hat.shape[0] * keyframes[kj].X_hat.shape[1]
    if m.idx.numel() != P_j or m.valid.numel() != P_j or m.q.numel() != P_j:
        raise InputError(
            f"refine_depths: edge ({edge.i}, {edge.j}) has {m.idx.numel()} "
            f"matches for a keyframe j of {P_j} pixels"
        )
    return ki, kj, P_i


def _outside_error(edge: Edge, P_i: int) -> InputError:
    return InputError(
        f"refine_depths: edge ({edge.i}, {edge.j}) matches pixel indices "
        f"outside keyframe i's {P_i} pixels"
    )


def _relative_pose(poses: Tensor, ki: int, kj: int) -> Tensor:
    """``(8,)`` ``T_ij = T_i^-1 T_j`` of two keyframe positions in ``poses (N, 8)``."""
    return sim3_compose(sim3_inverse(poses[ki]), poses[kj])


def _flatten_matches(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    index_of: Callable[[int], int],
    pixel_offsets: list[int],
    param: Tensor,
    rays: Tensor,
    sigma_point: float,
    ranges: Sequence[float] | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Matches of all edges whose endpoints are valid and at least one is free.

    Args:
        param: ``(P,)`` every pixel's log-scale (-1: invalid, -2: valid and fixed).
        rays: ``(P, 3)`` every pixel's unit ray.
        ranges: each keyframe's median range ``d_i`` (None: computed here).

    Returns:
        pixel of i ``(K,)``, pixel of j ``(K,)`` (flat over all keyframes), j's ray in frame
        i ``s_ij R_ij psi_j`` ``(K, 3)`` (the data Jacobian of j's endpoint over d_j,
        C-Sec. A.6; constant at frozen poses), the translation of ``T_ij`` per match
        ``(K, 3)`` and the whitening ``sqrt(q) / (sigma_point d_i)`` ``(K,)``, with ``d_i``
        keyframe i's median range: ``sigma_point`` is relative to the scene depth
        (:mod:`como3r.geometry.units`), the residual is in camera i's units.
    """
    dtype, device = poses.dtype, poses.device
    parts = []
    depth_of = _RangeCache(keyframes, ranges)
    for edge in edges:
        ki, kj, P_i = _edge_rows(edge, index_of, keyframes)
        m = edge.matches
        n = torch.nonzero(
            m.valid.to(device) & torch.isfinite(m.q.to(device)) & (m.q.to(device) > 0)
        ).squeeze(-1)
        idx = m.idx.to(device)[n]
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= P_i):
            raise _outside_error(edge, P_i)
        a, b = idx + pixel_offsets[ki], n + pixel_offsets[kj]
        pa, pb = param[a], param[b]
        keep = (pa != -1) & (pb != -1) & ((pa >= 0) | (pb >= 0))
        a, b = a[keep], b[keep]
        T_ij = _relative_pose(poses, ki, kj)
        # one rotation matrix per edge, applied as a product, not a quaternion per match
        ray_b_in_a = T_ij[7] * (rays[b] @ quat_to_matrix(T_ij[3:7]).T)
        sqrt_w = m.q.to(device=device, dtype=dtype)[n[keep]].sqrt() / (sigma_point * depth_of[ki])
        parts.append((a, b, ray_b_in_a, T_ij[:3].expand(a.numel(), 3), sqrt_w))
    if not parts:
        empty_i = torch.zeros(0, dtype=torch.int64, device=device)
        empty_f = torch.zeros(0, dtype=dtype, device=device)
        return empty_i, empty_i, empty_f.reshape(0, 3), empty_f.reshape(0, 3), empty_f
    match_a, match_b, rays_b_in_a, t_ab, sqrt_w = (torch.cat(p) for p in zip(*parts))
    return match_a, match_b, rays_b_in_a, t_ab, sqrt_w


class _RangeCache(dict):
    """Keyframe position -> its median range ``d_i`` (given, or computed once when asked)."""

    def __init__(
        self, keyframes: Sequence[RefinableKeyframe], ranges: Sequence[float] | None
    ) -> None:
        super().__init__()
        self._keyframes, self._ranges = keyframes, ranges

    def __missing__(self, k: int) -> float:
        self[k] = (
            float(median_range(self._keyframes[k].X_hat))
            if self._ranges is None
            else float(self._ranges[k])
        )
        return self[k]


def chunk_streams(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    index_of: Callable[[int], int],
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
    pinned: set[int],
    ranges: Sequence[float] | None = None,
) -> cpu_kernels.MatchStreams:
    """The data term of CPU keyframes as the compiled loop reads it: what
    ``match_streams(build_problem(..., data_only=True))`` gives, each edge's kept matches
    written straight into the streams by one compiled pass (the flattened problem's
    per-match arrays, concatenations and gathers took 10 times as long on 3 M matches).
    Arguments as for :func:`build_problem`.

    Raises:
        InputError: an edge naming an unknown keyframe, or matching pixels outside one.
    """
    dtype = keyframes[0].X_init.dtype
    px = _pixels(keyframes, labels, config, pinned, data_only=True)
    poses, depth_of = poses.to(dtype), _RangeCache(keyframes, ranges)
    rows = [_edge_rows(edge, index_of, keyframes) for edge in edges]
    counts = []
    for edge, (ki, kj, P_i) in zip(edges, rows):
        count = cpu_kernels.count_kept(
            edge.matches, px.param, px.pixel_offsets[ki], px.pixel_offsets[kj], P_i
        )
        if count < 0:
            raise _outside_error(edge, P_i)
        counts.append(count)
    streams = cpu_kernels.MatchStreams.empty(sum(counts), dtype)
    first = 0
    for edge, (ki, kj, _), count in zip(edges, rows, counts):
        T_ij = _relative_pose(poses, ki, kj)
        cpu_kernels.pack_kept(
            edge.matches,
            px.depth0,
            px.rays,
            px.param,
            px.pixel_offsets[ki],
            px.pixel_offsets[kj],
            quat_to_matrix(T_ij[3:7]),
            T_ij,
            1.0 / (config.sigma_point * depth_of[ki]),
            first,
            streams,
        )
        first += count
    return streams


def match_streams(
    problem: Problem, param_a: Tensor | None = None, param_b: Tensor | None = None
) -> cpu_kernels.MatchStreams:
    """A CPU problem's matches laid out for the compiled data term
    (:class:`~como3r.backend.cpu_kernels.MatchStreams`); ``param_a, param_b (K,)``, the
    matches' log-scales, when already gathered."""
    p = problem
    return cpu_kernels.MatchStreams.of(
        p.depth0,
        p.rays,
        p.match_a,
        p.match_b,
        p.param[p.match_a] if param_a is None else param_a,
        p.param[p.match_b] if param_b is None else param_b,
        p.rays_b_in_a,
        p.t_ab,
        p.sqrt_w,
    )
