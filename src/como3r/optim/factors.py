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
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Protocol

import torch

import como3r.optim.cpu_kernels as cpu_kernels
from como3r.config import TrackingConfig
from como3r.errors import InputError
from como3r.geometry.lie import (
    sim3_act,
    sim3_adjoint,
    sim3_compose,
    sim3_inverse,
    sim3_log,
)
from como3r.geometry.residuals import (
    calibrated_residual,
    huber_weight,
    ray_range_error,
    ray_range_residual,
    ray_range_terms,
)
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
            ``cpu_kernels.MIN_DEPTH_RATIO`` of their observed depth, behind it included).
        """
        T_WC_i, T_ij = self._relative_poses(poses, edges)
        e, J, defined = self._residual(T_ij.to(self.q.dtype), edges)
        # The stored inputs are finite (see _finite_rows), so e and J are finite for finite
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

    def _edge_costs(self, poses: torch.Tensor, edges: slice) -> torch.Tensor:
        """Robust energy of each edge of a slice, ``(e,)`` float64."""
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
        ``T_ij``, and ``T_WC_i`` ``(e, 8)``, for a slice of edges: by the compiled loop on
        CPU, else by PyTorch."""
        if self._runs_compiled(poses):
            T_WC_i, T_ij = self._relative_poses(poses, edges)
            return (*self._compiled_blocks(T_ij, edges), T_WC_i)
        return self._vectorised_blocks(poses, edges)

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


class RayRangeFactors(RelativePoseFactors):
    """Ray-and-range factors of C-Eq. 6 (uncalibrated tracking, local and global BA).

    Args:
        i, j: ``(E,)`` pose indices of each edge; the residual depends on
            ``T_ij = T_WC_i^-1 T_WC_j``.
        X_i: ``(E, P, 3)`` canonical points of keyframe i at the matched pixels m, in
            camera i.
        X_j: ``(E, P, 3)`` canonical points of j at the matched pixels n, in camera j.
        q: ``(E, P)`` per-match confidence ``q_mn`` (C-Eq. 7).
        valid: ``(E, P)`` bool, which matches exist.
        sigma_ray, sigma_dist: ray and range noise (C-Tab. 3).
        huber_k: Huber breakpoint on whitened components.
        chunk_matches: how many matches to linearize at once (memory bound).
        range_scale: ``(E,)`` optional length that multiplies ``sigma_dist`` per edge
            (keyframe i's median range when ``sigma_dist`` is relative to the scene).
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        X_i: torch.Tensor,
        X_j: torch.Tensor,
        q: torch.Tensor,
        valid: torch.Tensor,
        sigma_ray: float = TrackingConfig.sigma_ray,
        sigma_dist: float = TrackingConfig.sigma_dist,
        huber_k: float = TrackingConfig.huber_k,
        chunk_matches: int = DEFAULT_CHUNK_MATCHES,
        range_scale: torch.Tensor | None = None,
    ) -> None:
        scale = None
        if range_scale is not None:
            if range_scale.shape != q.shape[:1]:
                raise InputError(
                    f"RayRangeFactors: range_scale must have shape "
                    f"({q.shape[0]},), got {tuple(range_scale.shape)}"
                )
            scale = torch.ones(q.shape[0], 4, dtype=q.dtype, device=q.device)
            scale[:, 3] = range_scale.to(q)
        super().__init__(
            i,
            j,
            q,
            valid,
            (sigma_ray,) * 3 + (sigma_dist,),
            huber_k,
            chunk_matches,
            sigma_scale=scale,
        )
        for label, X in (("X_i", X_i), ("X_j", X_j)):
            if X.shape != (*q.shape, 3):
                raise InputError(
                    f"RayRangeFactors: {label} must have shape "
                    f"{(*q.shape, 3)}, got {tuple(X.shape)}"
                )
        # A point at the camera centre has no ray (the geometry clamps its norm instead of
        # returning NaN), and Sim(3) maps only the centre to the centre, so this is static.
        self.valid = self.valid & _usable_points(X_i) & _usable_points(X_j)
        self.X_i = _finite_rows(X_i, self.valid)
        self.X_j = _finite_rows(X_j, self.valid)
        self._keep_valid_matches("X_i", "X_j")

    def _residual(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, None]:
        e, J = ray_range_residual(T_ij, self.X_j[edges], self.X_i[edges])
        return e, J, None

    def _error(self, T_ij: torch.Tensor, edges: slice) -> tuple[torch.Tensor, None]:
        return ray_range_error(T_ij, self.X_j[edges], self.X_i[edges]), None

    def _compiled_blocks(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return cpu_kernels.ray_range_blocks(
            T_ij,
            self.X_i[edges],
            self.X_j[edges],
            self.q[edges],
            self.valid[edges],
            self._inv_sigmas[edges, 0],
            self.huber_k,
        )

    def _compiled_costs(self, T_ij: torch.Tensor, edges: slice) -> torch.Tensor:
        return cpu_kernels.ray_range_costs(
            T_ij,
            self.X_i[edges],
            self.X_j[edges],
            self.q[edges],
            self.valid[edges],
            self._inv_sigmas[edges, 0],
            self.huber_k,
        )

    def _vectorised_blocks(
        self, poses: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``J^T W J`` and ``J^T W e`` of C-Eq. 6 summed in closed form, without ``J``.

        With ``x = T_ij X_j``, ``d = ||x||``, ``r = x / d`` the Jacobian rows are (C-Eq. 9-10,
        :func:`~como3r.geometry.residuals.ray_range_residual`) ``J_c = [(e_c - r_c r) / d,
        S_c, 0]`` for the ray components c = 0..2, with ``S = -[r]_x``, and
        ``J_3 = [r^T, 0, d]`` for the range. With per-component weights ``a_c`` (ray),
        ``b`` (range) and weighted residuals ``alpha_c``, ``beta`` (IRLS weight times
        information, C-Sec. A.1) the blocks of ``H = sum_c a_c J_c^T J_c + b J_3^T J_3`` are

            H_tt = diag(sum u) - M - M^T + sum (u . (r*r) + b) r r^T,  u = a / d^2,
                   M = sum (u * r) r^T
            H_tw = sum (diag(a) S - r v^T) / d,  v = S^T (a * r)
            H_ww = sum S^T diag(a) S,  H_ts = sum b d r,  H_ss = sum b d^2,  H_ws = 0
            g_t = sum ((alpha - (alpha . r) r) / d + beta r),  g_w = sum r x alpha,
            g_s = sum beta d

        so a match costs a few 3-vectors and 3x3 products instead of a ``(4, 7)`` Jacobian
        (the same sums as the generic path up to rounding; tests pin both to autograd).
        """
        T_WC_i, T_ij = self._relative_poses(poses, edges)
        d, r, e = ray_range_terms(T_ij.to(self.q.dtype), self.X_j[edges], self.X_i[edges])
        sqrt_info = self._sqrt_info(edges, None)
        whitened = e * sqrt_info
        weight = huber_weight(whitened, self.huber_k) * sqrt_info
        W, G = weight * sqrt_info, weight * whitened  # (e, P, 4): w s^2 and w s^2 e
        a, b = W[..., :3], W[..., 3]
        alpha, beta = G[..., :3], G[..., 3]
        inv_d = 1.0 / d
        r0, r1, r2 = r.unbind(-1)
        # products of the two other components of r, indexed by the missing one
        cross = torch.stack([r1 * r2, r0 * r2, r0 * r1], dim=-1)
        u = a * (inv_d * inv_d)[..., None]
        M = torch.einsum("epk,epl->ekl", u * r, r)
        N = torch.einsum("epk,epl->ekl", ((u * r * r).sum(-1) + b)[..., None] * r, r)
        H_tt = torch.diag_embed(u.sum(1)) - M - M.transpose(1, 2) + N
        # v = S^T (a * r): v_l = cross_l (a_{l+2} - a_{l+1}) (indices mod 3)
        v = cross * (a.roll(-2, dims=-1) - a.roll(-1, dims=-1))
        A = torch.einsum("epk,epl->ekl", a * inv_d[..., None], r)  # sum a_k r_l / d
        zero = torch.zeros_like(A[:, 0, 0])
        # (sum diag(a) S / d)_{kl} = sum a_k S_kl / d with S = -[r]_x
        aS = torch.stack(
            [
                torch.stack([zero, A[:, 0, 2], -A[:, 0, 1]], -1),
                torch.stack([-A[:, 1, 2], zero, A[:, 1, 0]], -1),
                torch.stack([A[:, 2, 1], -A[:, 2, 0], zero], -1),
            ],
            dim=1,
        )
        H_tw = aS - torch.einsum("epk,epl->ekl", r * inv_d[..., None], v)
        # S^T diag(a) S: diagonal sum_{c != l != k} a_c r_l^2, off-diagonal -a_m r_k r_l
        ar2 = torch.einsum("epc,epl->ecl", a, r * r)
        off = (a * cross).sum(1)
        H_ww = torch.stack(
            [
                torch.stack([ar2[:, 1, 2] + ar2[:, 2, 1], -off[:, 2], -off[:, 1]], -1),
                torch.stack([-off[:, 2], ar2[:, 0, 2] + ar2[:, 2, 0], -off[:, 0]], -1),
                torch.stack([-off[:, 1], -off[:, 0], ar2[:, 0, 1] + ar2[:, 1, 0]], -1),
            ],
            dim=1,
        )
        bd = b * d
        H_ts = (bd[..., None] * r).sum(1)
        num = H_tt.shape[0]
        H_rel = H_tt.new_zeros(num, 7, 7)
        H_rel[:, :3, :3] = H_tt
        H_rel[:, :3, 3:6] = H_tw
        H_rel[:, 3:6, :3] = H_tw.transpose(1, 2)
        H_rel[:, 3:6, 3:6] = H_ww
        H_rel[:, :3, 6] = H_ts
        H_rel[:, 6, :3] = H_ts
        H_rel[:, 6, 6] = (bd * d).sum(1)
        along = (alpha * r).sum(-1, keepdim=True)
        g_t = ((alpha - along * r) * inv_d[..., None] + beta[..., None] * r).sum(1)
        g_w = torch.linalg.cross(r, alpha, dim=-1).sum(1)
        g_rel = torch.cat([g_t, g_w, (beta * d).sum(1, keepdim=True)], dim=-1)
        return H_rel, g_rel, T_WC_i


class CalibratedFactors(RelativePoseFactors):
    """Pixel-reprojection and log-depth factors of C-Eq. 17 (known calibration, C-Sec. A.5).

    Args:
        i, j: ``(E,)`` pose indices of each edge.
        X_j: ``(E, P, 3)`` canonical points of j at the matched pixels n, in camera j.
        p_i: ``(E, P, 2)`` observed pixel coordinates m in image i.
        z_i: ``(E, P)`` depth ``[X_i]_3`` of keyframe i at pixel m (metres, > 0).
        K: ``(E, 3, 3)`` or ``(3, 3)`` intrinsics of camera i.
        q, valid: as in :class:`RayRangeFactors`.
        sigma_pixel, sigma_depth: pixel and log-depth noise (C-Tab. 3).
        huber_k, chunk_matches: as in :class:`RayRangeFactors`.
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        X_j: torch.Tensor,
        p_i: torch.Tensor,
        z_i: torch.Tensor,
        K: torch.Tensor,
        q: torch.Tensor,
        valid: torch.Tensor,
        sigma_pixel: float = TrackingConfig.sigma_pixel,
        sigma_depth: float = TrackingConfig.sigma_depth,
        huber_k: float = TrackingConfig.huber_k,
        chunk_matches: int = DEFAULT_CHUNK_MATCHES,
    ) -> None:
        super().__init__(
            i, j, q, valid, (sigma_pixel,) * 2 + (sigma_depth,), huber_k, chunk_matches
        )
        for label, value, shape in (
            ("X_j", X_j, (*q.shape, 3)),
            ("p_i", p_i, (*q.shape, 2)),
            ("z_i", z_i, tuple(q.shape)),
        ):
            if value.shape != shape:
                raise InputError(
                    f"CalibratedFactors: {label} must have shape {shape}, got {tuple(value.shape)}"
                )
        if K.shape == (3, 3):
            K = K.expand(q.shape[0], 3, 3)
        if K.shape != (q.shape[0], 3, 3):
            raise InputError(
                f"CalibratedFactors: K must have shape (3, 3) or "
                f"({q.shape[0]}, 3, 3), got {tuple(K.shape)}"
            )
        if z_i.device.type == "cpu":
            observed = cpu_kernels.observed(p_i, z_i)
        else:
            observed = torch.isfinite(p_i).all(-1) & torch.isfinite(z_i) & (z_i > 0)
        self.valid = self.valid & observed & _usable_points(X_j)
        self.X_j = _finite_rows(X_j, self.valid)
        self.p_i = _finite_rows(p_i, self.valid)
        self.z_i = _finite_rows(z_i[..., None], self.valid)[..., 0]
        self.K = K
        self._keep_valid_matches("X_j", "p_i", "z_i")

    def _residual(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        X_j = self.X_j[edges]
        e, J = calibrated_residual(T_ij, X_j, self.p_i[edges], self.z_i[edges], self.K[edges])
        # Pi_K and log z exist only in front of camera i, and their Jacobian grows as 1 / z^2
        # near it: a match counts where the transformed depth is at least MIN_DEPTH_RATIO of
        # the observed one (C-Eq. 17-18), recomputed at every iterate.
        z = sim3_act(T_ij[:, None, :], X_j)[..., 2]
        return e, J, z > cpu_kernels.MIN_DEPTH_RATIO * self.z_i[edges].to(z.dtype)

    def _compiled_blocks(
        self, T_ij: torch.Tensor, edges: slice
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return cpu_kernels.calibrated_blocks(
            T_ij,
            self.K[edges],
            self.X_j[edges],
            self.p_i[edges],
            self.z_i[edges],
            self.q[edges],
            self.valid[edges],
            self._inv_sigmas[edges, 0],
            self.huber_k,
        )

    def _compiled_costs(self, T_ij: torch.Tensor, edges: slice) -> torch.Tensor:
        return cpu_kernels.calibrated_costs(
            T_ij,
            self.K[edges],
            self.X_j[edges],
            self.p_i[edges],
            self.z_i[edges],
            self.q[edges],
            self.valid[edges],
            self._inv_sigmas[edges, 0],
            self.huber_k,
        )


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


def _usable_points(X: torch.Tensor) -> torch.Tensor:
    """``(E, P)`` bool: finite points away from the camera centre."""
    if X.device.type == "cpu":
        return cpu_kernels.usable_points(X)
    return torch.isfinite(X).all(-1) & (torch.linalg.vector_norm(X, dim=-1) > 0)


def _finite_rows(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
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
