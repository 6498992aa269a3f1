"""Tests of como3r.optim.band: the band + coarse preconditioned CG backend of ``solve``."""

from __future__ import annotations

import pytest
import torch

from como3r.geometry.lie import sim3_compose
from como3r.optim import band, linear, pcg
from como3r.optim.linear import SolveStatus, solve
from como3r.optim.match_factors import RayRangeFactors
from como3r.optim.optimizer import gauss_newton_irls
from como3r.optim.synthetic import chain_loop_edges, chain_poses, random_sim3, synthetic_graph
from como3r.optim.system import BlockSystem, EdgeBlocks, assemble
from como3r.optim.values import PoseValues

DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=pytest.mark.skipif(
            not torch.cuda.is_available(), reason="no CUDA device on this machine"
        ),
    ),
]
DTYPES = [torch.float32, torch.float64]


def _relative_error(step: torch.Tensor, reference: torch.Tensor) -> float:
    return float((step.cpu() - reference.cpu()).norm() / reference.cpu().norm())


def _ray_range_problem(
    num_poses: int,
    loop_every: int,
    dtype: torch.dtype,
    points: int = 16,
    seed: int = 0,
    i: torch.Tensor | None = None,
    j: torch.Tensor | None = None,
) -> tuple[BlockSystem, torch.Tensor]:
    """The first Gauss-Newton system of a synthetic chain + loop graph (as
    benchmarks/ba_scaling.py builds, with fewer matches), factors in ``dtype``, pose 0
    pinned; edges ``(i, j)`` if given."""
    generator = torch.Generator().manual_seed(seed)
    truth = chain_poses(num_poses, generator)
    if i is None:
        i, j = chain_loop_edges(num_poses, loop_every, generator)
    graph = synthetic_graph(truth, i, j, points, generator)
    initial = sim3_compose(random_sim3(num_poses, 2.0, 0.2, 0.03, generator), truth)
    initial[0] = truth[0]
    factors = RayRangeFactors(
        graph.i, graph.j, graph.X_i.to(dtype), graph.X_j.to(dtype), graph.q.to(dtype), graph.valid
    )
    values = PoseValues.from_poses(initial, num_pinned=1)
    return assemble(num_poses, [factors.linearize(values.poses)]), values.free


def test_path_order_keeps_a_numbered_chain():
    k = torch.arange(19)
    i = torch.cat([k, k[:-1], torch.tensor([3, 12])])
    j = torch.cat([k + 1, k[:-1] + 2, torch.tensor([15, 0])])  # loops: to the remainder
    assert torch.equal(band.path_order(i, j, 20), torch.arange(20))


def test_path_order_lays_interleaved_chains_end_to_end():
    """Three agents' keyframes numbered by arrival (agent a's k-th at 3k + a): each chain
    comes out on consecutive positions, in its own order, so its sequential and skip
    edges fall within the band (they are 3 and 6 apart in the numbering)."""
    agents, length = 3, 15
    i, j = [], []
    for a in range(agents):
        for k in range(length - 1):
            i.append(3 * k + a)
            j.append(3 * (k + 1) + a)
        for k in range(length - 2):
            i.append(3 * k + a)
            j.append(3 * (k + 2) + a)
    position = band.path_order(torch.tensor(i), torch.tensor(j), agents * length)
    assert sorted(position.tolist()) == list(range(agents * length))
    for a in range(agents):
        chain = position[torch.arange(length) * 3 + a]
        assert torch.equal(chain, chain[0] + torch.arange(length))


def test_path_order_is_a_permutation_of_any_graph():
    generator = torch.Generator().manual_seed(0)
    i = torch.randint(0, 50, (200,), generator=generator)
    j = torch.randint(0, 50, (200,), generator=generator)  # repeats, self-loops, isolated
    position = band.path_order(i, j, 53)
    assert sorted(position.tolist()) == list(range(53))


@pytest.mark.parametrize("dtype", DTYPES, ids=["float32", "float64"])
@pytest.mark.parametrize("loop_every", [4, 50], ids=["loops_1_4", "chain_loops_1_50"])
def test_band_step_equals_the_sparse_step(loop_every, dtype):
    system, free = _ray_range_problem(150, loop_every, dtype)
    sparse = solve(system, free, backend="sparse")
    assert sparse.status is SolveStatus.SUCCESS
    tight = solve(system, free, backend="band", cg_tolerance=1e-10)
    assert tight.status is SolveStatus.SUCCESS and tight.backend == "band"
    assert tight.step.dtype == torch.float64 and torch.all(tight.step[~free] == 0)
    assert _relative_error(tight.step, sparse.step) < 1e-7
    default = solve(system, free, backend="band")
    assert default.status is SolveStatus.SUCCESS
    # At the default tolerance (1e-4): measured step errors 1.0e-3 (loops 1/4) and 1.3e-3
    # (1/50) in 19 and 21 iterations, both dtypes alike; block-Jacobi pcg takes 107 and 424
    # (its step errors 3.6e-2 and 8.3e-2)
    assert _relative_error(default.step, sparse.step) < 5e-3
    jacobi = solve(system, free, backend="pcg")
    assert default.cg_iterations < jacobi.cg_iterations / 4


def _agent_problem(agents: int, interleaved: bool) -> tuple[BlockSystem, torch.Tensor]:
    """Chains of 40 keyframes per agent with sequential and skip edges, and cross-agent
    links from keyframe k to keyframe k - 10 of the next agent (a revisit), numbered agent
    after agent or renumbered by arrival (agent a's k-th keyframe is number agents k + a):
    one problem in two numberings."""
    length = 40
    edges = [
        (length * a + k, length * a + k + step)
        for a in range(agents)
        for step in (1, 2)
        for k in range(length - step)
    ]
    edges += [
        (length * a + k, length * ((a + 1) % agents) + k - 10)
        for a in range(agents)
        for k in range(15, length, 8)
    ]
    i = torch.tensor([e[0] for e in edges])
    j = torch.tensor([e[1] for e in edges])
    system, free = _ray_range_problem(agents * length, 0, torch.float32, i=i, j=j)
    if not interleaved:
        return system, free
    pose = torch.arange(agents * length)
    number = agents * (pose % length) + pose // length
    H_diag, g, renumbered_free = (torch.empty_like(t) for t in (system.H_diag, system.g, free))
    H_diag[number], g[number], renumbered_free[number] = system.H_diag, system.g, free
    return (
        BlockSystem(H_diag, number[system.off_i], number[system.off_j], system.H_off, g),
        renumbered_free,
    )


@pytest.mark.parametrize("agents", [3, 4])
def test_band_is_not_tied_to_one_agent_numbering(agents, monkeypatch):
    """Numbering the keyframes by arrival instead of agent after agent costs (nearly) no
    iteration: the path order lays each agent's chain on consecutive positions again.
    Without it (the numbering as the order) the sequential edges, ``agents`` apart, fall
    outside the band, and CG needs 2-3x the iterations."""
    iterations = {}
    for interleaved in (False, True):
        system, free = _agent_problem(agents, interleaved)
        sparse = solve(system, free, backend="sparse").step
        solution = solve(system, free, backend="band")
        assert _relative_error(solution.step, sparse) < 2e-2  # measured 4e-3 to 8e-3
        tight = solve(system, free, backend="band", cg_tolerance=1e-10)
        assert _relative_error(tight.step, sparse) < 1e-7
        iterations[interleaved] = solution.cg_iterations
    # measured 22 / 22 (3 agents) and 26 / 28 (4 agents)
    assert iterations[True] <= iterations[False] + 4
    monkeypatch.setattr(band, "path_order", lambda i, j, num: torch.arange(num))
    system, free = _agent_problem(agents, True)
    assert solve(system, free, backend="band").cg_iterations > iterations[True] + 15  # 54, 74


def _random_system(num_poses: int, edges: list[tuple[int, int]], seed: int) -> BlockSystem:
    generator = torch.Generator().manual_seed(seed)
    J = torch.randn(len(edges), 24, 14, generator=generator, dtype=torch.float64)
    e = torch.randn(len(edges), 24, generator=generator, dtype=torch.float64)
    H = J.mT @ J
    g = (J.mT @ e[..., None])[..., 0]
    i = torch.tensor([a for a, _ in edges])
    j = torch.tensor([b for _, b in edges])
    return assemble(
        num_poses, [EdgeBlocks(i, j, H[:, :7, :7], H[:, 7:, 7:], H[:, :7, 7:], g[:, :7], g[:, 7:])]
    )


def test_each_level_is_exactly_its_equation():
    """In the order given (here a random one), the attempt's product is A, its band level
    with b >= F is A^-1, its coarse level is P (P^T A P)^-1 P^T with P stacking identity
    blocks over runs of 5 poses; with b = 1 the band level drops the blocks farther out."""
    num = 12
    generator = torch.Generator().manual_seed(1)
    edges = [(k, k + 1) for k in range(num - 1)] + [(0, 7), (3, 11), (5, 5), (2, 3)]
    system = _random_system(num, edges, seed=2)
    diag = system.H_diag + 1e-3 * torch.eye(7, dtype=torch.float64)
    position = torch.randperm(num, generator=generator)
    pose = torch.argsort(position)  # the pose at each position
    index = (7 * pose[:, None] + torch.arange(7)).reshape(-1)
    A = (system.to_dense() + 1e-3 * torch.eye(7 * num, dtype=torch.float64))[index][:, index]
    r = torch.randn(7 * num, generator=generator, dtype=torch.float64)
    ordered = band.OrderedSystem(
        system.off_i,
        system.off_j,
        system.H_off,
        system.g,
        position=position,
        band_blocks=num,
        group_size=5,
    )
    torch.testing.assert_close(ordered.rhs, system.g[pose].reshape(-1))
    torch.testing.assert_close(ordered.unorder(ordered.rhs), system.g)
    exact, reason = ordered.attempt(diag)
    assert reason == "" and exact.fine == "band"
    torch.testing.assert_close(exact.apply(r), A @ r, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(
        exact.fine_solve(r), torch.linalg.solve(A, r), rtol=1e-10, atol=1e-12
    )
    P = torch.zeros(7 * num, 7 * 3, dtype=torch.float64)
    for p in range(num):
        P[7 * p : 7 * p + 7, 7 * (p // 5) : 7 * (p // 5) + 7] = torch.eye(7)
    coarse = P @ torch.linalg.solve(P.T @ A @ P, P.T @ r)
    torch.testing.assert_close(exact.coarse_solve(r), coarse, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(exact(r), exact.fine_solve(r) + coarse)
    # b = 1 in the numbering: (0, 7) and (3, 11) leave B, (5, 5) is on its diagonal
    narrow, _ = band.OrderedSystem(
        system.off_i,
        system.off_j,
        system.H_off,
        system.g,
        position=torch.arange(num),
        band_blocks=1,
    ).attempt(diag)
    B = system.to_dense() + 1e-3 * torch.eye(7 * num, dtype=torch.float64)
    for a, b in [(0, 7), (3, 11)]:
        B[7 * a : 7 * a + 7, 7 * b : 7 * b + 7] = 0
        B[7 * b : 7 * b + 7, 7 * a : 7 * a + 7] = 0
    torch.testing.assert_close(
        narrow.fine_solve(r), torch.linalg.solve(B, r), rtol=1e-10, atol=1e-12
    )


@pytest.mark.parametrize("device", DEVICES)
def test_band_step_on_the_system_device_with_damping_and_inner_pins(device):
    system, free = _ray_range_problem(90, 6, torch.float32)
    free[[0, 17, 55]] = False
    moved = BlockSystem(
        *(t.to(device) for t in (system.H_diag, system.off_i, system.off_j, system.H_off, system.g))
    )
    solution = solve(moved, free.to(device), backend="band", lm_lambda=1e-2, cg_tolerance=1e-10)
    assert solution.step.device.type == device and solution.step.dtype == torch.float64
    assert torch.all(solution.step[~free.to(device)] == 0)
    dense = solve(system, free, backend="dense", lm_lambda=1e-2).step
    assert _relative_error(solution.step, dense) < 1e-7


def test_indefinite_coarse_level_fails_the_attempt():
    """``P^T A P`` not positive definite (so neither is A) while the diagonal blocks are:
    two poses, one group, H = [[I, -1.5 I], [-1.5 I, I]] (its band, H itself, is not
    either; the fine level falls back to the diagonal blocks). Escalation, indefinite
    diagonal blocks and NaNs: test_pcg.py, for both CG backends."""
    eye = torch.eye(7, dtype=torch.float64)
    system = BlockSystem(
        torch.stack([eye, eye]),
        torch.tensor([0]),
        torch.tensor([1]),
        -1.5 * eye[None],
        torch.ones(2, 7, dtype=torch.float64),
    )
    outcomes = list(
        pcg.pcg_attempts(
            system, torch.ones(2, dtype=torch.bool), 0.0, 1e-6, 2, preconditioner="band"
        )
    )
    assert [o.reason for o in outcomes] == ["indefinite_coarse"] * 2


def test_a_band_that_is_not_positive_definite_falls_back_to_block_jacobi(monkeypatch):
    """B is not a principal submatrix of A: A = [[1, .75, .5], [.75, 1, .75], [.5, .75, 1]]
    (x I7) is positive definite (lambda_min 0.16), its band of width 1 is not (-0.06).
    The attempt does not fail: its fine level becomes A's diagonal blocks."""
    eye = torch.eye(7, dtype=torch.float64)
    i, j = torch.tensor([0, 1, 0]), torch.tensor([1, 2, 2])
    upper = torch.stack([0.75 * eye, 0.75 * eye, 0.5 * eye])
    diag = eye.expand(3, 7, 7).clone()
    g = torch.randn(3, 7, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    attempt, reason = band.OrderedSystem(i, j, upper, g, band_blocks=1).attempt(diag)
    assert reason == "" and attempt.fine == "jacobi"
    system = BlockSystem(diag, i, j, upper, g)
    free = torch.ones(3, dtype=torch.bool)
    monkeypatch.setattr(band, "BAND_BLOCKS", 1)
    solution = solve(system, free, backend="band", cg_tolerance=1e-12)
    assert solution.status is SolveStatus.SUCCESS and solution.attempts == 1
    dense = solve(system, free, backend="dense").step
    assert _relative_error(solution.step, dense) < 1e-10


def test_a_pose_no_factor_touches_gets_a_negligible_step():
    """Its Hessian block is eps_0 I alone; the coarse level couples it to its group's other
    poses only through that group's rigid motion, so its step is rounding (measured
    2e-17 against steps of order 1)."""
    num = 70
    system = _random_system(num, [(k, k + 1) for k in range(num - 2)], seed=6)
    free = torch.ones(num, dtype=torch.bool)
    free[0] = False
    solution = solve(system, free, backend="band")
    assert solution.status is SolveStatus.SUCCESS
    assert float(solution.step[-1].abs().max()) < 1e-12 * float(solution.step.abs().max())


def test_auto_takes_dense_up_to_the_crossover_and_band_above():
    dense_max = linear.DENSE_MAX_FREE_POSES
    assert [linear.auto_backend(n) for n in (1, dense_max, dense_max + 1, 100 * dense_max)] == [
        "dense",
        "dense",
        "band",
        "band",
    ]
    system, free = _ray_range_problem(dense_max + 2, 10, torch.float32)
    free[0] = False  # exactly DENSE_MAX_FREE_POSES + 1 free poses
    above = solve(system, free)
    assert above.backend == "band" and above.cg_iterations > 0
    free[1] = False
    below = solve(system, free)
    assert below.backend == "dense" and below.cg_iterations == 0
    # both near the factorised step (the band one at the CG tolerance; measured 1.5e-3)
    free[1] = True
    assert _relative_error(above.step, solve(system, free, backend="sparse").step) < 5e-3


def test_gauss_newton_with_the_band_backend_matches_sparse():
    generator = torch.Generator().manual_seed(4)
    truth = chain_poses(120, generator)
    i, j = chain_loop_edges(120, 8, generator)
    graph = synthetic_graph(truth, i, j, 24, generator)
    initial = sim3_compose(random_sim3(120, 2.0, 0.2, 0.03, generator), truth)
    initial[0] = truth[0]
    factors = RayRangeFactors(
        graph.i, graph.j, graph.X_i.float(), graph.X_j.float(), graph.q.float(), graph.valid
    )
    values = PoseValues.from_poses(initial, num_pinned=1)
    results = {}
    for backend in ("band", "sparse"):
        solved, report = gauss_newton_irls(
            factors, values, max_iters=30, step_tol=1e-6, backend=backend, length_scale=12.5
        )
        assert report.converged
        results[backend] = (solved.poses, report.iterations)
    # measured: 5 iterations each, max position error 4.9e-7 m, poses equal to 1.2e-13
    error = float((results["band"][0][:, :3] - truth[:, :3]).norm(dim=-1).max())
    assert error < 1e-5
    assert float((results["band"][0] - results["sparse"][0]).abs().max()) < 1e-5
    assert abs(results["band"][1] - results["sparse"][1]) <= 1
