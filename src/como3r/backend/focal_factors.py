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

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.config import TrackingConfig
from como3r.errors import InputError
from como3r.frontend.graph import Edge, Pointmap, build_factors, count_batches
from como3r.geometry.lie import quat_to_matrix, sim3_adjoint, sim3_compose, sim3_inverse
from como3r.geometry.residuals import huber_weight
from como3r.optim.factors import endpoint_blocks
from como3r.optim.focal_kernels import focal_blocks
from como3r.optim.match_factors import CalibratedFactors
from como3r.optim.system import BlockSystem, assemble
from como3r.optim.values import PoseValues

#: Matches whose focal terms are formed at once (bounds the per-match temporaries).
CHUNK_MATCHES = 1 << 18


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


class FocalEdgeFactors:
    """C-Eq. 17 edges whose two cameras' focal lengths are variables (module docstring).

    The edges' dense factors are built once, on the pointmaps and intrinsics the keyframes
    hold (the corrections are relative to them), and kept for the solve, as the pose BA
    keeps its own (:class:`~como3r.optim.relinearization.ThresholdRelinearized`): a trial
    correction is a per-edge factor on camera i's ``fx, fy`` and on the x and y of camera
    j's points (:func:`~como3r.geometry.camera.rescale_focal`, every point keeps its pixel
    and depth), so no keyframe is read, and no batch packed, again.

    Args:
        edges: directed edges between keys (global keyframe indices).
        keyframe: maps a key to its keyframe (pointmap ``X_hat`` and intrinsics ``K`` at the
            focal length the correction is relative to).
        row: maps a key to its row in the poses.
        camera: maps a key to its camera's column in ``log_focal``.
        tracking: noise model and Huber breakpoint (C-Eq. 7-8, C-Tab. 3 ``sigma_p``,
            ``sigma_z``).
        compiled: CPU factors take the compiled loop (:func:`compiled_edge_blocks`); False:
            the PyTorch path (:func:`edge_blocks`) on every device (tests, benchmarks).
        max_matches: an edge with more valid matches is built over an even subset of about
            this many, its blocks weighed by the share left out
            (:func:`~como3r.frontend.graph.thinned`); 0: every match.

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
        compiled: bool = True,
        max_matches: int = 0,
    ) -> None:
        if not edges:
            raise InputError("FocalEdgeFactors: no edges")
        self.tracking, self.compiled = tracking, compiled
        keys = sorted({k for e in edges for k in (e.i, e.j)})
        for key in keys:
            if keyframe(key).K is None:
                raise InputError(
                    f"FocalEdgeFactors: keyframe {key} has no intrinsics (a focal length is "
                    "estimated only for calibrated or self-calibrated keyframes)"
                )
        self.batches: list[_Batch] = []
        for _, batch, weights in count_batches(edges, max_matches):
            factors = build_factors(batch, keyframe, row, tracking)
            if not isinstance(factors, CalibratedFactors):
                raise InputError("FocalEdgeFactors: the edges did not give C-Eq. 17 factors")
            device = factors.q.device
            self.batches.append(
                _Batch(
                    factors,
                    torch.tensor([camera(e.i) for e in batch], device=device),
                    torch.tensor([camera(e.j) for e in batch], device=device),
                    None if weights is None else weights.to(device),
                )
            )

    def linearize(self, values: FocalValues) -> FocalSystem:
        """The joint normal equations at ``values`` (Huber-IRLS weights at its residuals)."""
        poses = values.poses.poses
        N, A = poses.shape[0], values.num_cameras
        log_focal = values.log_focal.to(poses.device)
        blocks = []
        H_pf = torch.zeros(N * A, 7, dtype=torch.float64, device=poses.device)
        H_ff = torch.zeros(A, A, dtype=torch.float64, device=poses.device)
        g_f = torch.zeros(A, dtype=torch.float64, device=poses.device)
        for batch in self.batches:
            factors = batch.factors
            scale_i, scale_j = log_focal[batch.camera_i].exp(), (-log_focal[batch.camera_j]).exp()
            if self.compiled and factors.q.device.type == "cpu" and not poses.requires_grad:
                parts = [compiled_edge_blocks(factors, poses, scale_i, scale_j, self.tracking)]
                slices = [slice(0, factors.num_edges)]
            else:
                moved = rescaled(factors, scale_i, scale_j)
                step = max(1, CHUNK_MATCHES // max(1, factors.q.shape[1]))
                slices = [
                    slice(s, min(s + step, factors.num_edges))
                    for s in range(0, factors.num_edges, step)
                ]
                parts = [edge_blocks(moved, poses, edges, self.tracking) for edges in slices]
            for edges, (H9, g9, T_WC_i) in zip(slices, parts):
                if batch.weight is not None:
                    H9 = H9 * batch.weight[edges, None, None].to(H9)
                    g9 = g9 * batch.weight[edges, None].to(g9)
                i, j = factors.i[edges], factors.j[edges]
                blocks.append(endpoint_blocks(i, j, H9[:, :7, :7], g9[:, :7], T_WC_i))
                c = torch.stack([batch.camera_i[edges], batch.camera_j[edges]], dim=1)  # (e, 2)
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


@dataclass(frozen=True)
class _Batch:
    """A factor batch of the solve, its edges' cameras ``(e,)`` (columns of
    ``log_focal``) and weights ``(e,)`` (thinned edges; None: all 1)."""

    factors: CalibratedFactors
    camera_i: Tensor
    camera_j: Tensor
    weight: Tensor | None = None


def rescaled(factors: CalibratedFactors, scale_i: Tensor, scale_j: Tensor) -> CalibratedFactors:
    """The factors at trial focal corrections: ``fx, fy`` of camera i times ``scale_i (e,)``
    (``exp(phi_i)``), x and y of camera j's points times ``scale_j (e,)`` (``exp(-phi_j)``);
    the observed pixels and depths stay (:func:`~como3r.geometry.camera.rescale_focal`). A
    shallow copy: the other per-match arrays are shared."""
    moved = copy.copy(factors)
    X_j = factors.X_j
    moved.X_j = torch.cat([X_j[..., :2] * scale_j.to(X_j)[:, None, None], X_j[..., 2:]], dim=-1)
    K = factors.K.clone()
    K[:, 0, 0] *= scale_i.to(K)
    K[:, 1, 1] *= scale_i.to(K)
    moved.K = K
    return moved


def compiled_edge_blocks(
    factors: CalibratedFactors,
    poses: Tensor,
    scale_i: Tensor,
    scale_j: Tensor,
    tracking: TrackingConfig,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`edge_blocks` of all the factors' edges at trial corrections (as
    :func:`rescaled`) by the compiled CPU loop (:mod:`como3r.optim.focal_kernels`)."""
    T_WC_i = poses[factors.i]
    T_ij = sim3_compose(sim3_inverse(T_WC_i), poses[factors.j])
    H, g = focal_blocks(
        T_ij,
        factors.K,
        scale_i,
        scale_j,
        factors.X_j,
        factors.p_i,
        factors.z_i,
        factors.q,
        factors.valid,
        (1 / tracking.sigma_pixel, 1 / tracking.sigma_pixel, 1 / tracking.sigma_depth),
        factors.huber_k,
    )
    return H.to(poses.device), g.to(poses.device), T_WC_i


def edge_blocks(
    factors: CalibratedFactors, poses: Tensor, edges: slice, tracking: TrackingConfig
) -> tuple[Tensor, Tensor, Tensor]:
    """Gauss-Newton blocks of a slice of C-Eq. 17 edges in ``(T_ij, phi_i, phi_j)``, in
    PyTorch (any device).

    The residual, its usable-depth mask, its Jacobian in ``T_ij`` and the Huber weights are
    the factors' own (:meth:`~como3r.optim.factors.RelativePoseFactors.whitened_residual`,
    :func:`~como3r.geometry.residuals.calibrated_residual`); two focal columns are added to
    the Jacobian: with ``D = d e / d x`` its first three columns (C-Eq. 9) and ``x = T_ij
    X_j = (x, y, z)``, ``d e / d phi_i = (fx x / z, fy y / z, 0)`` (``x / z`` and ``y / z``
    are the log-depth row's rotation entries ``-J[2, 4]`` and ``J[2, 3]``) and ``d e / d
    phi_j = D s R (-X_j.x, -X_j.y, 0)``.

    Args:
        factors: the edges' factors at the trial focal lengths (:func:`rescaled`).
        poses: ``(N, 8)`` poses.
        edges: which edges.
        tracking: the noise model the factors were built with (its Huber breakpoint).

    Returns:
        ``H (e, 9, 9)`` and ``g (e, 9)`` float64 (the first 7 rows in the left tangent of
        ``T_ij``, then camera i's and camera j's log focal) and ``T_WC_i (e, 8)``.
    """
    r, sqrt_info, J, T_WC_i = factors.whitened_residual(poses, edges)
    X_j = factors.X_j[edges]
    dtype = X_j.dtype  # the pointmaps' precision, as the factors' own PyTorch path
    T_ij = sim3_compose(sim3_inverse(T_WC_i), poses[factors.j[edges]]).to(dtype)
    sR = quat_to_matrix(T_ij[:, 3:7]) * T_ij[:, 7, None, None]  # (e, 3, 3)
    K = factors.K[edges].to(dtype)
    fx, fy = K[:, None, 0, 0], K[:, None, 1, 1]
    n0, n1 = -J[..., 2, 4], J[..., 2, 3]  # x / z and y / z
    J_i = torch.stack([fx * n0, fy * n1, torch.zeros_like(n0)], dim=-1)  # (e, P, 3)
    d = -(X_j[..., :2] @ sR[:, :, :2].transpose(1, 2))  # (e, P, 3): s R (-X.x, -X.y, 0)
    J_j = (J[..., :3] @ d[..., None])[..., 0]
    J9 = torch.cat([J, J_i[..., None], J_j[..., None]], dim=-1).flatten(1, 2)  # (e, 3P, 9)
    weight = huber_weight(r, tracking.huber_k) * sqrt_info
    W, G = (weight * sqrt_info).flatten(1), (weight * r).flatten(1)  # (e, 3P)
    H = (J9 * W[..., None]).transpose(1, 2) @ J9
    g = (J9.transpose(1, 2) @ G[..., None])[..., 0]
    return H.double(), g.double(), T_WC_i


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
