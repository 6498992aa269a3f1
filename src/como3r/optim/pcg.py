"""Preconditioned conjugate gradients for the damped normal equations (C-Eq. 25).

The ``"pcg"`` backend of :func:`como3r.optim.linear.solve` (block-Jacobi preconditioner),
and the CG loop and positive-definiteness tests that its ``"band"`` backend (band + coarse
two-level preconditioner, :mod:`como3r.optim.band`, what ``backend="auto"`` takes above
the dense crossover) shares. pcg never forms a matrix: the product ``A x`` of the
free-pose system ``A = H + lambda diag(H) + eps_r I`` is computed blockwise from the 7x7
blocks of the :class:`~como3r.optim.system.BlockSystem` (one gather, batched multiply-adds,
one ``index_add_``, float64, on the system's device), and the preconditioner is the
inverse of A's 7x7 diagonal blocks (batched Cholesky). Its cost per CG iteration is linear
in poses + edges, with no fill-in, and it runs on CUDA unchanged. Its iteration count is
not: block-Jacobi leaves the long-wavelength modes of the pose graph (the smooth drift of
a chain away from its pinned anchor) to CG, and the preconditioned condition number grows
about as N^2 on a chain (measured 460 / 2600 / 11200 at N = 50 / 100 / 200 on
benchmarks/ba_scaling.py's graphs), so CG needs O(N) iterations where loop closures do not
shorten the graph. That is why ``backend="auto"`` does not pick it: pcg / sparse solve time
of the first GN iteration (benchmarks/ba_scaling.py, one thread) is 3.1 / 1.9 / 1.3 / 0.63
/ 0.30 at N = 500 / 750 / 1000 / 1500 / 2000 with a loop edge every 4 keyframes to a random
earlier one (SuperLU's fill grows, CG's ~400 iterations do not), but 6.6 / 32 / 35 at N =
100 / 500 / 2000 with one every 50 (no fill, and CG's iterations grow as N); the number of
poses alone cannot tell the two apart (the band backend's coarse level removes those modes,
:mod:`como3r.optim.band`). Whole GN solves: N = 2000, loops 1/4, pcg 71 s vs sparse 151 s
(100 iterations each, mean 358 CG iterations per solve); N = 500, loops 1/4, 1.8 vs 1.1 s;
N = 500, loops 1/50, 5.6 vs 1.0 s.

Positive definiteness (the success test of C-Sec. B.2's Tikhonov escalation) is checked
where CG can see it: a diagonal block that is not positive definite, or a search direction
of non-positive curvature ``p^T A p <= 0``, fails the attempt like a failed Cholesky, and
the escalation raises eps. Unlike a factorisation CG only explores the Krylov space of the
right-hand side: negative curvature orthogonal to everything it explores (e.g. an indefinite
gauge direction that the gradient does not excite) goes unnoticed at the default tolerance
(a much tighter one runs long enough for rounding to excite it), and the step it returns
is then the solution within that space.

The constants were chosen on benchmarks/ba_scaling.py's problems (float32 ray-range
factors, P = 256, noisy initial poses, pose 0 pinned; ``gauss_newton_irls`` with
``GlobalBAConfig``: step_tol 1e-4 at length_scale 12.5, at most 100 iterations), pcg at
several tolerances against the exact sparse step. GN iterations / max pose error (m) / CG
iterations of the largest solve; "loops 1/4" has a loop edge every 4 keyframes, "1/50"
every 50 (nearly a chain, as keyframe graphs with rare loop closures are):

    problem            sparse        tol 1e-3          tol 1e-4         tol 1e-5
    N=100, loops 1/4   4 / 1.5e-6    4 / 2.3e-6 / 103  4 / 1.7e-6 / 123  4 / 1.2e-6 / 146
    N=500, loops 1/4   7 / 5.9e-6    9 / 1.3e-4 / 544  8 / 6.5e-6 / 697  8 / 7.8e-6 / 719
    N=500, loops 1/50  8 / 3.8e-5    -                 9 / 2.4e-5 / 1963 -
    N=2000, loops 1/4  100 / 5.2e-5  -                 100 / 1.7e-4 / 2230 (both at the
                                                       float32 floor, cost 2.25 vs 2.13)

Final costs agree within 5 %, either way (float32 rounding at the minimum), at tol <= 1e-4.
Looser tolerances shorten the step (CG's iterates grow monotonically in norm from zero),
which GN's step-norm test mistakes for convergence: at 1e-3 the N = 500 error is 22x the
exact step's, at 1e-1 1000x.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Literal

import torch

from como3r.optim.band import OrderedSystem, TwoLevelAttempt
from como3r.optim.system import BlockSystem

logger = logging.getLogger(__name__)

Preconditioner = Literal["jacobi", "band"]

# Stopping test: sqrt(r^T M^-1 r / b^T M^-1 b) <= CG_RELATIVE_TOLERANCE, the residual in
# the preconditioner's inverse norm. It is invariant to a per-pose rescaling of the unknowns
# (the 1e7 spread between ray and range weights does not bias it), and with M ~ A it tracks
# the step's A-norm error, i.e. the part of the GN model's decrease left unrealised. 1e-4:
# the loosest tolerance at which GN's iterations and accuracy match the exact step's (above).
CG_RELATIVE_TOLERANCE = 1e-4
# Iteration cap of one CG solve (one Tikhonov attempt): max(CG_MIN_ITERATION_CAP, 7F), the
# number of unknowns, i.e. CG's termination bound in exact arithmetic. The largest solves
# measured above took 0.16 x 7F (N = 2000, loops 1/4) and 0.56 x 7F (N = 500, loops 1/50).
# A tighter cap is harmful: at a fixed cap of 500 on N = 500, loops 1/50, the truncated steps
# late in the solve barely reduce the residual (the error left is the smooth part
# block-Jacobi cannot see) and GN needs 79-90 iterations to a 20x larger error.
CG_MIN_ITERATION_CAP = 100
# What happens at the cap: the last iterate is returned whatever its residual. It is the
# iterate closest to the exact step in the A-norm (CG's own optimality), and every CG
# iterate from zero lowers the GN model, so it is a descent step; the divergence guard of
# gauss_newton_irls still vets it. Escalating instead does not help: eps_r <= 1e4 is small
# against diagonals of 1e5-1e8, so the next attempt converges no faster. Measured at a cap
# of 500 on N = 500, loops 1/50: escalating when the residual is above 1e-2 ends the solve
# with every attempt failed after 7 GN iterations (error 2.0 m); above 1e-1, 380 escalations
# in 100 GN iterations (error 1.4 m); accepting every capped iterate converges (7e-4 m).


@dataclass(frozen=True, eq=False)
class CGOutcome:
    """One CG solve of a damped system.

    Attributes:
        x: ``(F, 7)`` float64 solution over the free poses, ``None`` when the attempt failed.
        iterations: CG iterations run (matrix-vector products).
        residual: final preconditioned relative residual (``inf`` when it failed early).
        reason: ``"converged"``, ``"capped"`` (the last iterate at the cap),
            ``"indefinite_block"``, ``"negative_curvature"`` or ``"non_finite"``.
    """

    x: torch.Tensor | None
    iterations: int
    residual: float
    reason: str


class _FreeOperator:
    """The free-pose Hessian ``H_ff`` of a :class:`BlockSystem`, kept as blocks.

    Holds the diagonal blocks ``(F, 7, 7)``, the upper off-diagonal blocks ``(K, 7, 7)``
    whose two poses are both free, their free-pose indices ``(K,)``, and the right-hand
    side ``-g_f`` ``(F, 7)``.
    """

    def __init__(self, system: BlockSystem, free: torch.Tensor) -> None:
        device = system.g.device
        free = free.to(device)
        new_index = torch.full((system.num_poses,), -1, dtype=torch.int64, device=device)
        new_index[free] = torch.arange(int(free.sum()), device=device)
        keep = free[system.off_i] & free[system.off_j]
        self.i = new_index[system.off_i[keep]]
        self.j = new_index[system.off_j[keep]]
        self.upper = system.H_off[keep]
        self.diag = system.H_diag[free]
        self.rhs = -system.g[free]

    def damped_diagonal(self, lm_lambda: float, epsilon: float) -> torch.Tensor:
        """``(F, 7, 7)`` diagonal blocks of ``H + lm_lambda diag(H) + epsilon I``."""
        blocks = self.diag.clone()
        diagonal = blocks.diagonal(dim1=-2, dim2=-1)
        diagonal.add_(lm_lambda * diagonal + epsilon)
        return blocks


class _ScaledOperator:
    """``A_hat = L^-1 A L^-T`` with ``L`` the block-diagonal Cholesky factor of A's diagonal
    blocks: plain CG on ``A_hat x_hat = L^-1 b``, ``x = L^-T x_hat``, is block-Jacobi PCG
    on ``A x = b`` (the same iterates, residual norms ``r^T M^-1 r`` and curvatures
    ``p^T A p``), with the preconditioner folded into the blocks once per attempt.

    ``A_hat``'s diagonal blocks are the identity. Its off-diagonal blocks, both triangles,
    are stored component-major, ``(7 in, 7 out, 2K)``, and vectors as ``(7, F)``: the
    product is then 7 multiply-adds over contiguous ``(7, 2K)`` rows between one gather and
    one ``index_add_``, 1.6x faster than a batched ``bmm`` over ``(2K, 7, 7)`` blocks on one
    x86-64 core at K = 4500 (the 7x7 matmuls are too small for a BLAS call each).
    """

    def __init__(self, operator: _FreeOperator, L: torch.Tensor) -> None:
        identity = torch.eye(L.shape[-1], dtype=L.dtype, device=L.device).expand_as(L)
        self.L_inv = torch.linalg.solve_triangular(L, identity, upper=False)  # (F, 7, 7)
        scaled = self.L_inv[operator.i] @ operator.upper @ self.L_inv[operator.j].mT
        both = torch.cat([scaled, scaled.mT])  # (2K, 7 out, 7 in)
        self.blocks = both.permute(2, 1, 0).contiguous()  # (7 in, 7 out, 2K)
        self.src = torch.cat([operator.j, operator.i])
        self.dst = torch.cat([operator.i, operator.j])

    def scale_rhs(self, b: torch.Tensor) -> torch.Tensor:
        """``L^-1 b`` for b ``(F, 7)``, returned component-major ``(7, F)``."""
        return (self.L_inv @ b[..., None])[..., 0].T.contiguous()

    def unscale_solution(self, x_hat: torch.Tensor) -> torch.Tensor:
        """``L^-T x_hat`` for ``x_hat`` ``(7, F)``, returned ``(F, 7)``."""
        return (self.L_inv.mT @ x_hat.T[..., None])[..., 0]

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """``A_hat x`` for x ``(7, F)``."""
        if not len(self.src):
            return x.clone()
        gathered = x.index_select(1, self.src)  # (7, 2K)
        products = self.blocks[0] * gathered[0]
        for component in range(1, x.shape[0]):
            products.addcmul_(self.blocks[component], gathered[component])
        return x.clone().index_add_(1, self.dst, products)


def pcg_attempts(
    system: BlockSystem,
    free: torch.Tensor,
    lm_lambda: float,
    tikhonov_base: float,
    retries: int,
    tolerance: float = CG_RELATIVE_TOLERANCE,
    max_iterations: int | None = None,
    preconditioner: Preconditioner = "jacobi",
) -> Iterator[CGOutcome]:
    """Yield one :class:`CGOutcome` per Tikhonov attempt ``eps_r = eps_0 100^r`` (C-Sec. B.2).

    Args:
        system: block normal equations over N poses.
        free: ``(N,)`` bool, at least one true.
        lm_lambda: multiplicative damping of the diagonal.
        tikhonov_base: eps_0.
        retries: R, the number of attempts.
        tolerance: stopping preconditioned relative residual.
        max_iterations: CG iteration cap per attempt (``None``: max(CG_MIN_ITERATION_CAP,
            7F) for F free poses).
        preconditioner: ``"jacobi"`` (block-Jacobi, this module) or ``"band"`` (band +
            coarse two-level, :mod:`como3r.optim.band`).
    """
    operator = _FreeOperator(system, free)
    if max_iterations is None:
        max_iterations = max(CG_MIN_ITERATION_CAP, operator.rhs.numel())
    ordered = None
    if preconditioner == "band":
        ordered = OrderedSystem(operator.i, operator.j, operator.upper, operator.rhs)
    for r in range(retries):
        diag = operator.damped_diagonal(lm_lambda, tikhonov_base * 100.0**r)
        if ordered is not None:
            yield _band_attempt(ordered, diag, tolerance, max_iterations)
            continue
        L, info = torch.linalg.cholesky_ex(diag)
        if bool((info != 0).any()) or not bool(L.isfinite().all()):
            # a principal submatrix of a positive definite matrix is positive definite
            yield CGOutcome(None, 0, math.inf, "indefinite_block")
            continue
        scaled = _ScaledOperator(operator, L)
        outcome = _cg(scaled, scaled.scale_rhs(operator.rhs), tolerance, max_iterations)
        if outcome.x is not None:
            outcome = CGOutcome(
                scaled.unscale_solution(outcome.x),
                outcome.iterations,
                outcome.residual,
                outcome.reason,
            )
        yield outcome


def _band_attempt(
    ordered: OrderedSystem, diag: torch.Tensor, tolerance: float, max_iterations: int
) -> CGOutcome:
    """One attempt of the band-preconditioned CG, damped diagonal blocks ``diag``."""
    attempt, reason = ordered.attempt(diag)
    if attempt is None:
        return CGOutcome(None, 0, math.inf, reason)
    outcome = _cg(attempt, ordered.rhs, tolerance, max_iterations, attempt)
    if outcome.x is None:
        return outcome
    return CGOutcome(
        ordered.unorder(outcome.x), outcome.iterations, outcome.residual, outcome.reason
    )


def _cg(
    operator: _ScaledOperator | TwoLevelAttempt,
    b: torch.Tensor,
    tolerance: float,
    max_iterations: int,
    precondition: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> CGOutcome:
    """Preconditioned conjugate gradients from x = 0 on ``A x = b`` (``operator.apply``),
    b ``(7, F)`` (pcg) or ``(7F,)`` (band); the outcome's x has b's shape. Without
    ``precondition`` (M = I) this is plain CG, which on the scaled system is block-Jacobi
    PCG."""
    x = torch.zeros_like(b)
    r = b.clone()
    z = r if precondition is None else precondition(r)
    rz = float(torch.dot(r.reshape(-1), z.reshape(-1)))
    if not math.isfinite(rz):
        return CGOutcome(None, 0, math.inf, "non_finite")
    if rz == 0.0:  # zero gradient: the step is zero
        return CGOutcome(x, 0, 0.0, "converged")
    rz_initial, stop = rz, tolerance**2 * rz
    p = z.clone()
    residual, iterations = 1.0, 0
    while iterations < max_iterations:
        iterations += 1
        Ap = operator.apply(p)
        curvature = float(torch.dot(p.reshape(-1), Ap.reshape(-1)))
        if not math.isfinite(curvature):
            return CGOutcome(None, iterations, math.inf, "non_finite")
        if curvature <= 0.0:
            return CGOutcome(None, iterations, math.inf, "negative_curvature")
        alpha = rz / curvature
        x.add_(p, alpha=alpha)
        r.sub_(Ap, alpha=alpha)
        z = r if precondition is None else precondition(r)
        rz_next = float(torch.dot(r.reshape(-1), z.reshape(-1)))
        if not math.isfinite(rz_next):
            return CGOutcome(None, iterations, math.inf, "non_finite")
        residual = math.sqrt(max(rz_next, 0.0) / rz_initial)
        if rz_next <= stop:
            return CGOutcome(x, iterations, residual, "converged")
        p.mul_(rz_next / rz).add_(z)
        rz = rz_next
    logger.debug(
        "PCG: relative residual %.2e at the cap of %d iterations; last iterate kept",
        residual,
        iterations,
    )
    return CGOutcome(x, iterations, residual, "capped")
