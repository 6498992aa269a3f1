"""The two residual models of a match as factor batches: ray and range (C-Eq. 6, the
uncalibrated default) and pixel and log-depth (C-Eq. 17, calibrated).

Both are :class:`~como3r.optim.factors.RelativePoseFactors`: the batch layout, chunking,
robust weights and linearization are there; here are what each residual reads, its
whitening and its compiled CPU kernels (:mod:`como3r.optim.cpu_kernels`).
"""

from __future__ import annotations

import torch

import como3r.optim.cpu_kernels as cpu_kernels
from como3r.config import TrackingConfig
from como3r.errors import InputError
from como3r.geometry.lie import sim3_act
from como3r.geometry.residuals import (
    calibrated_residual,
    huber_weight,
    ray_range_error,
    ray_range_residual,
    ray_range_terms,
)
from como3r.optim.cpu_loops import MIN_DEPTH_RATIO
from como3r.optim.factors import DEFAULT_CHUNK_MATCHES, RelativePoseFactors, finite_rows


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
        self.X_i = finite_rows(X_i, self.valid)
        self.X_j = finite_rows(X_j, self.valid)
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
        self.X_j = finite_rows(X_j, self.valid)
        self.p_i = finite_rows(p_i, self.valid)
        self.z_i = finite_rows(z_i[..., None], self.valid)[..., 0]
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
        return e, J, z > MIN_DEPTH_RATIO * self.z_i[edges].to(z.dtype)

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


def _usable_points(X: torch.Tensor) -> torch.Tensor:
    """``(E, P)`` bool: finite points away from the camera centre."""
    if X.device.type == "cpu":
        return cpu_kernels.usable_points(X)
    return torch.isfinite(X).all(-1) & (torch.linalg.vector_norm(X, dim=-1) > 0)
