"""Dense relative-pose factors over pointmap correspondences (C-Eq. 2, 5, 17).

One factor batch holds E edges (i, j), each with P matched pixels (padded and masked by
``valid``; matches invalid at every pose are dropped when the batch is built). Its
residual is a function of the relative pose ``T_ij = T_WC_i^-1 T_WC_j`` (C-Eq. 13) only,
so the same class serves

* tracking (C-Eq. 2): one edge (keyframe 0, frame 1) with the keyframe pinned at the
  identity, so ``T_ij`` is the frame pose ``T_kf``;
* the per-agent local keyframe-graph solve and the global bundle adjustment (C-Eq. 5).

Each match contributes C residual components, each whitened by
``Sigma_mn^-1/2 = sqrt(q_mn) / sigma_c`` (C-Eq. 7) and robustified independently by a
Huber kernel (C-Eq. 8). ``linearize`` produces the per-edge Gauss-Newton blocks with the
IRLS weights ``w = min(1, k/|r|)`` recomputed from the whitened residual of the poses it is
given (C-Sec. B.2); ``cost`` evaluates the robust energy for Levenberg-Marquardt.

The two residual models, :class:`~como3r.optim.match_factors.RayRangeFactors` (C-Eq. 6) and
:class:`~como3r.optim.match_factors.CalibratedFactors` (C-Eq. 17), are in
:mod:`como3r.optim.match_factors`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Protocol

import torch

import como3r.optim.cpu_kernels as cpu_kernels
from como3r.errors import InputError
from como3r.geometry.lie import (
    sim3_adjoint,
    sim3_compose,
    sim3_inverse,
    sim3_log,
)
from como3r.geometry.residuals import huber_weight
from como3r.optim.system import EdgeBlocks

# Matches linearized at once: bounds the (chunk, P, C, 7) Jacobian, its weighted copy and
# the temporaries of the residual to ~100 MB in float32 whatever E and P are (a chunk holds
# at least one edge, so one tracking edge of 200k pixels is a single chunk).
DEFAULT_CHUNK_MATCHES = 1 << 18


class Factor(Protocol):
    """What an optimizer needs from a factor batch (GTSAM's NonlinearFactor, batched)."""

    def linearize(self, poses: torch.Tensor) -> EdgeBlocks:
        """Per-edge Gauss-Newton blocks at poses ``(N, 8)``."""
        ...

    def cost(self, poses: torch.Tensor) -> torch.Tensor:
        """Robust energy at poses ``(N, 8)``, a float64 scalar."""
        ...

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to."""
        ...


class RelativePoseFactors(ABC):
    """Common machinery of a batch of E relative-pose edges with P matches each.

    Subclasses provide ``_residual(T_ij, edges)``: the residual ``(e, P, C)`` and its
    Jacobian ``(e, P, C, 7)`` w.r.t. a left perturbation of ``T_ij`` for a slice of edges.
    Matches that are invalid, whose confidence is not positive, or whose residual is not
    defined (see the subclasses) get zero weight.
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        q: torch.Tensor,
        valid: torch.Tensor,
        sigmas: Sequence[float],
        huber_k: float,
        chunk_matches: int,
        sigma_scale: torch.Tensor | None = None,
    ) -> None:
        name = type(self).__name__
        self.i = _edge_index(i, "i", name).to(q.device)
        self.j = _edge_index(j, "j", name).to(q.device)
        num_edges = self.i.shape[0]
        if self.j.shape != self.i.shape:
            raise InputError(
                f"{name}: i and j must have the same length, got {num_edges} and {self.j.shape[0]}"
            )
        if bool((self.i == self.j).any()):
            raise InputError(f"{name}: an edge connects a pose to itself (i == j)")
        self._max_pose_index = int(torch.maximum(self.i, self.j).max()) if num_edges else -1
        if q.ndim != 2 or q.shape[0] != num_edges:
            raise InputError(
                f"{name}: q must have shape (E, P) with E={num_edges}, got {tuple(q.shape)}"
            )
        if valid.shape != q.shape or valid.dtype != torch.bool:
            raise InputError(f"{name}: valid must be a bool tensor of shape {tuple(q.shape)}")
        for label, value in zip(("sigma", "huber_k"), (*sigmas, huber_k)):
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{name}: {label} must be a positive number, got {value}")
        if chunk_matches < 1:
            raise InputError(f"{name}: chunk_matches must be >= 1, got {chunk_matches}")
        # A match with a non-finite or non-positive confidence carries no information.
        if q.device.type == "cpu":
            self.valid, self.q = cpu_kernels.confident(valid, q)
        else:
            self.valid = valid & torch.isfinite(q) & (q > 0)
            self.q = torch.where(self.valid, q, torch.zeros_like(q))
        self.huber_k = float(huber_k)
        # (E, 1, C): per edge, so a noise given relative to the scene (sigma_scale) applies
        inv_sigmas = torch.tensor([1.0 / s for s in sigmas], dtype=q.dtype, device=q.device)
        self._inv_sigmas = inv_sigmas.expand(num_edges, 1, len(sigmas)).clone()
        if sigma_scale is not None:
            if sigma_scale.shape != (num_edges, len(sigmas)):
                raise InputError(
                    f"{name}: sigma_scale must have shape "
                    f"{(num_edges, len(sigmas))}, got {tuple(sigma_scale.shape)}"
                )
            if not bool((torch.isfinite(sigma_scale) & (sigma_scale > 0)).all()):
                raise InputError(f"{name}: sigma_scale must be positive and finite")
            self._inv_sigmas /= sigma_scale.to(q)[:, None, :]
        self._chunk_matches = chunk_matches
        self._edges_per_chunk = max(1, chunk_matches // max(1, q.shape[1]))
        self._edge_weight: torch.Tensor | None = None

    def weigh_edges(self, weight: torch.Tensor) -> None:
        """Multiply each edge's Gauss-Newton blocks and energy by ``weight (E,)`` (positive):
        an edge whose matches were thinned to a share of them stands for all of them
        (:meth:`~como3r.backend.global_graph.GlobalGraph.optimize`'s ``max_matches``). Its
        residuals and Huber weights are those of its own matches."""
        if weight.shape != self.i.shape or not bool((torch.isfinite(weight) & (weight > 0)).all()):
            raise InputError(
                f"{type(self).__name__}: edge weights must be {tuple(self.i.shape)} positive "
                "finite numbers"
            )
        self._edge_weight = weight.to(device=self.q.device, dtype=torch.float64)

    @abstractmethod
    def _residual(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Residual ``(e, P, C)``, Jacobian ``(e, P, C, 7)`` and, where the residual can
        degenerate at some poses, a ``(e, P)`` bool mask of the matches it is defined for."""

    @abstractmethod
    def _compiled_blocks(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``H = J^T W J`` ``(e, 7, 7)`` and ``g = J^T W e`` ``(e, 7)`` float64 in the tangent
        of ``T_ij`` ``(e, 8)`` by the compiled CPU loop (:mod:`como3r.optim.cpu_kernels`)."""

    @abstractmethod
    def _compiled_costs(self, T_ij: torch.Tensor, edges: slice) -> torch.Tensor:
        """Robust energy of each edge of a slice by the compiled CPU loop, ``(e,)`` float64."""

    def _error(self, T_ij: torch.Tensor, edges: slice) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Residual ``(e, P, C)`` and definedness mask without the Jacobian (cost evaluation);
        subclasses override it where the residual alone is cheaper."""
        e, _, defined = self._residual(T_ij, edges)
        return e, defined

    def _keep_valid_matches(self, *names: str) -> None:
        """Drop the matches that are invalid whatever the poses, packing each edge's valid
        matches to the front and padding to the largest valid count.

        An invalid match has zero square-root information, so it contributes nothing to the
        cost, the Hessian or the gradient (C-Eq. 5, 7): the problem is unchanged while every
        linearization touches only matches that count (a keyframe pair typically has a third
        to two thirds of its pixels unmatched).

        Args:
            names: the subclass's per-match ``(E, P, ...)`` attributes to compact with
                ``q`` and ``valid``.
        """
        E, P = self.q.shape
        if not (E and P):
            return
        # stable sort: valid matches first, in their original order (on CPU one compiled
        # pass instead of the count, the sort and the gathers)
        if self.valid.device.type == "cpu":
            order, kept = cpu_kernels.valid_first(self.valid)
            take: Callable[[torch.Tensor, torch.Tensor, int], torch.Tensor]
            take = cpu_kernels.take_matches
        else:
            kept = int(self.valid.sum(1).max())
            order = torch.sort((~self.valid).to(torch.uint8), dim=1, stable=True).indices
            take = _take_matches
        kept = max(1, kept)
        if kept == P:
            return
        for name in ("q", "valid", *names):
            setattr(self, name, take(getattr(self, name), order, kept))
        self._edges_per_chunk = max(1, self._chunk_matches // kept)

    @property
    def num_edges(self) -> int:
        """E, the number of edges."""
        return self.i.shape[0]

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to (-1 for an empty batch)."""
        return self._max_pose_index

    def whitened_residual(
        self, poses: torch.Tensor, edges: slice = slice(None)
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Whitened residual of a slice of edges at the given poses.

        Args:
            poses: ``(N, 8)`` poses ``T_WC``.
            edges: which edges.

        Returns:
            ``r = Sigma^-1/2 e`` ``(e, P, C)``, ``sqrt_info`` ``(e, P, C)``, the raw Jacobian
            ``J`` ``(e, P, C, 7)`` w.r.t. a left perturbation of ``T_ij``, and ``T_WC_i``
            ``(e, 8)``. ``r`` and ``sqrt_info`` are zero for unusable matches (invalid, or in
            the calibrated residual brought nearer camera i than
            ``cpu_loops.MIN_DEPTH_RATIO`` of their observed depth, behind it included).
        """
        T_WC_i, T_ij = self._relative_poses(poses, edges)
        e, J, defined = self._residual(T_ij.to(self.q.dtype), edges)
        # The stored inputs are finite (see finite_rows), so e and J are finite for finite
        # poses and a zero sqrt_info removes a match from every sum without masking J.
        sqrt_info = self._sqrt_info(edges, defined)
        return e * sqrt_info, sqrt_info, J, T_WC_i

    def _relative_poses(
        self, poses: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``T_WC_i`` and ``T_ij = T_WC_i^-1 T_WC_j`` (C-Eq. 13), ``(e, 8)`` each in the poses'
        dtype.

        The PyTorch path then runs the per-match work in the matches' own precision
        (``T_ij.to(q.dtype)``): promoting millions of float32 matches to float64 doubles the
        linearization's memory traffic, and the step tolerance (1e-4 of the scene depth) is
        far above float32's resolution. The compiled CPU loops compute each match in float64.
        """
        self._check_poses(poses)
        T_WC_i = poses[self.i[edges]]
        return T_WC_i, sim3_compose(sim3_inverse(T_WC_i), poses[self.j[edges]])

    def _runs_compiled(self, poses: torch.Tensor) -> bool:
        """CPU factors take the compiled loops, except for poses autograd differentiates."""
        return self.q.device.type == "cpu" and not poses.requires_grad

    def _sqrt_info(self, edges: slice, defined: torch.Tensor | None) -> torch.Tensor:
        """``Sigma^-1/2`` ``(e, P, C)`` of C-Eq. 7, zero for unusable matches."""
        ok = self.valid[edges] if defined is None else self.valid[edges] & defined
        return torch.sqrt(self.q[edges])[..., None] * self._inv_sigmas[edges] * ok[..., None]

    def linearize(self, poses: torch.Tensor) -> EdgeBlocks:
        """Per-edge Gauss-Newton blocks with Huber-IRLS weights at ``poses`` ``(N, 8)``.

        In the relative tangent of ``T_ij`` an edge gives ``H = J^T W J`` and ``g = J^T W e``
        with ``W = w(r) Sigma^-1`` per component. By C-Eq. 11 the endpoint Jacobians are
        ``J_i = -J Ad`` and ``J_j = J Ad`` with ``Ad = Ad(T_WC_i^-1)``, constant over the
        edge's matches, so the 7x7 edge blocks are projected once per edge instead of per
        match: ``H_jj = H_ii = Ad^T H Ad = -H_ij``, ``g_j = Ad^T g = -g_i``.
        """
        parts = [self._linearize_chunk(poses, chunk) for chunk in self.chunks(poses)]
        if not parts:
            return _empty_blocks(poses)
        return EdgeBlocks.cat(parts)

    def cost(self, poses: torch.Tensor) -> torch.Tensor:
        """Robust energy ``sum rho(r_c)`` of C-Eq. 2 / 5 at ``poses`` ``(N, 8)``, float64.

        ``rho`` is the Huber kernel with ``rho(r) = r^2/2`` inside the breakpoint, whose
        IRLS weight is exactly ``w(r) = rho'(r)/r = min(1, k/|r|)``.
        """
        return sum(
            (self._edge_costs(poses, chunk).sum() for chunk in self.chunks(poses)),
            torch.zeros((), dtype=torch.float64, device=poses.device),
        )

    def quadratic_model(self, poses: torch.Tensor) -> QuadraticEdges:
        """Each edge's robust energy as a quadratic in its relative pose at ``poses``
        ``(N, 8)``: the Gauss-Newton blocks of :meth:`linearize` before they are projected
        onto the endpoints, and each edge's energy (see :class:`QuadraticEdges`)."""
        T_ij: list[torch.Tensor] = []
        H_rel: list[torch.Tensor] = []
        g_rel: list[torch.Tensor] = []
        costs: list[torch.Tensor] = []
        for chunk in self.chunks(poses):
            for part, value in zip((T_ij, H_rel, g_rel), self.relative_blocks(poses, chunk)):
                part.append(value)
            costs.append(self._edge_costs(poses, chunk))
        return QuadraticEdges(
            self.i, self.j, torch.cat(T_ij), torch.cat(H_rel), torch.cat(g_rel), torch.cat(costs)
        )

    def relative_blocks(
        self, poses: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A slice of edges (at most a :meth:`chunks` slice) linearized in the tangent of
        their relative poses at ``poses`` ``(N, 8)``, before the projection onto the
        endpoints: ``T_ij`` ``(e, 8)``, ``H`` ``(e, 7, 7)`` and ``g`` ``(e, 7)``, float64."""
        H, g, _ = self._relative_blocks(poses, edges)
        T_ij = self._relative_poses(poses, edges)[1]
        return T_ij.to(torch.float64), H.to(torch.float64), g.to(torch.float64)

    def edge_costs(self, poses: torch.Tensor, edges: slice) -> torch.Tensor:
        """Robust energy of each edge of a slice (at most a :meth:`chunks` slice) at
        ``poses`` ``(N, 8)``, ``(e,)`` float64."""
        return self._edge_costs(poses, edges)

    def _edge_costs(self, poses: torch.Tensor, edges: slice) -> torch.Tensor:
        """Robust energy of each edge of a slice (times its weight), ``(e,)`` float64."""
        costs = self._unweighted_costs(poses, edges)
        return costs if self._edge_weight is None else costs * self._edge_weight[edges]

    def _unweighted_costs(self, poses: torch.Tensor, edges: slice) -> torch.Tensor:
        """Robust energy of each edge of a slice over its own matches, ``(e,)`` float64."""
        if self._runs_compiled(poses):
            return self._compiled_costs(self._relative_poses(poses, edges)[1], edges)
        e, defined = self._error(self._relative_poses(poses, edges)[1].to(self.q.dtype), edges)
        r = (e * self._sqrt_info(edges, defined)).abs()
        k = self.huber_k
        rho = torch.where(r <= k, 0.5 * r * r, k * (r - 0.5 * k))
        # per-match terms in the data dtype, summed in float64
        return rho.flatten(1).sum(1, dtype=torch.float64)

    def _linearize_chunk(self, poses: torch.Tensor, edges: slice) -> EdgeBlocks:
        H_rel, g_rel, T_WC_i = self._relative_blocks(poses, edges)
        return endpoint_blocks(self.i[edges], self.j[edges], H_rel, g_rel, T_WC_i)

    def _relative_blocks(
        self, poses: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``H = J^T W J`` ``(e, 7, 7)`` and ``g = J^T W e`` ``(e, 7)`` in the tangent of
        ``T_ij``, and ``T_WC_i`` ``(e, 8)``, for a slice of edges (times their weights): by
        the compiled loop on CPU, else by PyTorch."""
        if self._runs_compiled(poses):
            T_WC_i, T_ij = self._relative_poses(poses, edges)
            H, g = self._compiled_blocks(T_ij, edges)
        else:
            H, g, T_WC_i = self._vectorised_blocks(poses, edges)
        if self._edge_weight is not None:
            weight = self._edge_weight[edges].to(H)
            H, g = H * weight[:, None, None], g * weight[:, None]
        return H, g, T_WC_i

    def _vectorised_blocks(
        self, poses: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`_relative_blocks` in PyTorch from the generic Jacobian (any device)."""
        r, sqrt_info, J, T_WC_i = self.whitened_residual(poses, edges)
        # The IRLS weight is absorbed into the square-root information (C-Sec. A.1): with
        # s = sqrt_info and r = s e, H = J^T (w s^2) J and g = J^T (w s r) = J^T (w s^2) e.
        weight = huber_weight(r, self.huber_k) * sqrt_info
        num, P, C = r.shape
        # J^T as (7, C * P) per edge, matches innermost: free for the residuals'
        # component-major Jacobians (geometry.residuals._jacobian_buffer), so both products
        # below run over one long contiguous dimension
        J_T = J.permute(0, 3, 2, 1).reshape(num, 7, C * P)
        WJ_T = J_T * (weight * sqrt_info).transpose(1, 2).reshape(num, 1, C * P)
        H_rel = WJ_T @ J_T.transpose(1, 2)
        g_rel = torch.bmm(J_T, (weight * r).transpose(1, 2).reshape(num, C * P, 1))[..., 0]
        return H_rel, g_rel, T_WC_i

    def chunks(self, poses: torch.Tensor) -> list[slice]:
        """Slices of edges to linearize at once: all of them for the compiled loops (they
        hold no per-match temporaries), else ``chunk_matches`` matches' worth."""
        if self._runs_compiled(poses):
            return [slice(0, self.num_edges)] if self.num_edges else []
        step = self._edges_per_chunk
        return [slice(s, min(s + step, self.num_edges)) for s in range(0, self.num_edges, step)]

    def _check_poses(self, poses: torch.Tensor) -> None:
        if poses.ndim != 2 or poses.shape[1] != 8:
            raise InputError(
                f"{type(self).__name__}: poses must be (N, 8), got {tuple(poses.shape)}"
            )
        if self.max_pose_index >= poses.shape[0]:
            raise InputError(
                f"{type(self).__name__}: an edge refers to pose {self.max_pose_index} but only "
                f"{poses.shape[0]} poses are given"
            )


def endpoint_blocks(
    i: torch.Tensor, j: torch.Tensor, H_rel: torch.Tensor, g_rel: torch.Tensor, T_WC_i: torch.Tensor
) -> EdgeBlocks:
    """Endpoint blocks of edges from their blocks in the tangent of ``T_ij`` (C-Eq. 11).

    ``J_i = -J Ad`` and ``J_j = J Ad`` with ``Ad = Ad(T_WC_i^-1)``, constant over an edge's
    matches, so ``H_jj = H_ii = Ad^T H Ad = -H_ij`` and ``g_j = Ad^T g = -g_i``.

    Args:
        i, j: ``(E,)`` pose indices.
        H_rel: ``(E, 7, 7)``; g_rel: ``(E, 7)``: the blocks in the tangent of ``T_ij``.
        T_WC_i: ``(E, 8)`` poses of the edges' i endpoints (their dtype is the blocks').
    """
    H_rel, g_rel = H_rel.to(T_WC_i.dtype), g_rel.to(T_WC_i.dtype)
    Ad = sim3_adjoint(sim3_inverse(T_WC_i))
    Ad_T = Ad.transpose(1, 2)
    H_jj = Ad_T @ H_rel @ Ad
    H_jj = 0.5 * (H_jj + H_jj.transpose(1, 2))  # exactly symmetric, also in float32
    g_j = (Ad_T @ g_rel[..., None])[..., 0]
    return EdgeBlocks(i, j, H_jj, H_jj, -H_jj, -g_j, g_j)


class QuadraticEdges:
    """Edges whose robust energy is a quadratic in their relative pose (a Factor).

    Edge k was linearized at the relative pose ``T0_k``; at ``T_ij = Exp(delta) T0_k``
    (left perturbation, C-Sec. 3.2) its energy is taken as
    ``c_k + g_k^T delta + delta^T H_k delta / 2``, with the Gauss-Newton ``H_k = J^T W J``
    and ``g_k = J^T W e`` of its dense residuals (C-Eq. 5-8) at ``T0_k``, and the IRLS
    weights held at theirs. Its blocks at other poses are ``H_k`` and ``g_k + H_k delta``
    in the tangent of ``T_ij`` (the left Jacobian of ``delta`` taken as the identity: exact
    to first order in ``delta``), projected onto the endpoints as the dense edges' are.
    An edge costs 65 floats whatever its matches.

    Args:
        i, j: ``(E,)`` pose indices.
        T0: ``(E, 8)`` relative poses ``T_WC_i^-1 T_WC_j`` of the linearization.
        H: ``(E, 7, 7)``; g: ``(E, 7)``; c: ``(E,)`` float64 energies at ``T0``.
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        T0: torch.Tensor,
        H: torch.Tensor,
        g: torch.Tensor,
        c: torch.Tensor,
    ) -> None:
        self.i = _edge_index(i, "i", "QuadraticEdges")
        self.j = _edge_index(j, "j", "QuadraticEdges")
        self.T0, self.H, self.g, self.c = T0, H, g, c
        self._max_pose_index = int(torch.maximum(self.i, self.j).max()) if len(self.i) else -1

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to (-1 for none)."""
        return self._max_pose_index

    def motion(self, poses: torch.Tensor) -> torch.Tensor:
        """``delta`` ``(E, 7)`` = ``Log(T_ij T0^-1)`` at ``poses`` ``(N, 8)``, float64."""
        poses = poses.to(torch.float64)
        T_ij = sim3_compose(sim3_inverse(poses[self.i]), poses[self.j])
        return sim3_log(sim3_compose(T_ij, sim3_inverse(self.T0)))

    def linearize(self, poses: torch.Tensor) -> EdgeBlocks:
        """Per-edge blocks at ``poses`` ``(N, 8)`` (see the class docstring)."""
        delta = self.motion(poses)
        g_rel = self.g + (self.H @ delta[..., None])[..., 0]
        return endpoint_blocks(self.i, self.j, self.H, g_rel, poses[self.i])

    def cost(self, poses: torch.Tensor) -> torch.Tensor:
        """The quadratic energies' sum at ``poses`` ``(N, 8)``, a float64 scalar."""
        delta = self.motion(poses)
        quadratic = 0.5 * (delta[:, None, :] @ self.H @ delta[..., None])[:, 0, 0]
        return (self.c + (self.g * delta).sum(-1) + quadratic).sum()


def _edge_index(index: torch.Tensor, label: str, name: str) -> torch.Tensor:
    """Validate an ``(E,)`` pose index tensor and return it as int64."""
    if not isinstance(index, torch.Tensor) or index.ndim != 1:
        raise InputError(f"{name}: {label} must be a 1-D tensor of pose indices")
    if index.is_floating_point() or index.dtype == torch.bool:
        raise InputError(f"{name}: {label} must hold integer pose indices, got {index.dtype}")
    if index.numel() and int(index.min()) < 0:
        raise InputError(f"{name}: {label} holds a negative pose index")
    return index.to(torch.int64)


def _take_matches(value: torch.Tensor, order: torch.Tensor, kept: int) -> torch.Tensor:
    """``value`` ``(E, P, ...)`` at each edge's first ``kept`` matches of ``order``."""
    E = order.shape[0]
    index = order[:, :kept].reshape(E, kept, *(1,) * (value.ndim - 2))
    return torch.gather(value, 1, index.expand(E, kept, *value.shape[2:]))


def finite_rows(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``values`` ``(E, P, k)`` with the rows of invalid matches set to 1 if any of them is
    not finite: garbage behind the mask (NaN pointmap pixels) must not turn a zero weight
    into NaN. Without such garbage the input is kept as is (no copy)."""
    if (
        cpu_kernels.all_finite(values)
        if values.device.type == "cpu"
        else bool(torch.isfinite(values).all())
    ):
        return values
    return torch.where(valid[..., None], values, torch.ones_like(values))


def _empty_blocks(poses: torch.Tensor) -> EdgeBlocks:
    index = torch.zeros(0, dtype=torch.int64, device=poses.device)
    block = torch.zeros(0, 7, 7, dtype=poses.dtype, device=poses.device)
    vector = torch.zeros(0, 7, dtype=poses.dtype, device=poses.device)
    return EdgeBlocks(index, index, block, block, block, vector, vector)
