"""Per-camera focal lengths as variables of the global Sim(3) BA: values and factors.

Self-calibrated agents (:mod:`como3r.frontend.focal`) each put their keyframes on the rays of
their own estimate ``K_a`` (C-Eq. 16), and the global BA compares them through the
pixel-and-log-depth residual of the known-calibration variant (C-Eq. 17-18; C-Sec. A.5). The
paper runs that residual with a KNOWN ``K``; here each camera ``a`` (an agent) gets a log
focal correction ``phi_a``: its keyframes' focal lengths ``fx, fy`` become ``f exp(phi_a)``
and their pointmaps ``X = (x, y, z)`` become ``(x exp(-phi_a), y exp(-phi_a), z)``
(:func:`~como3r.geometry.camera.rescale_focal`: every point keeps its pixel and depth). For
an edge (i, j) with ``x = T_ij X_j`` (C-Eq. 13) the residual's derivatives are then

* ``d e / d phi_i``: ``(fx x / z, fy y / z, 0)``: camera i's focal acts only in ``Pi_K``
  of C-Eq. 17 (the observed pixel ``p_i`` and depth ``z_i`` stay);
* ``d e / d phi_j``: ``(d e / d x) s R (-X_j.x, -X_j.y, 0)``, where ``d e / d x`` is the
  translation block of C-Eq. 18 composed with C-Eq. 9 (a left perturbation's translation
  moves ``x`` by itself);

summed when both keyframes are one camera's. The robust weights are those of C-Eq. 7-8.

:class:`FocalValues` holds the poses and the corrections (GTSAM's ``Values``),
:class:`FocalEdgeFactors` and :class:`FocalPrior` linearize into a :class:`FocalSystem`,
and :mod:`como3r.backend.focal_solver` solves it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import TrackingConfig
from como3r.errors import InputError
from como3r.frontend.graph import Edge, Pointmap, build_factors
from como3r.geometry.camera import rescale_focal
from como3r.geometry.lie import quat_to_matrix, sim3_adjoint, sim3_inverse
from como3r.geometry.residuals import huber_weight
from como3r.optim.cpu_loops import MIN_DEPTH_RATIO
from como3r.optim.factors import endpoint_blocks
from como3r.optim.match_factors import CalibratedFactors
from como3r.optim.system import BlockSystem, assemble
from como3r.optim.values import PoseValues

#: Matches whose focal terms are formed at once (bounds the per-match temporaries).
CHUNK_MATCHES = 1 << 18

#: Edges per factor batch (a batch pads to its largest edge; edges sorted by match count).
EDGES_PER_BATCH = 8


@dataclass(frozen=True, eq=False)
class FocalValues:
    """Poses and per-camera log focal corrections of a joint solve.

    Attributes:
        poses: the keyframes' Sim(3) poses and which are pinned.
        log_focal: ``(A,)`` float64 correction ``phi_a`` of each camera's focal length,
            relative to the focal length its keyframes hold.
        held: ``(A,)`` bool, cameras whose focal length stays (a frozen map's).
    """

    poses: PoseValues
    log_focal: Tensor
    held: Tensor

    def __post_init__(self) -> None:
        if self.log_focal.ndim != 1 or self.held.shape != self.log_focal.shape:
            raise InputError(
                f"FocalValues: log_focal and held must be (A,) tensors, got "
                f"{tuple(self.log_focal.shape)} and {tuple(self.held.shape)}"
            )

    @property
    def num_cameras(self) -> int:
        """A, the number of cameras."""
        return int(self.log_focal.shape[0])

    def retract(self, tau: Tensor, delta: Tensor) -> FocalValues:
        """Poses moved by the tangent step ``tau (N, 7)`` (C-Eq. 25), free corrections by
        ``delta (A,)``."""
        moved = self.log_focal + torch.where(self.held, torch.zeros_like(delta), delta)
        return FocalValues(self.poses.retract(tau), moved, self.held)


@dataclass(frozen=True, eq=False)
class FocalSystem:
    """The normal equations of a joint pose and focal solve.

    Attributes:
        poses: the pose-pose blocks and pose gradient (:class:`BlockSystem`).
        H_pf: ``(N, 7, A)`` float64 pose-focal coupling.
        H_ff: ``(A, A)`` float64 focal-focal block.
        g_f: ``(A,)`` float64 focal gradient.
    """

    poses: BlockSystem
    H_pf: Tensor
    H_ff: Tensor
    g_f: Tensor


@dataclass(frozen=True)
class _Pointmap:
    """A keyframe's pointmap and intrinsics at a trial focal length (what a factor reads)."""

    X_hat: Tensor
    K: Tensor | None


class FocalEdgeFactors:
    """C-Eq. 17 edges whose two cameras' focal lengths are variables (module docstring).

    Args:
        edges: directed edges between keys (global keyframe indices).
        keyframe: maps a key to its keyframe (pointmap ``X_hat`` and intrinsics ``K`` at the
            focal length the correction is relative to).
        row: maps a key to its row in the poses.
        camera: maps a key to its camera's column in ``log_focal``.
        tracking: noise model and Huber breakpoint (C-Eq. 7-8, C-Tab. 3 ``sigma_p``,
            ``sigma_z``).

    Raises:
        InputError: no edges, or a keyframe without intrinsics.
    """

    def __init__(
        self,
        edges: Sequence[Edge],
        keyframe: Callable[[int], Pointmap],
        row: Callable[[int], int],
        camera: Callable[[int], int],
        tracking: TrackingConfig,
    ) -> None:
        if not edges:
            raise InputError("FocalEdgeFactors: no edges")
        self._keyframe = keyframe
        self._row, self._camera, self.tracking = row, camera, tracking
        keys = sorted({k for e in edges for k in (e.i, e.j)})
        for key in keys:
            if keyframe(key).K is None:
                raise InputError(
                    f"FocalEdgeFactors: keyframe {key} has no intrinsics (a focal length is "
                    "estimated only for calibrated or self-calibrated keyframes)"
                )
        order = sorted(edges, key=lambda e: int(e.matches.valid.sum()))
        self.batches = [
            order[s : s + EDGES_PER_BATCH] for s in range(0, len(order), EDGES_PER_BATCH)
        ]

    def _at(self, log_focal: Tensor) -> Callable[[int], _Pointmap]:
        """The keyframe accessor at the corrections ``log_focal (A,)``."""
        cache: dict[int, _Pointmap] = {}

        def pointmap(key: int) -> _Pointmap:
            if key not in cache:
                kf = self._keyframe(key)
                K = kf.K
                assert K is not None  # checked at construction
                X, K = rescale_focal(kf.X_hat, K, float(log_focal[self._camera(key)]))
                cache[key] = _Pointmap(X, K)
            return cache[key]

        return pointmap

    def linearize(self, values: FocalValues) -> FocalSystem:
        """The joint normal equations at ``values`` (Huber-IRLS weights at its residuals)."""
        poses = values.poses.poses
        N, A = poses.shape[0], values.num_cameras
        pointmap = self._at(values.log_focal)
        blocks = []
        H_pf = torch.zeros(N * A, 7, dtype=torch.float64, device=poses.device)
        H_ff = torch.zeros(A, A, dtype=torch.float64, device=poses.device)
        g_f = torch.zeros(A, dtype=torch.float64, device=poses.device)
        for batch in self.batches:
            factors = build_factors(batch, pointmap, self._row, self.tracking)
            if not isinstance(factors, CalibratedFactors):
                raise InputError("FocalEdgeFactors: the edges did not give C-Eq. 17 factors")
            cameras_i = torch.tensor([self._camera(e.i) for e in batch], device=poses.device)
            cameras_j = torch.tensor([self._camera(e.j) for e in batch], device=poses.device)
            step = max(1, CHUNK_MATCHES // max(1, factors.q.shape[1]))
            for start in range(0, factors.num_edges, step):
                edges = slice(start, min(start + step, factors.num_edges))
                H9, g9, T_WC_i = edge_blocks(factors, poses, edges, self.tracking)
                i, j = factors.i[edges], factors.j[edges]
                blocks.append(endpoint_blocks(i, j, H9[:, :7, :7], g9[:, :7], T_WC_i))
                c = torch.stack([cameras_i[edges], cameras_j[edges]], dim=1)  # (e, 2)
                # pose-focal coupling: J_i = -J Ad, J_j = J Ad (C-Eq. 11)
                Ad_T = sim3_adjoint(sim3_inverse(T_WC_i)).transpose(1, 2)
                coupling = Ad_T @ H9[:, :7, 7:]  # (e, 7, 2)
                for side in range(2):
                    H_pf.index_add_(0, i * A + c[:, side], -coupling[:, :, side])
                    H_pf.index_add_(0, j * A + c[:, side], coupling[:, :, side])
                    g_f.index_add_(0, c[:, side], g9[:, 7 + side])
                    for other in range(2):
                        H_ff.index_put_(
                            (c[:, side], c[:, other]), H9[:, 7 + side, 7 + other], accumulate=True
                        )
        system = assemble(N, blocks)
        return FocalSystem(system, H_pf.reshape(N, A, 7).transpose(1, 2), H_ff, g_f)


def edge_blocks(
    factors: CalibratedFactors, poses: Tensor, edges: slice, tracking: TrackingConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """Gauss-Newton blocks of a slice of C-Eq. 17 edges in ``(T_ij, phi_i, phi_j)``.

    The pose block is the factors' own (``relative_blocks``: the compiled loop on CPU). The
    focal rows are summed here from ``D = d e / d x`` per match (C-Eq. 18 and the log-depth
    row ``(0, 0, 1/z)``): with ``J_T = D [I, -[x]_x, x]`` (C-Eq. 9) the coupling of a
    focal column ``j_f`` is ``J_T^T W j_f = (m, x cross m, x . m)``, ``m = D^T W j_f``, so no
    per-match ``(3, 7)`` Jacobian is formed.

    Args:
        factors: the edges' factors at the current focal lengths.
        poses: ``(N, 8)`` poses.
        edges: which edges.
        tracking: the noise model the factors were built with (``sigma_pixel``,
            ``sigma_depth``).

    Returns:
        ``H (e, 9, 9)`` and ``g (e, 9)`` float64 (the first 7 rows in the left tangent of
        ``T_ij``, then camera i's and camera j's log focal) and ``T_WC_i (e, 8)``.
    """
    T_ij64, H_T, g_T = factors.relative_blocks(poses, edges)
    T_WC_i = poses[factors.i[edges]]
    X_j = factors.X_j[edges]
    dtype = X_j.dtype  # the pointmaps' precision, as the factors' own PyTorch path
    T_ij = T_ij64.to(dtype)
    R = quat_to_matrix(T_ij[:, 3:7]) * T_ij[:, 7, None, None]  # (e, 3, 3): s R
    x = X_j @ R.transpose(1, 2) + T_ij[:, None, :3]  # (e, P, 3) in camera i
    K = factors.K[edges].to(dtype)
    fx, skew_, cx = K[:, None, 0, 0], K[:, None, 0, 1], K[:, None, 0, 2]
    fy, cy = K[:, None, 1, 1], K[:, None, 1, 2]
    z_i = factors.z_i[edges].to(dtype)
    usable = factors.valid[edges] & (x[..., 2] > MIN_DEPTH_RATIO * z_i)
    # padded and unusable matches hold anything (zero depths): they get zero weight below
    z = torch.where(usable, x[..., 2], torch.ones_like(z_i))
    z_i = torch.where(usable, z_i, torch.ones_like(z_i))
    inv_z = 1.0 / z
    x0, x1 = x[..., 0] * inv_z, x[..., 1] * inv_z
    u, v = fx * x0 + skew_ * x1 + cx, fy * x1 + cy
    p_i = factors.p_i[edges].to(dtype)
    e = torch.stack([u - p_i[..., 0], v - p_i[..., 1], z.log() - z_i.log()], dim=-1)
    e = torch.where(usable[..., None], e, torch.zeros_like(e))
    inv_sigma = torch.tensor(
        [1 / tracking.sigma_pixel, 1 / tracking.sigma_pixel, 1 / tracking.sigma_depth],
        dtype=dtype,
        device=e.device,
    )
    sqrt_info = (factors.q[edges].to(dtype).clamp_min(0).sqrt() * usable)[..., None] * inv_sigma
    r = e * sqrt_info
    weight = huber_weight(r, factors.huber_k) * sqrt_info
    W, G = weight * sqrt_info, weight * r  # (e, P, 3)
    # rows of D = d e / d x: (fx, skew, cx - u) / z, (0, fy, cy - v) / z, (0, 0, 1) / z,
    # written out per component (a stacked (P, 3, 3) D costs more than the arithmetic)
    du, dv = (cx - u) * inv_z, (cy - v) * inv_z
    # d e / d phi_i = (fx x / z, fy y / z, 0): camera i's focal in Pi_K
    J_i = (fx * x0, fy * x1, torch.zeros_like(x0))
    # d e / d phi_j = D s R (-X_j.x, -X_j.y, 0)
    dx = -(X_j[..., :2] @ R[:, :, :2].transpose(1, 2))
    d0, d1, d2 = dx.unbind(-1)
    J_j = (
        (fx * d0 + skew_ * d1) * inv_z + du * d2,
        fy * d1 * inv_z + dv * d2,
        d2 * inv_z,
    )
    w0, w1, w2 = W.unbind(-1)
    X0, X1, X2 = x.unbind(-1)
    rows = []
    for jf in (J_i, J_j):
        t0, t1, t2 = w0 * jf[0], w1 * jf[1], w2 * jf[2]
        m = torch.stack(
            [fx * t0 * inv_z, (skew_ * t0 + fy * t1) * inv_z, du * t0 + dv * t1 + t2 * inv_z], -1
        )
        m0, m1, m2 = m.unbind(-1)
        cross = torch.stack([X1 * m2 - X2 * m1, X2 * m0 - X0 * m2, X0 * m1 - X1 * m0], -1)
        rows.append(torch.cat([m, cross, (x * m).sum(-1, keepdim=True)], -1).sum(1))
    H_Tf = torch.stack(rows, dim=1)  # (e, 2, 7): J_T^T W j_f = (m, x cross m, x . m)
    J_f = torch.stack([torch.stack(J_i, -1), torch.stack(J_j, -1)], dim=-1)  # (e, P, 3, 2)
    WJ = (W[..., None] * J_f).flatten(1, 2)
    H_ff = WJ.transpose(1, 2) @ J_f.flatten(1, 2)
    g_f = (J_f.flatten(1, 2).transpose(1, 2) @ G.flatten(1)[..., None])[..., 0]
    num = H_T.shape[0]
    H = H_T.new_zeros(num, 9, 9)
    H[:, :7, :7] = H_T
    H[:, 7:, :7] = H_Tf.double()
    H[:, :7, 7:] = H_Tf.double().transpose(1, 2)
    H[:, 7:, 7:] = H_ff.double()
    g = torch.cat([g_T, g_f.double()], dim=-1)
    return H, g, T_WC_i


@dataclass(frozen=True)
class FocalPrior:
    """A Gaussian prior ``phi_a ~ N(centre_a, sigma^2)`` on each free camera's correction:
    what an agent's own self-calibration knows. It anchors the directions the edges leave
    open (a common focal scale under nearly translational motion, where a wider field of view
    and a shorter baseline give the same pixels) and ties a camera seen by few matches."""

    centre: Tensor
    sigma: float

    def __post_init__(self) -> None:
        if not self.sigma > 0:
            raise InputError(f"FocalPrior: sigma must be > 0, got {self.sigma}")

    def add_to(self, system: FocalSystem, values: FocalValues) -> FocalSystem:
        """``system`` with the prior's information and gradient added at ``values``."""
        info = 1.0 / self.sigma**2
        eye = torch.eye(values.num_cameras, dtype=torch.float64, device=system.H_ff.device)
        g = info * (values.log_focal - self.centre.to(values.log_focal))
        return FocalSystem(system.poses, system.H_pf, system.H_ff + info * eye, system.g_f + g)
