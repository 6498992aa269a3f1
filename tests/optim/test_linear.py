"""Tests of como3r.optim.linear: assembly, the three backends, Tikhonov escalation (the pcg
backend's own tests are in test_pcg.py)."""

from __future__ import annotations

import logging

import pytest
import torch

from como3r.errors import InputError
from como3r.optim import linear
from como3r.optim.linear import SolveStatus, solve
from como3r.optim.system import (
    BlockSystem,
    EdgeBlocks,
    assemble,
    free_dense,
    free_triplets,
    triplets_to_dense,
)

FACTORISATIONS = ["dense", "sparse"]
BACKENDS = [*FACTORISATIONS, "pcg", "band"]


def _random_edges(
    num_poses: int, edges: list[tuple[int, int]], seed: int, rank: int = 40
) -> EdgeBlocks:
    """Edge blocks of random Gauss-Newton terms J^T J over stacked (J_i, J_j) Jacobians."""
    generator = torch.Generator().manual_seed(seed)
    i = torch.tensor([e[0] for e in edges])
    j = torch.tensor([e[1] for e in edges])
    J = torch.randn(len(edges), rank, 14, generator=generator, dtype=torch.float64)
    e = torch.randn(len(edges), rank, generator=generator, dtype=torch.float64)
    H = J.transpose(1, 2) @ J
    g = (J.transpose(1, 2) @ e[..., None])[..., 0]
    return EdgeBlocks(i, j, H[:, :7, :7], H[:, 7:, 7:], H[:, :7, 7:], g[:, :7], g[:, 7:])


def _dense_reference(blocks: EdgeBlocks, num_poses: int) -> torch.Tensor:
    """The global Hessian built edge by edge with explicit slicing."""
    H = torch.zeros(num_poses * 7, num_poses * 7, dtype=torch.float64)
    for k in range(len(blocks.i)):
        a, b = int(blocks.i[k]) * 7, int(blocks.j[k]) * 7
        H[a : a + 7, a : a + 7] += blocks.H_ii[k]
        H[b : b + 7, b : b + 7] += blocks.H_jj[k]
        H[a : a + 7, b : b + 7] += blocks.H_ij[k]
        H[b : b + 7, a : a + 7] += blocks.H_ij[k].T
    return H


GRAPH = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (1, 3), (3, 1), (2, 4)]  # (1,3) twice


def test_assembly_scatter_adds_blocks_and_repeated_pairs():
    blocks = _random_edges(5, GRAPH, seed=0)
    system = assemble(5, [blocks])
    torch.testing.assert_close(system.to_dense(), _dense_reference(blocks, 5))
    g = torch.zeros(5, 7, dtype=torch.float64)
    g.index_add_(0, blocks.i, blocks.g_i).index_add_(0, blocks.j, blocks.g_j)
    torch.testing.assert_close(system.g, g)


def test_assembly_of_several_contributions_equals_one():
    first, second = _random_edges(5, GRAPH[:4], seed=1), _random_edges(5, GRAPH[4:], seed=2)
    together = assemble(5, [EdgeBlocks.cat([first, second])])
    apart = assemble(5, [first, second])
    torch.testing.assert_close(apart.to_dense(), together.to_dense())
    torch.testing.assert_close(apart.g, together.g)


@pytest.mark.parametrize("lm_lambda", [0.0, 1e-2])
def test_dense_and_sparse_backends_give_the_same_step(lm_lambda):
    system = assemble(5, [_random_edges(5, GRAPH, seed=3)])
    free = torch.tensor([False, True, True, False, True])
    dense = solve(system, free, lm_lambda=lm_lambda, backend="dense")
    sparse = solve(system, free, lm_lambda=lm_lambda, backend="sparse")
    assert dense.status is sparse.status is SolveStatus.SUCCESS
    assert (dense.backend, sparse.backend) == ("dense", "sparse")
    torch.testing.assert_close(dense.step, sparse.step, rtol=1e-9, atol=1e-12)
    # Both equal the solution of the reduced damped system, and pinned poses do not move.
    index = torch.cat([torch.arange(k * 7, k * 7 + 7) for k in (1, 2, 4)])
    H = system.to_dense()[index][:, index]
    A = H + lm_lambda * torch.diag(H.diagonal()) + 1e-6 * torch.eye(21, dtype=torch.float64)
    expected = torch.linalg.solve(A, -system.g[free].reshape(-1))
    torch.testing.assert_close(dense.step[free].reshape(-1), expected, rtol=1e-9, atol=1e-12)
    assert torch.all(dense.step[~free] == 0) and torch.all(sparse.step[~free] == 0)


def _slightly_indefinite_system() -> tuple[BlockSystem, torch.Tensor]:
    """A gauge-free system (no pose pinned) whose 7-dimensional null space picked up an
    eigenvalue of -1e-5, as rounding does to a gauge direction at large weights: the first
    attempt (eps = 1e-6) is not positive definite, the second (1e-4) is."""
    system = assemble(4, [_random_edges(4, [(0, 1), (1, 2), (2, 3), (3, 0)], seed=4)])
    H = system.to_dense()
    null = torch.randn(28, 7, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    null = torch.linalg.qr(null).Q
    projector = torch.eye(28, dtype=torch.float64) - null @ null.T
    H = projector @ H @ projector - 1e-5 * null @ null.T
    H = 0.5 * (H + H.T)
    blocks = H.reshape(4, 7, 4, 7).transpose(1, 2)
    diag = torch.arange(4)
    off_i, off_j = torch.triu_indices(4, 4, offset=1)
    g = projector @ system.g.reshape(-1)
    indefinite = BlockSystem(
        H_diag=blocks[diag, diag],
        off_i=off_i,
        off_j=off_j,
        H_off=blocks[off_i, off_j],
        g=g.reshape(4, 7),
    )
    return indefinite, torch.ones(4, dtype=torch.bool)


@pytest.mark.parametrize("backend", FACTORISATIONS)
def test_tikhonov_escalation_on_an_indefinite_system(backend):
    system, free = _slightly_indefinite_system()
    solution = solve(system, free, backend=backend)
    assert solution.status is SolveStatus.ESCALATED
    assert solution.attempts == 2 and solution.escalations == 1
    assert solution.epsilon == pytest.approx(1e-4)
    A = system.to_dense() + 1e-4 * torch.eye(28, dtype=torch.float64)
    residual = A @ solution.step.reshape(-1) + system.g.reshape(-1)
    assert residual.abs().max() < 1e-8 * system.g.abs().max()


@pytest.mark.parametrize("backend", ["pcg", "band"])
def test_cg_does_not_see_negative_curvature_the_gradient_does_not_excite(backend):
    """The CG backends' documented limit: CG sees curvature only in the Krylov space it
    explores. On the gauge-free system above (null space at -1e-5, gradient orthogonal to
    it) it converges at the default tolerance (8 and 9 iterations) before rounding excites
    the null space, at eps_0 instead of escalating, to the solution of that system. (The
    band backend's band is not positive definite here, as this H is no sum of PSD edge
    terms; it falls back to block-Jacobi, which is.)"""
    system, free = _slightly_indefinite_system()
    solution = solve(system, free, backend=backend)
    assert solution.status is SolveStatus.SUCCESS and solution.epsilon == pytest.approx(1e-6)
    A = system.to_dense() + 1e-6 * torch.eye(28, dtype=torch.float64)
    residual = A @ solution.step.reshape(-1) + system.g.reshape(-1)
    assert residual.abs().max() < 2e-4 * system.g.abs().max()  # measured 8.0e-5


@pytest.mark.parametrize("backend", [*FACTORISATIONS, "pcg"])
def test_unconstrained_pose_is_held_by_tikhonov_alone(backend):
    """A free pose that no factor touches has a zero Hessian block: eps_0 makes the system
    definite at the first attempt and the pose gets a zero step (the band backend's coarse
    level gives it a rounding-sized one: test_band.py)."""
    system = assemble(4, [_random_edges(4, [(0, 1), (1, 2)], seed=6)])
    free = torch.tensor([False, True, True, True])
    solution = solve(system, free, backend=backend)
    assert solution.status is SolveStatus.SUCCESS
    assert torch.all(solution.step[3] == 0) and torch.any(solution.step[1] != 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_step_and_failed_status_when_every_attempt_fails(backend, caplog):
    system = assemble(5, [_random_edges(5, GRAPH, seed=7)])
    H_diag = system.H_diag.clone()
    H_diag[2, 3, 3] = float("nan")
    broken = BlockSystem(H_diag, system.off_i, system.off_j, system.H_off, system.g)
    with caplog.at_level(logging.WARNING, logger="como3r.optim.linear"):
        solution = solve(broken, torch.ones(5, dtype=torch.bool), retries=6, backend=backend)
    assert solution.status is SolveStatus.FAILED
    assert solution.attempts == 6 and solution.escalations == 6 and solution.epsilon is None
    assert torch.all(solution.step == 0)
    assert "zero step" in caplog.text


def test_auto_backend_switches_at_the_measured_crossover():
    small = linear.DENSE_MAX_FREE_POSES
    edges = [(k, k + 1) for k in range(small + 1)]
    system = assemble(small + 2, [_random_edges(small + 2, edges, seed=8, rank=10)])
    free = torch.ones(small + 2, dtype=torch.bool)
    free[0] = False  # exactly DENSE_MAX_FREE_POSES + 1 free poses
    assert solve(system, free).backend == "band"
    free[1] = False
    assert solve(system, free).backend == "dense"


def test_solve_validates_its_arguments():
    system = assemble(3, [_random_edges(3, [(0, 1), (1, 2)], seed=9)])
    with pytest.raises(InputError, match="free"):
        solve(system, torch.ones(2, dtype=torch.bool))
    with pytest.raises(InputError, match="backend"):
        solve(system, torch.ones(3, dtype=torch.bool), backend="cholmod")
    with pytest.raises(InputError, match="retries"):
        solve(system, torch.ones(3, dtype=torch.bool), retries=0)


def test_dense_free_hessian_sums_the_same_blocks_in_the_same_order_as_the_triplets():
    # free_dense replaces triplets_to_dense(*free_triplets(...)) in the dense solve: equal bit
    # for bit, repeated pairs (in both orientations) and pinned poses included
    blocks = _random_edges(5, GRAPH + [(3, 1), (1, 3), (0, 2)], seed=3)
    system = assemble(5, [blocks])
    for pinned in ([], [0], [0, 3], [1, 2, 4]):
        free = torch.ones(5, dtype=torch.bool)
        free[pinned] = False
        assert torch.equal(
            free_dense(system, free), triplets_to_dense(*free_triplets(system, free))
        )
