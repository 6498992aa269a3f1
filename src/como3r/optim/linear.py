"""The damped solution of a pose solve's block normal equations (C-Eq. 25).

Factors linearize into per-edge 7x7 blocks that :func:`como3r.optim.system.assemble`
scatter-adds into the global block system (:class:`~como3r.optim.system.BlockSystem`)
over N poses; :func:`solve` solves

    (H + lambda diag(H) + eps_r I) tau = -g

over the free poses with the Tikhonov escalation ``eps_r = eps_0 * 100^r``, r = 0..R-1 of
C-Sec. B.2, returning a zero step and ``SolveStatus.FAILED`` when every attempt fails.
Four interchangeable backends: a dense Cholesky in torch, a sparse symmetric LU in scipy,
and preconditioned conjugate gradients on the blocks (:mod:`como3r.optim.pcg`) with a
block-Jacobi (``"pcg"``) or a band + coarse two-level (``"band"``, :mod:`como3r.optim.band`)
preconditioner. ``"auto"`` takes the dense Cholesky on small systems and ``"band"`` above.
The linear algebra always runs in float64: pose Hessians of dense correspondences weigh
rays by 1/sigma_ray^2 ~ 1e5 and ranges by 1/sigma_dist^2 = 1e-2 (C-Tab. 3), a spread of
1e7 that is the whole precision of float32.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from como3r.errors import InputError
from como3r.optim.pcg import CG_RELATIVE_TOLERANCE, pcg_attempts
from como3r.optim.system import BlockSystem, D, free_dense, free_triplets

logger = logging.getLogger(__name__)

Backend = Literal["auto", "dense", "sparse", "pcg", "band"]
BACKENDS: tuple[str, ...] = ("auto", "dense", "sparse", "pcg", "band")

# backend="auto" (:func:`auto_backend`): a dense Cholesky up to DENSE_MAX_FREE_POSES free
# poses, the band-preconditioned CG above. Measured with benchmarks/ba_scaling.py (2-core
# x86-64 CPU shared with other jobs, torch.set_num_threads(1), chain + loop graphs):
# * dense vs the rest: assembling the free-pose matrix, factorising and solving take the
#   same time as SuperLU at N = 55-63 keyframes (~400 unknowns) over three runs, and as
#   band at N = 56 and 67 (two runs). Below it the dense Cholesky wins (0.4 ms vs 0.8-1.7 ms
#   for SuperLU and ~2 ms for band at N = 10: no scipy conversion or set-up); above it its
#   O(N^3) cost dominates (N = 500: dense 1.0-2.3 s, sparse 0.045-0.065 s).
# * above it, band is the backend whose cost grows about linearly on both graph families
#   of the benchmark (numbers in como3r.optim.band): with a loop edge every 4 keyframes
#   SuperLU's fill grows (solve time log-log slope 1.7-1.8; band / sparse 0.24-0.25 at
#   N = 2000), with one every 50 (nearly a chain) SuperLU is linear and band stays within
#   0.9-1.9x of it at N = 500-2000 (block-Jacobi "pcg": 24-42x). SuperLU is still up to
#   ~2x faster on chain-like graphs and on loop-rich ones up to ~500 keyframes (3x at
#   N = 100, a few milliseconds); but the one rule that keeps the cost per GN iteration
#   about linear on both families is band above the dense crossover (slopes in
#   como3r.optim.band), and SuperLU's loss on the loop-rich graphs grows with N.
DENSE_MAX_FREE_POSES = 60


class SolveStatus(enum.Enum):
    """Outcome of one damped linear solve."""

    SUCCESS = "success"  # the first factorisation (eps_0) succeeded
    ESCALATED = "escalated"  # succeeded after raising the Tikhonov term (r > 0)
    FAILED = "failed"  # every attempt failed; the step is zero


@dataclass(frozen=True, eq=False)
class LinearSolution:
    """A step of C-Eq. 25 and how it was obtained.

    Attributes:
        step: ``(N, 7)`` tangent step (zeros at pinned poses, and everywhere on failure),
            float64, on the device of the system.
        status: see :class:`SolveStatus`.
        attempts: number of attempts tried (1..R): factorisations, or CG solves.
        epsilon: Tikhonov term of the successful attempt, ``None`` on failure.
        backend: ``"dense"``, ``"sparse"``, ``"pcg"`` or ``"band"``, the backend actually
            used.
        cg_iterations: conjugate-gradient iterations over all attempts (0 unless pcg or
            band).
    """

    step: torch.Tensor
    status: SolveStatus
    attempts: int
    epsilon: float | None
    backend: str
    cg_iterations: int = 0

    @property
    def escalations(self) -> int:
        """How many times the Tikhonov term had to be raised (R when all attempts failed)."""
        if self.status is SolveStatus.FAILED:
            return self.attempts
        return max(self.attempts - 1, 0)


def auto_backend(num_free: int) -> Literal["dense", "band"]:
    """The backend ``"auto"`` takes for ``num_free`` free poses (see DENSE_MAX_FREE_POSES)."""
    return "dense" if num_free <= DENSE_MAX_FREE_POSES else "band"


def solve(
    system: BlockSystem,
    free: torch.Tensor,
    *,
    lm_lambda: float = 0.0,
    tikhonov_base: float = 1e-6,
    retries: int = 6,
    backend: Backend = "auto",
    cg_tolerance: float = CG_RELATIVE_TOLERANCE,
    cg_max_iterations: int | None = None,
) -> LinearSolution:
    """Solve ``(H + lm_lambda diag(H) + eps_r I) tau = -g`` over the free poses (C-Eq. 25).

    Args:
        system: block normal equations over N poses.
        free: ``(N,)`` bool, the poses to solve for; the others get a zero step.
        lm_lambda: multiplicative Levenberg-Marquardt damping (0 for local/global BA).
        tikhonov_base: eps_0 of the escalation eps_r = eps_0 * 100^r (C-Sec. B.2).
        retries: R, the number of factorisation attempts.
        backend: ``"dense"``, ``"sparse"``, ``"pcg"``, ``"band"`` or ``"auto"`` (dense up
            to ``DENSE_MAX_FREE_POSES`` free poses, band above; see :mod:`como3r.optim.pcg`
            and :mod:`como3r.optim.band`).
        cg_tolerance, cg_max_iterations: the CG backends' stopping relative residual and
            iteration cap per attempt (``None``: 7 per free pose, at least 100; see
            :mod:`como3r.optim.pcg`); ignored by the factorisations.
    """
    if free.shape != (system.num_poses,) or free.dtype != torch.bool:
        raise InputError(f"solve: free must be a bool tensor of shape ({system.num_poses},)")
    if retries < 1:
        raise InputError(f"solve: retries must be >= 1, got {retries}")
    if backend not in BACKENDS:
        raise InputError(f"solve: backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if not (cg_tolerance >= 0 and (cg_max_iterations is None or cg_max_iterations >= 1)):
        raise InputError(
            f"solve: cg_tolerance must be >= 0 and cg_max_iterations >= 1, got "
            f"{cg_tolerance} and {cg_max_iterations}"
        )
    num_free = int(free.sum())
    if backend == "auto":
        backend = auto_backend(num_free)
    step = torch.zeros_like(system.g)
    if num_free == 0:
        return LinearSolution(step, SolveStatus.SUCCESS, 0, tikhonov_base, backend)
    if backend in ("pcg", "band"):
        outcomes = pcg_attempts(
            system,
            free,
            lm_lambda,
            tikhonov_base,
            retries,
            cg_tolerance,
            cg_max_iterations,
            "jacobi" if backend == "pcg" else "band",
        )
        attempts = ((outcome.x, outcome.iterations) for outcome in outcomes)
    else:
        factorise = _dense_attempts if backend == "dense" else _sparse_attempts
        attempts = ((tau, 0) for tau in factorise(system, free, lm_lambda, tikhonov_base, retries))
    cg_iterations = 0
    for r, (tau_free, iterations) in enumerate(attempts):
        cg_iterations += iterations
        if tau_free is not None:
            step[free] = tau_free
            status = SolveStatus.SUCCESS if r == 0 else SolveStatus.ESCALATED
            return LinearSolution(
                step, status, r + 1, tikhonov_base * 100.0**r, backend, cg_iterations
            )
    logger.warning(
        "damped normal equations not positive definite after %d Tikhonov attempts "
        "(eps up to %.0e); returning a zero step",
        retries,
        tikhonov_base * 100.0 ** (retries - 1),
    )
    return LinearSolution(step, SolveStatus.FAILED, retries, None, backend, cg_iterations)


def _dense_attempts(
    system: BlockSystem, free: torch.Tensor, lm_lambda: float, tikhonov_base: float, retries: int
) -> Iterator[torch.Tensor | None]:
    """Yield the free-pose step ``(F, 7)`` of each escalation attempt, or None on failure."""
    H = free_dense(system, free)
    for tau in dense_attempts(H, system.g[free].reshape(-1), lm_lambda, tikhonov_base, retries):
        yield None if tau is None else tau.reshape(-1, D)


def dense_attempts(
    H: torch.Tensor, g: torch.Tensor, lm_lambda: float, tikhonov_base: float, retries: int
) -> Iterator[torch.Tensor | None]:
    """Yield ``-(H + lm_lambda diag(H) + eps_r I)^-1 g`` ``(n,)`` of each escalation attempt
    ``eps_r = tikhonov_base 100^r`` (C-Sec. B.2) for a dense ``H (n, n)``, ``g (n,)``, or
    None where it does not factorise or is not finite."""
    rhs = -g.reshape(-1, 1)
    damping = lm_lambda * H.diagonal()
    for r in range(retries):
        A = H.clone()  # one working copy at a time: 7N = 14000 is 1.5 GB per matrix
        A.diagonal().add_(damping + tikhonov_base * 100.0**r)
        L, info = torch.linalg.cholesky_ex(A)
        del A
        tau = torch.cholesky_solve(rhs, L)[:, 0] if int(info) == 0 else None
        yield tau if tau is not None and bool(tau.isfinite().all()) else None


def _sparse_attempts(
    system: BlockSystem, free: torch.Tensor, lm_lambda: float, tikhonov_base: float, retries: int
) -> Iterator[torch.Tensor | None]:
    """Sparse counterpart of :func:`_dense_attempts` (scipy SuperLU in symmetric mode)."""
    rows, cols, values, size = free_triplets(system, free)
    H = scipy.sparse.coo_matrix(
        (values.cpu().numpy(), (rows.cpu().numpy(), cols.cpu().numpy())), shape=(size, size)
    ).tocsc()  # sums
    rhs = -system.g[free].reshape(-1).cpu().numpy()
    damping = lm_lambda * H.diagonal()
    for r in range(retries):
        damped = H + scipy.sparse.diags(damping + tikhonov_base * 100.0**r, 0)
        tau = _spd_solve(damped.tocsc(), rhs)
        yield None if tau is None else torch.from_numpy(tau).to(system.g.device).reshape(-1, D)


def _spd_solve(A: scipy.sparse.csc_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """Solve ``A x = rhs`` if A is numerically positive definite, else return None.

    scipy has no sparse Cholesky, so this uses SuperLU as one: with a symmetric
    fill-reducing ordering (MMD on A^T + A, applied to rows and columns alike),
    ``SymmetricMode`` and ``diag_pivot_thresh = 0`` it always takes the diagonal pivot,
    i.e. factors P A P^T = L U with no row exchanges. For symmetric A that is
    A = L D L^T with D = diag(U), and a symmetric matrix is positive definite iff all
    pivots of this elimination are positive. So "every diag(U) finite and > 0 and no row
    exchange happened" (SuperLU only leaves the diagonal on an exactly zero pivot) is the
    same success test as a Cholesky factorisation, and the step is the same up to rounding.
    """
    try:
        lu = scipy.sparse.linalg.splu(
            A,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options=dict(SymmetricMode=True),
        )
    except RuntimeError:  # "Factor is exactly singular"
        return None
    pivots = lu.U.diagonal()
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    if not (np.all(np.isfinite(pivots)) and np.all(pivots > 0.0)):
        return None
    x = lu.solve(rhs)
    return x if np.all(np.isfinite(x)) else None
