"""Two-level band + coarse preconditioner for conjugate gradients on C-Eq. 25.

The ``"band"`` backend of :func:`como3r.optim.linear.solve` (what ``backend="auto"`` takes
above ``DENSE_MAX_FREE_POSES`` free poses) runs :mod:`como3r.optim.pcg`'s conjugate
gradients on the damped free-pose system ``A = H + lambda diag(H) + eps_r I`` of C-Eq. 25
with

    M^-1 r = B^-1 r + P (P^T A P)^-1 P^T r

(an additive two-level preconditioner, cf. the subgraph preconditioners of Dellaert et al.,
IROS 2010, and Jian, Balch, Dellaert, ICCV 2011, with an aggregation coarse level):

* **Band level B.** The poses are put in a *path order* (:func:`path_order`): a linear
  forest of the pose graph, chosen greedily from the edges shortest in keyframe numbering,
  is laid out path after path, so odometry-like edges join consecutive poses whatever the
  number of agents and however their keyframes interleave. B is A's diagonal blocks plus
  every block within ``BAND_BLOCKS`` = 2 of the diagonal in that order; it equals A on
  that band, holds the diagonal blocks that the edges outside it contribute, and is
  positive definite whenever H is a sum of positive semi-definite edge terms (a
  Gauss-Newton Hessian: each remaining edge's diagonal blocks are a principal part of a
  PSD term). It is factorised with LAPACK's banded Cholesky (``dpbtrf``, band width
  7(b+1) = 21, no fill outside the band) in O(F b^2) and applied in O(F b). On a chain
  (plus skip edges) it is A itself and CG converges in one or two iterations.
* **Coarse level P.** Consecutive runs of ``COARSE_GROUP`` = 32 poses of the path order form
  groups, and P gives every pose of a group the same tangent step. Updates are left
  perturbations (``T <- Exp(tau) T``; manual: docs/architecture.md, "Conventions"), so a
  constant tau over a group moves it as one rigid body (similarity): exactly the motions its
  internal edges do not resist and that B, anchored by the diagonal blocks of the edges
  outside the band, resists too much -- the long-wavelength drift of a chain between loop
  closures that leaves block-Jacobi PCG O(N) iterations (:mod:`como3r.optim.pcg`).
  ``P^T A P`` is a dense ``(7G, 7G)`` matrix over G = ceil(F / 32) groups (at most
  ``COARSE_MAX_GROUPS``; the groups grow beyond), summed from A's blocks, Cholesky-factorised
  and inverted once per attempt.

Positive definiteness (C-Sec. B.2's success test) is checked where A's structure allows:
``P^T A P`` not positive definite implies A is not (P has full column rank), and CG stops
on a direction with ``p^T A p <= 0`` as :mod:`como3r.optim.pcg` does; either fails the
attempt and the escalation raises eps. B is not a principal submatrix of A, so its
factorisation failing proves nothing: the attempt then runs with A's diagonal blocks as
the fine level (block-Jacobi + coarse), whose Cholesky is a test of A ("indefinite_block").

Where it runs: on the CPU, in float64, whatever the system's device. The products are a
scipy BSR matrix (0.19 ms at N = 2000, loops 1/4, against 0.41 ms for pcg's blockwise torch
product), the band solve is LAPACK's (scipy has no GPU band solver), the coarse level a
dense inverse in torch; the system's blocks are copied to the CPU once per solve and the
step is returned on the system's device.

Measured with benchmarks/ba_scaling.py (2-core x86-64 CPU shared with two other jobs, load
average ~5, one thread; first GN iteration at the noisy initial poses; P = 256 matches per
edge; "loops 1/4" has a loop edge every 4 keyframes to a random earlier one, "1/50" every
50, nearly a chain), two runs, solve seconds (band / sparse) and band's CG iterations:

    python benchmarks/ba_scaling.py --sizes 100 500 2000 --threads 1

    N      loops 1/4                            loops 1/50
    100    0.016 / 0.009, 0.009 / 0.010, 15     0.009 / 0.003, 0.007 / 0.008,  2
    500    0.059 / 0.068, 0.061 / 0.048, 42     0.031 / 0.032, 0.051 / 0.026, 34
    2000   0.50  / 2.09,  0.42  / 1.68, 117     0.18  / 0.11,  0.14  / 0.16,  48

band / sparse 0.24-0.25 at N = 2000 with many loop closures (SuperLU's fill grows: its
solve time has a log-log slope of 1.70-1.79 there, band's 1.13-1.26), 0.9-1.6 on the
chain-like graphs (block-Jacobi pcg: 40x), 0.9-1.9 at N = 500 and 0.9-3.2 at N = 100
(milliseconds: band's set-up, ~2 ms, weighs there). Whole GN iterations (linearize +
solve), the default's cost per iteration: log-log slope 0.99-1.06 (loops 1/4; sparse
1.33-1.46) and 0.95-0.97 (1/50). The step is within 2e-3 (loops 1/4) and 5.2e-3 (1/50)
of SuperLU's (relative) at the default tolerance, and whole solves (``gauss_newton_irls``
with ``GlobalBAConfig``, float64 poses, length_scale 12.5) take the same GN iterations to
the same poses: N = 500, loops 1/4, 7 vs 7 iterations, max position error 2.05e-6 vs
2.04e-6 m; 1/50, 9 vs 8, 6.87e-6 m both; N = 2000, loops 1/4, 37 vs 36, 8.80e-6 m both,
31 s vs 84 s.

How the pieces were chosen (CG iterations at N = 2000, loops 1/4 / loops 1/50, default
tolerance): block-Jacobi 381 / 3372; band alone (b = 2) 139 / 292; band + coarse with
groups of 8 / 16 / 32 / 64 poses 74 / 25, 99 / 34, 117 / 48, 126 / 99 (groups of 8 and 16
cost more in the coarse factorisation and products than they save: 1.3 and 0.9 s against
0.7 s per solve on loops 1/4 with an earlier torch implementation of the products, on the
loaded machine; groups of 64 lose on the chain-like graphs); b = 1 156 / 226 and b = 3 117
/ 48 with groups of 32 (the graphs' odometry edges join keyframes 1 and 2 apart);
block-Jacobi + coarse 179 / 277. A deflated (multiplicative, A-DEF2) coarse level took 79 /
27 iterations but one more product each, and no less time. Per iteration at N = 2000, loops
1/4, on the shared machine: product 0.19 ms, band solve (``dpbtrs``) 0.42 ms, coarse level
0.1 ms; set-up per solve: path order 3.7 ms, band factorisation 1.8 ms. The CG iterations
still grow on loops 1/4 (15 / 42 / 117 at N = 100 / 500 / 2000), presumably because those
graphs' loop edges join cameras up to N / pi apart that see the same points at 5-20 m from
one of them: ever weaker constraints on ever longer lever arms.

The path order is a heuristic: a cross-agent link that is shorter in the numbering than an
agent's own sequential edges can cut that agent's chain in the forest, and its sequential
edges there fall to the remainder (more CG iterations, the same step). On three and four
interleaved agents with revisit links (tests/optim/test_band.py) it restores the
iterations of the agent-after-agent numbering (22 / 22 and 26 / 28); the numbering as the
order takes 54 and 74.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import scipy.linalg.lapack
import scipy.sparse
import torch

logger = logging.getLogger(__name__)

D = 7  # tangent dimension of Sim(3)

# Block half-bandwidth b of the band level in the path order.
BAND_BLOCKS = 2
# Consecutive poses of the path order per coarse group, and the most groups: above
# COARSE_GROUP * COARSE_MAX_GROUPS free poses the groups grow instead, so the dense coarse
# factorisation stays O(COARSE_MAX_GROUPS^3).
COARSE_GROUP = 32
COARSE_MAX_GROUPS = 128


def path_order(i: torch.Tensor, j: torch.Tensor, num: int) -> torch.Tensor:
    """Positions ``(num,)`` int64 (on i's device) of ``num`` vertices in an order that lays
    a linear forest of the graph end to end.

    The forest is chosen greedily, edges shortest in index distance first (ties by their
    lower, then higher index): an edge joins it when both its vertices have fewer than two
    forest edges and it closes no cycle. Its paths are then walked one after the other,
    each from its end with the lower index, paths in the order of those ends. A chain
    numbered in order keeps its numbering; chains whose vertices interleave (keyframes of
    several agents numbered by arrival) come out one after the other.

    Args:
        i, j: ``(K,)`` int64 edge endpoints in ``[0, num)``; repeats and self-loops allowed.
        num: number of vertices.
    """
    a, b = i.cpu().numpy(), j.cpu().numpy()
    low, high = np.minimum(a, b), np.maximum(a, b)
    keep = low != high
    edges = np.unique(np.stack([high[keep] - low[keep], low[keep], high[keep]], 1), axis=0)
    root = list(range(num))
    neighbours: list[list[int]] = [[] for _ in range(num)]

    def find(v: int) -> int:
        while root[v] != v:
            root[v] = root[root[v]]
            v = root[v]
        return v

    for _, u, v in edges.tolist():  # sorted by (distance, low, high)
        if len(neighbours[u]) < 2 and len(neighbours[v]) < 2:
            ru, rv = find(u), find(v)
            if ru != rv:
                root[ru] = rv
                neighbours[u].append(v)
                neighbours[v].append(u)
    position = [-1] * num
    placed = 0
    for start in range(num):
        if position[start] >= 0 or len(neighbours[start]) == 2:
            continue  # placed already, or inside a path (every path has two ends)
        previous, current = -1, start
        while current >= 0:
            position[current] = placed
            placed += 1
            following = [v for v in neighbours[current] if v != previous]
            previous, current = current, (following[0] if following else -1)
    return torch.tensor(position, dtype=torch.int64, device=i.device)


class OrderedSystem:
    """A damped free-pose system in path order on the CPU, factorised per Tikhonov attempt.

    Holds what the attempts share: the path order, A's off-diagonal blocks renumbered into
    it, the right-hand side ``(7F,)`` (pose-major, float64), and the parts of the band and
    coarse matrices that the damped diagonal does not change. :meth:`attempt` adds A's
    diagonal blocks and factorises both levels.
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        upper: torch.Tensor,
        rhs: torch.Tensor,
        position: torch.Tensor | None = None,
        band_blocks: int | None = None,
        group_size: int | None = None,
    ) -> None:
        """
        Args:
            i, j, upper: ``(K,)``, ``(K,)``, ``(K, 7, 7)``: A's upper off-diagonal blocks
                over F poses (repeated pairs are summed, the lower triangle is their
                transpose), on any device.
            rhs: ``(F, 7)`` right-hand side; its device is the step's.
            position: ``(F,)`` order of the poses (default :func:`path_order`).
            band_blocks: b (default ``BAND_BLOCKS``).
            group_size: poses per coarse group (default: ``COARSE_GROUP``, or more so that
                there are at most ``COARSE_MAX_GROUPS`` groups).
        """
        num = rhs.shape[0]
        self.num, self.device = num, rhs.device
        if position is None:
            position = path_order(i, j, num)
        self.position = position.cpu()
        band_blocks = BAND_BLOCKS if band_blocks is None else band_blocks
        if group_size is None:
            group_size = max(COARSE_GROUP, math.ceil(num / COARSE_MAX_GROUPS))
        i, j = self.position[i.cpu()], self.position[j.cpu()]
        upper = upper.cpu()
        ordered = torch.empty(num, D, dtype=torch.float64)
        ordered[self.position] = rhs.cpu()
        self.rhs = ordered.reshape(-1)
        # products: A's blocks, both triangles and the diagonal, as a BSR matrix
        rows = torch.cat([torch.arange(num), i, j]).numpy()
        cols = torch.cat([torch.arange(num), j, i]).numpy()
        order = np.lexsort((cols, rows))
        self._indices = cols[order]
        self._indptr = np.searchsorted(rows[order], np.arange(num + 1))
        blocks = np.concatenate([np.zeros((num, D, D)), upper.numpy(), upper.mT.numpy()])
        self._blocks = blocks[order]
        self._diagonal_slot = np.argsort(order)[:num]
        self._finite = bool(np.isfinite(self._blocks).all())
        # band level: A's blocks within b of the diagonal, lower band storage
        self._band = torch.zeros(D * (band_blocks + 1) * D * num, dtype=torch.float64)
        near = (i - j).abs() <= band_blocks
        swap = i[near] < j[near]  # every block into the lower triangle
        _add_to_band(
            self._band,
            torch.where(swap, j[near], i[near]),
            torch.where(swap, i[near], j[near]),
            torch.where(swap[:, None, None], upper[near].mT, upper[near]),
            num,
        )
        loop = near & (i == j)  # a block at (k, k) adds its transpose too
        _add_to_band(self._band, i[loop], i[loop], upper[loop].mT, num)
        # coarse level: consecutive runs of group_size poses; A's blocks summed per pair
        self.group = torch.div(torch.arange(num), group_size, rounding_mode="floor")
        self.num_groups = int(self.group[-1]) + 1
        G = self.num_groups
        self._coarse = torch.zeros(G, G, D, D, dtype=torch.float64)
        self._coarse.index_put_((self.group[i], self.group[j]), upper, accumulate=True)
        self._coarse.index_put_((self.group[j], self.group[i]), upper.mT, accumulate=True)

    def attempt(self, diag: torch.Tensor) -> tuple[TwoLevelAttempt | None, str]:
        """Factorise both levels with A's damped diagonal blocks ``diag`` ``(F, 7, 7)``
        (free-pose order, any device); ``(None, reason)`` when A is found not positive
        definite: ``"non_finite"``, ``"indefinite_block"`` (a diagonal block of A) or
        ``"indefinite_coarse"`` (``P^T A P``)."""
        ordered = torch.empty(self.num, D, D, dtype=torch.float64)
        ordered[self.position] = diag.cpu()
        band = self._band.clone()
        index = torch.arange(self.num)
        _add_to_band(band, index, index, ordered, self.num)
        ab = band.reshape(-1, D * self.num).numpy()  # LAPACK's band storage
        if not (self._finite and np.isfinite(ab).all()):
            return None, "non_finite"
        fine: np.ndarray | torch.Tensor
        fine, info = scipy.linalg.lapack.dpbtrf(ab, lower=1, overwrite_ab=1)
        if info != 0:
            # B is not A's principal submatrix: its failure proves nothing about A. Fall
            # back to A's diagonal blocks, which are (a principal submatrix of a positive
            # definite matrix is positive definite).
            logger.debug(
                "band preconditioner: B not positive definite (pivot %d of %d); "
                "block-Jacobi fine level for this attempt",
                info,
                ab.shape[1],
            )
            fine, block_info = torch.linalg.cholesky_ex(ordered)
            if bool((block_info != 0).any()):
                return None, "indefinite_block"
        coarse = self._coarse.clone()
        coarse.index_put_((self.group, self.group), ordered, accumulate=True)
        size = D * self.num_groups
        factor, coarse_info = torch.linalg.cholesky_ex(
            coarse.permute(0, 2, 1, 3).reshape(size, size)
        )
        if int(coarse_info) != 0 or not bool(factor.isfinite().all()):
            return None, "indefinite_coarse"
        blocks = self._blocks.copy()
        blocks[self._diagonal_slot] += ordered.numpy()
        matrix = scipy.sparse.bsr_matrix(
            (blocks, self._indices, self._indptr), shape=(D * self.num, D * self.num)
        )
        return TwoLevelAttempt(matrix, fine, self.group, torch.cholesky_inverse(factor)), ""

    def unorder(self, x: torch.Tensor) -> torch.Tensor:
        """A vector ``(7F,)`` in path order as ``(F, 7)`` in free-pose order on the
        right-hand side's device."""
        return x.reshape(self.num, D)[self.position].to(self.device)


class TwoLevelAttempt:
    """The damped A of one attempt (its product) and ``M^-1 = B^-1 + P (P^T A P)^-1 P^T``
    (calling it), on pose-major vectors ``(7F,)`` in path order, float64, CPU. ``fine``
    says which fine level it holds: ``"band"``, or ``"jacobi"`` (B = A's diagonal blocks)
    when B was not positive definite."""

    def __init__(
        self,
        matrix: scipy.sparse.bsr_matrix,
        fine: np.ndarray | torch.Tensor,
        group: torch.Tensor,
        coarse_inverse: torch.Tensor,
    ) -> None:
        self.matrix = matrix
        self.fine_factor = fine  # LAPACK band Cholesky factor, or (F, 7, 7) block factors
        self.fine = "band" if isinstance(fine, np.ndarray) else "jacobi"
        self.group = group
        self.coarse_inverse = coarse_inverse  # (P^T A P)^-1, (7G, 7G)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """``A x``."""
        return torch.from_numpy(self.matrix @ x.numpy())

    def fine_solve(self, r: torch.Tensor) -> torch.Tensor:
        """``B^-1 r``."""
        if isinstance(self.fine_factor, torch.Tensor):  # self.fine == "jacobi"
            return torch.cholesky_solve(r.reshape(-1, D, 1), self.fine_factor).reshape(-1)
        solved, _ = scipy.linalg.lapack.dpbtrs(self.fine_factor, r.numpy().reshape(-1, 1), lower=1)
        return torch.from_numpy(solved).reshape(-1)

    def coarse_solve(self, r: torch.Tensor) -> torch.Tensor:
        """``P (P^T A P)^-1 P^T r``."""
        summed = torch.zeros(self.coarse_inverse.shape[0] // D, D, dtype=r.dtype)
        summed.index_add_(0, self.group, r.reshape(-1, D))  # P^T r
        return (self.coarse_inverse @ summed.reshape(-1)).reshape(-1, D)[self.group].reshape(-1)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """``M^-1 r``."""
        return self.fine_solve(r).add_(self.coarse_solve(r))


def _add_to_band(
    band: torch.Tensor, R: torch.Tensor, C: torch.Tensor, blocks: torch.Tensor, num: int
) -> None:
    """Add 7x7 blocks at block rows R >= block columns C (where R == C only their lower
    triangle) to a flat LAPACK lower band storage ``(rows, 7 num)``: ``ab[r - c, c] +=
    A[r, c]``."""
    offset = torch.arange(D)
    r, c = offset[:, None], offset[None, :]
    row = D * (R - C)[:, None, None] + r - c  # (K, 7, 7)
    column = (D * C[:, None, None] + c).expand_as(row)
    keep = row >= 0
    band.index_add_(0, (row * (D * num) + column)[keep], blocks[keep])
