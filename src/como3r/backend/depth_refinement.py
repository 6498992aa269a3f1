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
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import torch
from torch import Tensor

from como3r.backend import cpu_kernels
from como3r.backend.depth_problem import (
    Problem,
    RefinableKeyframe,
    build_problem,
    match_streams,
    mean_log_ratio,
)
from como3r.backend.segments import labels_in_order
from como3r.config import DepthRefinementConfig
from como3r.errors import ConfigError, InputError
from como3r.frontend.graph import Edge
from como3r.geometry.residuals import huber_weight

logger = logging.getLogger(__name__)

__all__ = [
    "DepthRefinementReport",
    "refine_depths",
    "refine_keyframes",
    "keyframe_labels",
]

HUBER_K = 1.345
"""Huber breakpoint of the data term (C-Tab. 3, the same kernel as the pose solve)."""

VARIANTS = ("segment", "pixel", "pixel_laplacian")


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


def _index_fn(key_to_index: Mapping[int, int] | Callable[[int], int]) -> Callable[[int], int]:
    if callable(key_to_index):
        return key_to_index
    return key_to_index.__getitem__


def _check_inputs(
    keyframes: Sequence[RefinableKeyframe],
    poses: Tensor,
    labels: Sequence[Tensor],
    config: DepthRefinementConfig,
) -> None:
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
            f"refine_depths: poses must be ({len(keyframes)}, 8), got {tuple(poses.shape)}"
        )
    if len(labels) != len(keyframes):
        raise InputError(f"refine_depths: {len(labels)} label maps for {len(keyframes)} keyframes")
    for k, (kf, lab) in enumerate(zip(keyframes, labels)):
        if kf.X_init.shape != kf.X_hat.shape or kf.X_hat.ndim != 3 or kf.X_hat.shape[-1] != 3:
            raise InputError(
                f"refine_depths: keyframe {k} X_hat {tuple(kf.X_hat.shape)} and "
                f"X_init {tuple(kf.X_init.shape)} must both be (H, W, 3)"
            )
        if tuple(lab.shape) != tuple(kf.X_hat.shape[:2]):
            raise InputError(
                f"refine_depths: label map {k} is {tuple(lab.shape)}, keyframe is "
                f"{tuple(kf.X_hat.shape[:2])}"
            )


def _huber_cost(r: Tensor, k: float) -> Tensor:
    """``sum rho(r)`` with ``rho(r) = r^2`` inside ``k`` and ``2 k |r| - k^2`` outside."""
    a = r.abs()
    return torch.where(a <= k, a * a, 2.0 * k * a - k * k).sum()


class _Refiner:
    """Newton iterations of C-Eq. 24 on a flattened problem."""

    def __init__(self, problem: Problem, config: DepthRefinementConfig, huber_k: float):
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


def _regularisers(s: Tensor, r_bnd: Tensor, config: DepthRefinementConfig) -> Tensor:
    """Boundary (C-Eq. 22) and prior (C-Eq. 23) energies."""
    return config.lambda_smooth * (r_bnd**2).sum() + config.lambda_prior * (s**2).sum()


def regularised(
    H: Tensor,
    g: Tensor,
    data_cost: float,
    s: Tensor,
    bnd_a: Tensor,
    bnd_b: Tensor,
    delta: Tensor,
    config: DepthRefinementConfig,
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


def damped_step(
    H: Tensor, g: Tensor, s: Tensor, config: DepthRefinementConfig
) -> tuple[Tensor, int]:
    """The damped, clipped 1x1 Newton step of C-Eq. 24 from the diagonal Hessian ``H (M,)``
    and gradient ``g (M,)`` at ``s (M,)``: ``ds (M,)`` and how many entries the clip
    limited."""
    damped = H * (1.0 + config.lambda_lm)
    ds = torch.where(
        damped > 0, -g / damped.clamp_min(torch.finfo(s.dtype).tiny), torch.zeros_like(g)
    )
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
    problem, pixel_offsets, param_offsets = build_problem(
        keyframes, poses, edges, _index_fn(key_to_index), labels, config, pinned_set
    )
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
            log_scales.append(
                mean_log_ratio(
                    kf.X_hat, kf.X_init.reshape(-1, 3).norm(dim=-1), lab.to(kf.X_hat.device), count
                )
            )
            continue
        rows = slice(pixel_offsets[k], pixel_offsets[k] + H * W)
        X_out.append(written_back(kf.X_hat, depths[rows], problem.rays[rows], problem.param[rows]))
        log_scales.append(s[param_offsets[k] : param_offsets[k] + count])
    report.seconds = time.perf_counter() - start
    logger.debug(
        "depth refinement (%s): %d params, %d matches, cost %.4g -> %.4g, max |ds| %.3g",
        report.variant,
        report.num_parameters,
        report.num_matches,
        report.initial_cost,
        report.final_cost,
        report.max_change,
    )
    return X_out, log_scales, report


def written_back(X_hat: Tensor, depths: Tensor, rays: Tensor, param: Tensor) -> Tensor:
    """A keyframe's refined pointmap (C-Eq. 19): ``X_hat (H, W, 3)`` with every pixel that
    has a free log-scale (``param (H W,) >= 0``) moved to ``depths (H W,)`` times its unit
    ray ``rays (H W, 3)``; the other pixels keep their ``X_hat``. A new tensor."""
    points = (depths[:, None] * rays).to(X_hat.dtype)
    return torch.where((param >= 0)[:, None], points, X_hat.reshape(-1, 3)).reshape(X_hat.shape)


def keyframe_labels(
    keyframes: Sequence[SegmentableKeyframe], config: DepthRefinementConfig
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
    X_new, _, report = refine_depths(keyframes, poses, edges, key_to_index, labels, config, pinned)
    for kf, X in zip(keyframes, X_new):
        kf.X_hat = X
    return report
