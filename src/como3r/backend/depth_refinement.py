"""Segment-level depth refinement at frozen poses (C-Sec. 3.5, A.6; C-Eq. 19-24; C-Tab. 5).

Every valid pixel ``p`` of a free keyframe lies on the ray of the frozen snapshot
``X_init`` with one multiplicative correction per segment (C-Eq. 19),

    X_p(s_g) = ||X_init,p|| exp(s_g) psi(X_init,p),

and the log-scales ``s`` minimise (C-Eq. 20)

    E = sum_matches sum_c rho(sqrt(q) [T_ij X_j,n(s_b) - X_i,m(s_a)]_c / sigma_point)   (C-Eq. 21)
      + lambda_smooth sum_(a,b) ((s_a - s_b) + Delta_ab)^2                              (C-Eq. 22)
      + lambda_prior sum_g s_g^2                                                        (C-Eq. 23)

by Jacobi-decoupled 1x1 damped Newton steps (C-Eq. 24): each segment's Hessian keeps only
its own diagonal terms (cross-segment terms are dropped, the gradient is exact), the LM
damping is multiplicative, ``H (1 + lambda_lm)``, and each step is clipped to
``|ds| <= s_max``. Everything is accumulated with ``index_add_`` over flat pixel arrays.

Inputs are plain (keyframe-like objects, a pose tensor, :class:`~como3r.frontend.graph.Edge`
lists and a key -> index mapping) so the per-agent graph and the coordinator's global graph
call the same code.

Choices the paper leaves open, made here:

* The log-scales are relative to ``X_init`` (so the prior of C-Eq. 23 anchors to the learned
  geometry) but start from the keyframe's current ``X_hat``: each segment's ``s`` is
  initialised to the mean of ``log(||X_hat,p|| / ||X_init,p||)`` over its pixels. Repeated
  calls of the alternation (C-Sec. A.7), each with fresh segments, therefore continue from
  the previous call's result instead of restarting from the snapshot.
* Pinned keyframes have no unknowns: their current ``X_hat`` enters the data term as a
  constant and is returned unchanged.
* The boundary residual is ``s_a - s_b`` by default (``depth.boundary_residual =
  "jump_change"``): it penalises changes of the depth jump the prior predicts between
  adjacent segments, which is how C-Sec. C.1 describes the term ("penalises only depth jumps
  that the prior itself does not predict") and lets a segment without matches keep the
  prior's depth (C-Eq. 23: "defaults to the MAST3R prediction"). C-Eq. 22 as printed adds
  ``Delta_ab`` and so pulls the refined log-depths on both sides of every segment boundary
  together; SLIC puts boundaries at depth discontinuities, so segments without matches were
  dragged across them (one step moved them by up to 60 % in depth and raised the map's RMS
  point error by a fifth on a 128x96 two-agent scene). ``"log_depth"`` restores it.
* The per-pixel + Laplacian variant is the boundary term on one-pixel segments. With
  ``"log_depth"``, ``(s_p - s_q) + log d_p^init - log d_q^init`` over 4-neighbours is the
  difference of the refined log-depths, whose squared sum is the 4-neighbour log-depth
  Laplacian energy of C-Sec. C.1; with ``"jump_change"`` it smooths the log-scale
  corrections instead.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping, Protocol, Sequence

import torch
from torch import Tensor

from como3r.backend import cpu_kernels
from como3r.backend.segments import labels_in_order
from como3r.config import DepthRefinementConfig
from como3r.errors import ConfigError, InputError
from como3r.frontend.graph import Edge
from como3r.geometry.lie import quat_to_matrix, sim3_compose, sim3_inverse
from como3r.geometry.residuals import huber_weight, psi
from como3r.geometry.units import median_range

logger = logging.getLogger(__name__)

__all__ = [
    "RefinableKeyframe",
    "DepthRefinementReport",
    "refine_depths",
    "refine_keyframes",
    "keyframe_labels",
]

HUBER_K = 1.345
"""Huber breakpoint of the data term (C-Tab. 3, the same kernel as the pose solve)."""

VARIANTS = ("segment", "pixel", "pixel_laplacian")

# Ranges below this have no usable ray; the pixel is left out of the problem.
_MIN_RANGE = 1e-6


class RefinableKeyframe(Protocol):
    """What the refinement needs of a keyframe (:class:`~como3r.frontend.keyframes.Keyframe`).

    Attributes:
        X_hat: ``(H, W, 3)`` current canonical pointmap in the keyframe's camera frame.
        X_init: ``(H, W, 3)`` frozen snapshot of C-Eq. 19.
    """

    X_hat: Tensor
    X_init: Tensor


class SegmentableKeyframe(Protocol):
    """What the segmentation needs of a keyframe.

    Attributes:
        X_hat: ``(H, W, 3)`` current canonical pointmap in the keyframe's camera frame.
    """

    X_hat: Tensor

    def mean_confidence(self) -> Tensor:
        """``(H, W)`` per-frame confidence of ``X_hat``."""


@dataclass
class DepthRefinementReport:
    """What one call of the depth refinement did.

    Attributes:
        variant: ``"segment"``, ``"pixel"`` or ``"pixel_laplacian"`` (C-Tab. 5).
        num_parameters: free log-scales M (pinned keyframes contribute none).
        num_matches: data-term matches with at least one free endpoint.
        num_boundary_pairs: unique adjacent parameter pairs of the boundary term.
        iterations: Newton iterations run.
        cost_history: energy of C-Eq. 20 (no 1/2 prefactor) at the start and after every
            iteration; not necessarily decreasing (C-Sec. A.7).
        max_step: ``max |ds|`` of the last iteration.
        max_change: ``max |s_final - s_start|`` over the free log-scales of this call.
        clipped_steps: parameter updates limited by the step clip, over all iterations.
        seconds: wall-clock time of the call.
    """

    variant: str
    num_parameters: int = 0
    num_matches: int = 0
    num_boundary_pairs: int = 0
    iterations: int = 0
    cost_history: list[float] = field(default_factory=list)
    max_step: float = 0.0
    max_change: float = 0.0
    clipped_steps: int = 0
    seconds: float = 0.0

    @property
    def initial_cost(self) -> float:
        """Energy at the warm start."""
        return self.cost_history[0] if self.cost_history else 0.0

    @property
    def final_cost(self) -> float:
        """Energy at the returned log-scales."""
        return self.cost_history[-1] if self.cost_history else 0.0


@dataclass
class _Problem:
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
    # (E, 3) int64 per edge: first and end match, and the keyframe i (position) whose median
    # range d_i whitens them
    edge_spans: Tensor
    bnd_a: Tensor  # (B,) log-scale a of each unique adjacent pair, a < b
    bnd_b: Tensor  # (B,)
    delta: Tensor  # (B,) Delta_ab of C-Eq. 22
    s_start: Tensor  # (M,) warm start


def _index_fn(key_to_index: Mapping[int, int] | Callable[[int], int]) -> Callable[[int], int]:
    if callable(key_to_index):
        return key_to_index
    return key_to_index.__getitem__


def _mean_log_ratio(X_hat: Tensor, d_init: Tensor, labels: Tensor, count: int) -> Tensor:
    """``(count,)`` mean over each label's pixels of ``log(||X_hat|| / d_init)`` (0 if none)."""
    d_hat = X_hat.reshape(-1, 3).norm(dim=-1)
    flat = labels.reshape(-1)
    ok = (flat >= 0) & torch.isfinite(d_hat) & (d_hat > _MIN_RANGE) & (d_init > _MIN_RANGE)
    ratio = torch.log(d_hat[ok] / d_init[ok])
    sums = torch.zeros(count, dtype=ratio.dtype, device=ratio.device).index_add_(0, flat[ok], ratio)
    counts = torch.zeros(count, dtype=ratio.dtype, device=ratio.device).index_add_(
        0, flat[ok], torch.ones_like(ratio))
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


def _boundary_terms(label_p: Tensor, label_q: Tensor, diff: Tensor, num_params: int
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Unique unordered pairs ``(a, b)``, ``a < b``, with ``Delta_ab`` averaged over the
    shared boundary pixels (C-Eq. 22)."""
    swap = label_p > label_q
    a = torch.where(swap, label_q, label_p)
    b = torch.where(swap, label_p, label_q)
    diff = torch.where(swap, -diff, diff)
    keys, inverse = torch.unique(a * num_params + b, return_inverse=True)
    sums = torch.zeros(keys.numel(), dtype=diff.dtype, device=diff.device).index_add_(
        0, inverse, diff)
    counts = torch.zeros_like(sums).index_add_(0, inverse, torch.ones_like(diff))
    return keys // num_params, keys % num_params, sums / counts


def _check_inputs(keyframes: Sequence[RefinableKeyframe], poses: Tensor,
                  labels: Sequence[Tensor], config: DepthRefinementConfig) -> None:
    if config.variant not in VARIANTS:
        raise ConfigError(f"depth.variant must be one of {VARIANTS}, got {config.variant!r}")
    for name in ("sigma_point", "step_clip"):
        if not getattr(config, name) > 0:
            raise ConfigError(f"depth.{name} must be positive, got {getattr(config, name)}")
    for name in ("lambda_smooth", "lambda_prior", "lambda_lm", "inner_iters"):
        if not getattr(config, name) >= 0:
            raise ConfigError(f"depth.{name} must be non-negative, got {getattr(config, name)}")
    if poses.ndim != 2 or poses.shape != (len(keyframes), 8):
        raise InputError(
            f"refine_depths: poses must be ({len(keyframes)}, 8), got {tuple(poses.shape)}")
    if len(labels) != len(keyframes):
        raise InputError(
            f"refine_depths: {len(labels)} label maps for {len(keyframes)} keyframes")
    for k, (kf, lab) in enumerate(zip(keyframes, labels)):
        if kf.X_init.shape != kf.X_hat.shape or kf.X_hat.ndim != 3 or kf.X_hat.shape[-1] != 3:
            raise InputError(f"refine_depths: keyframe {k} X_hat {tuple(kf.X_hat.shape)} and "
                             f"X_init {tuple(kf.X_init.shape)} must both be (H, W, 3)")
        if tuple(lab.shape) != tuple(kf.X_hat.shape[:2]):
            raise InputError(f"refine_depths: label map {k} is {tuple(lab.shape)}, keyframe is "
                             f"{tuple(kf.X_hat.shape[:2])}")


def _build_problem(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    index_of: Callable[[int], int],
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
    pinned: set[int],
    data_only: bool = False,
    ranges: Sequence[float] | None = None,
) -> tuple[_Problem, list[int], list[int]]:
    """Flatten keyframes, matches and boundary pairs.

    ``ranges`` are the keyframes' median ranges (:func:`median_range` of ``X_hat``) that
    whiten C-Eq. 21, when the caller has them; None computes them.
    ``data_only`` leaves the warm start and the boundary pairs out (empty): what a chunk of
    the data term needs (:mod:`como3r.backend.paged_refinement`).

    Returns:
        the problem, the first pixel of each keyframe, the first log-scale of each keyframe.
    """
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
        lab = torch.where(torch.isfinite(X_base).all(-1) & (d > _MIN_RANGE), lab, -1)
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
                s_start.append(_mean_log_ratio(kf.X_hat.to(dtype), d, lab.reshape(-1), count))
            if config.variant != "pixel" and not data_only:
                lp, lq, diff = _adjacent_pairs(lab.reshape(kf.X_hat.shape[:2]),
                                               d.clamp_min(_MIN_RANGE).log())
                bnd.append((lp + num_params, lq + num_params, diff))
            num_params += count
        num_pixels += lab.numel()

    depth0_t, rays_t, param_t = torch.cat(depth0), torch.cat(rays), torch.cat(param)
    match_a, match_b, rays_b_in_a, t_ab, sqrt_w, edge_spans = _flatten_matches(
        keyframes, poses.to(dtype), edges, index_of, pixel_offsets, param_t, rays_t,
        config.sigma_point, ranges)
    if bnd:
        bnd_a, bnd_b, delta = _boundary_terms(*(torch.cat(p) for p in zip(*bnd)),
                                              max(num_params, 1))
        if config.boundary_residual == "jump_change":
            delta = torch.zeros_like(delta)
    else:
        bnd_a = bnd_b = torch.zeros(0, dtype=torch.int64, device=device)
        delta = torch.zeros(0, dtype=dtype, device=device)
    s0 = torch.cat(s_start) if s_start else torch.zeros(0, dtype=dtype, device=device)
    problem = _Problem(depth0_t, rays_t, param_t.clamp_min(-1), match_a, match_b, rays_b_in_a,
                       t_ab, sqrt_w, edge_spans, bnd_a, bnd_b, delta, s0)
    return problem, pixel_offsets, param_offsets


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
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
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
        (:mod:`como3r.geometry.units`), the residual is in camera i's units; and the
        ``(E, 3)`` spans of :attr:`_Problem.edge_spans`.
    """
    dtype, device = poses.dtype, poses.device
    parts, spans, count = [], [], 0
    depth_of: dict[int, float] = {}
    for edge in edges:
        try:
            ki, kj = index_of(edge.i), index_of(edge.j)
        except (KeyError, IndexError):
            raise InputError(f"refine_depths: edge ({edge.i}, {edge.j}) names a keyframe key "
                             f"that is not in key_to_index") from None
        if not (0 <= ki < len(keyframes) and 0 <= kj < len(keyframes)):
            raise InputError(f"refine_depths: edge ({edge.i}, {edge.j}) maps to keyframe "
                             f"indices ({ki}, {kj}) outside 0..{len(keyframes) - 1}")
        m = edge.matches
        P_i = keyframes[ki].X_hat.shape[0] * keyframes[ki].X_hat.shape[1]
        P_j = keyframes[kj].X_hat.shape[0] * keyframes[kj].X_hat.shape[1]
        if m.idx.numel() != P_j or m.valid.numel() != P_j or m.q.numel() != P_j:
            raise InputError(f"refine_depths: edge ({edge.i}, {edge.j}) has {m.idx.numel()} "
                             f"matches for a keyframe j of {P_j} pixels")
        n = torch.nonzero(m.valid.to(device) & torch.isfinite(m.q.to(device))
                          & (m.q.to(device) > 0)).squeeze(-1)
        idx = m.idx.to(device)[n]
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= P_i):
            raise InputError(f"refine_depths: edge ({edge.i}, {edge.j}) matches pixel "
                             f"indices outside keyframe i's {P_i} pixels")
        a, b = idx + pixel_offsets[ki], n + pixel_offsets[kj]
        pa, pb = param[a], param[b]
        keep = (pa != -1) & (pb != -1) & ((pa >= 0) | (pb >= 0))
        a, b = a[keep], b[keep]
        T_ij = sim3_compose(sim3_inverse(poses[ki]), poses[kj])
        # one rotation matrix per edge, applied as a product, not a quaternion per match
        ray_b_in_a = T_ij[7] * (rays[b] @ quat_to_matrix(T_ij[3:7]).T)
        if ki not in depth_of:
            depth_of[ki] = (float(median_range(keyframes[ki].X_hat)) if ranges is None
                            else ranges[ki])
        sqrt_w = m.q.to(device=device, dtype=dtype)[n[keep]].sqrt() / (sigma_point * depth_of[ki])
        parts.append((a, b, ray_b_in_a, T_ij[:3].expand(a.numel(), 3), sqrt_w))
        spans.append((count, count + a.numel(), ki))
        count += a.numel()
    edge_spans = torch.tensor(spans, dtype=torch.int64, device=device).reshape(-1, 3)
    if not parts:
        empty_i = torch.zeros(0, dtype=torch.int64, device=device)
        empty_f = torch.zeros(0, dtype=dtype, device=device)
        return (empty_i, empty_i, empty_f.reshape(0, 3), empty_f.reshape(0, 3), empty_f,
                edge_spans)
    match_a, match_b, rays_b_in_a, t_ab, sqrt_w = (torch.cat(p) for p in zip(*parts))
    return match_a, match_b, rays_b_in_a, t_ab, sqrt_w, edge_spans


def _huber_cost(r: Tensor, k: float) -> Tensor:
    """``sum rho(r)`` with ``rho(r) = r^2`` inside ``k`` and ``2 k |r| - k^2`` outside."""
    a = r.abs()
    return torch.where(a <= k, a * a, 2.0 * k * a - k * k).sum()


class _Refiner:
    """Newton iterations of C-Eq. 24 on a flattened problem."""

    def __init__(self, problem: _Problem, config: DepthRefinementConfig, huber_k: float):
        self.p = problem
        self.config = config
        self.huber_k = huber_k
        self.free_pixels = torch.nonzero(problem.param >= 0).squeeze(-1)
        self.match_param_a = problem.param[problem.match_a]
        self.match_param_b = problem.param[problem.match_b]
        self._streams: cpu_kernels.MatchStreams | None = None

    def depths(self, s: Tensor) -> Tensor:
        """``(P,)`` ranges ``d0 exp(s_g)`` (C-Eq. 19); fixed pixels keep ``d0``."""
        log_scale = torch.zeros_like(self.p.depth0)
        log_scale[self.free_pixels] = s[self.p.param[self.free_pixels]]
        return self.p.depth0 * log_scale.exp()

    def _data(self, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Whitened residuals ``(K, 3)`` and both endpoints' Jacobians ``(K, 3)``."""
        p = self.p
        d = self.depths(s)
        d_a, d_b = d[p.match_a, None], d[p.match_b, None]
        w = p.sqrt_w[:, None]
        J_a = -w * d_a * p.rays[p.match_a]
        J_b = w * d_b * p.rays_b_in_a
        r = w * (d_b * p.rays_b_in_a + p.t_ab) + J_a
        return r, J_a, J_b

    def _energy(self, s: Tensor, r: Tensor, r_bnd: Tensor) -> Tensor:
        return _huber_cost(r, self.huber_k) + _regularisers(s, r_bnd, self.config)

    def energy(self, s: Tensor) -> Tensor:
        """Energy of C-Eq. 20 (differentiable in ``s`` when it requires a gradient)."""
        r_bnd = s[self.p.bnd_a] - s[self.p.bnd_b] + self.p.delta
        if self._runs_compiled(s):
            data = self._compiled_data(s, with_blocks=False)[2]
            return data + _regularisers(s, r_bnd, self.config)
        return self._energy(s, self._data(s)[0], r_bnd)

    def data_terms(self, s: Tensor, with_blocks: bool = True) -> tuple[Tensor, Tensor, float]:
        """The data term of C-Eq. 21: its diagonal Hessian ``(M,)``, exact gradient ``(M,)``
        (Jacobi-decoupled, C-Eq. 24; float64 from the compiled loop, else ``s``'s dtype) and
        its cost; ``with_blocks=False`` computes the cost alone (``H`` and ``g`` are zero)."""
        if self._runs_compiled(s):
            return self._compiled_data(s, with_blocks)
        H, g = torch.zeros_like(s), torch.zeros_like(s)
        r, J_a, J_b = self._data(s)
        if with_blocks:
            w = huber_weight(r, self.huber_k)
            for params, J in ((self.match_param_a, J_a), (self.match_param_b, J_b)):
                free = params >= 0
                # Jacobi decoupling: only J_a^T W J_a and J_b^T W J_b; J_a^T W J_b is dropped.
                H.index_add_(0, params[free], (w * J * J).sum(-1)[free])
                g.index_add_(0, params[free], (w * J * r).sum(-1)[free])
        return H, g, float(_huber_cost(r, self.huber_k))

    def normal_equations(self, s: Tensor) -> tuple[Tensor, Tensor, float]:
        """Diagonal Hessian ``(M,)``, exact gradient ``(M,)`` (C-Eq. 24) and the energy."""
        p = self.p
        return regularised(*self.data_terms(s), s, p.bnd_a, p.bnd_b, p.delta, self.config)

    def _runs_compiled(self, s: Tensor) -> bool:
        """CPU problems take the compiled loop, except for log-scales autograd
        differentiates."""
        return s.device.type == "cpu" and not s.requires_grad

    def _compiled_data(self, s: Tensor, with_blocks: bool = True) -> tuple[Tensor, Tensor, float]:
        """The data term's diagonal Hessian, gradient (float64, ``(M,)``) and cost by
        :func:`como3r.backend.cpu_kernels.depth_normal_equations` (its matches laid out
        match by match at the first call)."""
        if self._streams is None:
            self._streams = match_streams(self.p, self.match_param_a, self.match_param_b)
        return cpu_kernels.depth_normal_equations(s, self._streams, self.huber_k, with_blocks)

    def step(self, s: Tensor) -> tuple[Tensor, int, float]:
        """One damped, clipped Newton step.

        Returns:
            ``ds (M,)``, how many entries the clip limited, and the energy at ``s``.
        """
        H, g, energy = self.normal_equations(s)
        return (*damped_step(H, g, s, self.config), energy)


def match_streams(problem: _Problem, param_a: Tensor | None = None,
                  param_b: Tensor | None = None) -> cpu_kernels.MatchStreams:
    """A CPU problem's matches laid out for the compiled data term
    (:class:`~como3r.backend.cpu_kernels.MatchStreams`); ``param_a, param_b (K,)``, the
    matches' log-scales, when already gathered."""
    p = problem
    return cpu_kernels.MatchStreams.of(
        p.depth0, p.rays, p.match_a, p.match_b,
        p.param[p.match_a] if param_a is None else param_a,
        p.param[p.match_b] if param_b is None else param_b, p.rays_b_in_a, p.t_ab, p.sqrt_w)


def _regularisers(s: Tensor, r_bnd: Tensor, config: DepthRefinementConfig) -> Tensor:
    """Boundary (C-Eq. 22) and prior (C-Eq. 23) energies."""
    return config.lambda_smooth * (r_bnd ** 2).sum() + config.lambda_prior * (s ** 2).sum()


def regularised(H: Tensor, g: Tensor, data_cost: float, s: Tensor, bnd_a: Tensor,
                bnd_b: Tensor, delta: Tensor, config: DepthRefinementConfig
                ) -> tuple[Tensor, Tensor, float]:
    """The data term's normal equations with the boundary (C-Eq. 22) and prior (C-Eq. 23)
    terms added: the Hessian diagonal ``(M,)``, gradient ``(M,)`` (in ``s``'s dtype) and the
    energy of C-Eq. 20.

    Args:
        H, g: ``(M,)`` the data term's diagonal Hessian and gradient; data_cost: its cost.
        s: ``(M,)`` the log-scales.
        bnd_a, bnd_b: ``(B,)`` int64 adjacent log-scale pairs; delta: ``(B,)`` their
            ``Delta_ab``.
        config: ``lambda_smooth``, ``lambda_prior``.
    """
    r_bnd = s[bnd_a] - s[bnd_b] + delta
    H, g = H.to(s) + config.lambda_prior, g.to(s) + config.lambda_prior * s
    energy = data_cost + float(_regularisers(s, r_bnd, config))
    ones = torch.full_like(r_bnd, config.lambda_smooth)
    H.index_add_(0, bnd_a, ones).index_add_(0, bnd_b, ones)
    g.index_add_(0, bnd_a, config.lambda_smooth * r_bnd)
    g.index_add_(0, bnd_b, -config.lambda_smooth * r_bnd)
    return H, g, energy


def damped_step(H: Tensor, g: Tensor, s: Tensor, config: DepthRefinementConfig
                ) -> tuple[Tensor, int]:
    """The damped, clipped 1x1 Newton step of C-Eq. 24 from the diagonal Hessian ``H (M,)``
    and gradient ``g (M,)`` at ``s (M,)``: ``ds (M,)`` and how many entries the clip
    limited."""
    damped = H * (1.0 + config.lambda_lm)
    ds = torch.where(damped > 0, -g / damped.clamp_min(torch.finfo(s.dtype).tiny),
                     torch.zeros_like(g))
    clip = config.step_clip
    clipped = int((ds.abs() > clip).sum())
    return ds.clamp(-clip, clip), clipped


def refine_depths(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    key_to_index: Mapping[int, int] | Callable[[int], int],
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
    pinned: Iterable[int] = (),
    *,
    huber_k: float = HUBER_K,
) -> tuple[list[Tensor], list[Tensor], DepthRefinementReport]:
    """Refine the keyframes' depths at frozen poses (C-Eq. 19-24).

    Args:
        keyframes: N keyframe-like objects (``X_hat``, ``X_init``, both ``(H_k, W_k, 3)`` in
            the keyframe's camera frame).
        poses: ``(N, 8)`` Sim(3) ``T_WC`` of the keyframes, frozen during the refinement.
        edges: directed edges; ``edge.matches.idx[n]`` is the pixel of keyframe ``edge.i``
            matched to pixel ``n`` of keyframe ``edge.j`` (only ``valid`` matches are used:
            ``valid`` already carries the ``q > Q_min`` gate of the pose solve).
        key_to_index: maps an edge endpoint key to its position in ``keyframes``.
        labels: N label maps ``(H_k, W_k)`` int64, ``-1`` for excluded pixels
            (:func:`~como3r.backend.segments.parameter_labels` of ``config.variant``).
        config: ``variant``, noise, weights, damping, clip, ``inner_iters``.
        pinned: positions in ``keyframes`` held fixed (e.g. the gauge anchor).
        huber_k: Huber breakpoint of the data term.

    Returns:
        ``(X_hat, log_scales, report)``: N refined pointmaps (pinned keyframes' tensors are
        returned as they are, others are new tensors; pixels with label -1 keep their
        ``X_hat``), N log-scale vectors ``(M_k,)`` relative to ``X_init`` (pinned keyframes:
        the fixed mean log-ratio of their ``X_hat``), and a report.

    Raises:
        InputError: inconsistent shapes, or an edge naming an unknown keyframe.
        ConfigError: an unknown variant.
    """
    start = time.perf_counter()
    _check_inputs(keyframes, poses, labels, config)
    report = DepthRefinementReport(variant=config.variant)
    if not keyframes:
        return [], [], report
    pinned_set = {int(k) for k in pinned}
    problem, pixel_offsets, param_offsets = _build_problem(
        keyframes, poses, edges, _index_fn(key_to_index), labels, config, pinned_set)
    refiner = _Refiner(problem, config, huber_k)
    s = problem.s_start.clone()
    report.num_parameters = s.numel()
    report.num_matches = problem.match_a.numel()
    report.num_boundary_pairs = problem.bnd_a.numel()
    if s.numel():
        for _ in range(config.inner_iters):
            ds, clipped, energy = refiner.step(s)
            report.cost_history.append(energy)
            s = s + ds
            report.iterations += 1
            report.clipped_steps += clipped
            report.max_step = float(ds.abs().max())
        report.max_change = float((s - problem.s_start).abs().max())
    report.cost_history.append(float(refiner.energy(s)))

    depths = refiner.depths(s)
    X_out, log_scales = [], []
    for k, kf in enumerate(keyframes):
        H, W = kf.X_hat.shape[:2]
        lab = labels[k].to(torch.int64)
        count = int(lab.max()) + 1 if lab.numel() else 0
        if k in pinned_set:
            X_out.append(kf.X_hat)
            log_scales.append(_mean_log_ratio(kf.X_hat, kf.X_init.reshape(-1, 3).norm(dim=-1),
                                              lab.to(kf.X_hat.device), count))
            continue
        rows = slice(pixel_offsets[k], pixel_offsets[k] + H * W)
        X_out.append(written_back(kf.X_hat, depths[rows], problem.rays[rows],
                                  problem.param[rows]))
        log_scales.append(s[param_offsets[k]:param_offsets[k] + count])
    report.seconds = time.perf_counter() - start
    logger.debug("depth refinement (%s): %d params, %d matches, cost %.4g -> %.4g, max |ds| "
                 "%.3g", report.variant, report.num_parameters, report.num_matches,
                 report.initial_cost, report.final_cost, report.max_change)
    return X_out, log_scales, report


def written_back(X_hat: Tensor, depths: Tensor, rays: Tensor, param: Tensor) -> Tensor:
    """A keyframe's refined pointmap (C-Eq. 19): ``X_hat (H, W, 3)`` with every pixel that
    has a free log-scale (``param (H W,) >= 0``) moved to ``depths (H W,)`` times its unit
    ray ``rays (H W, 3)``; the other pixels keep their ``X_hat``. A new tensor."""
    points = (depths[:, None] * rays).to(X_hat.dtype)
    return torch.where((param >= 0)[:, None], points, X_hat.reshape(-1, 3)).reshape(X_hat.shape)


def keyframe_labels(keyframes: Sequence[SegmentableKeyframe], config: DepthRefinementConfig
                    ) -> list[Tensor]:
    """Label maps of ``config.variant`` for the keyframes' current ``X_hat`` (confidence:
    ``mean_confidence()``, comparable to one prediction's ``C``)."""
    pointmaps = ((k, kf.X_hat, kf.mean_confidence()) for k, kf in enumerate(keyframes))
    return [labels for _, labels in labels_in_order(pointmaps, config)]


def refine_keyframes(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    edges: Sequence[Edge],
    key_to_index: Mapping[int, int] | Callable[[int], int],
    config: DepthRefinementConfig,
    pinned: Iterable[int] = (),
    labels: Sequence[Tensor] | None = None,
) -> DepthRefinementReport:
    """One depth step of the alternation (C-Sec. A.7, steps 2a-2c), in place.

    Refines the log-scales at the frozen ``poses`` and writes the refined points back into
    ``X_hat``.

    Args:
        keyframes, poses, edges, key_to_index, config, pinned: as for :func:`refine_depths`.
        labels: the keyframes' label maps; None segments each keyframe's current ``X_hat``
            by ``config.variant`` (:func:`keyframe_labels`).

    Returns:
        The report; ``report.max_change`` is the ``max |ds|`` the alternation tests.
    """
    if labels is None:
        labels = keyframe_labels(keyframes, config)
    X_new, _, report = refine_depths(keyframes, poses, edges, key_to_index, labels, config,
                                     pinned)
    for kf, X in zip(keyframes, X_new):
        kf.X_hat = X
    return report
