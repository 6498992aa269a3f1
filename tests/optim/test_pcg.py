"""Tests of como3r.optim.pcg: the block-Jacobi PCG backend of ``linear.solve`` (and, where
marked, the CG loop's band-preconditioned variant, como3r.optim.band)."""

from __future__ import annotations

import logging

import pytest
import torch

from como3r.errors import InputError
from como3r.optim import pcg
from como3r.optim.linear import SolveStatus, solve
from como3r.optim.system import BlockSystem, EdgeBlocks, assemble

DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=pytest.mark.skipif(
            not torch.cuda.is_available(), reason="no CUDA device on this machine"
        ),
    ),
]
NUM_POSES = 40
PINNED = (0, 17)


def _edges(num_poses: int) -> list[tuple[int, int]]:
    """Chain (k, k+1), skips (k, k+2) and a loop (k, k+9) every third keyframe."""
    return (
        [(k, k + 1) for k in range(num_poses - 1)]
        + [(k, k + 2) for k in range(num_poses - 2)]
        + [(k, k + 9) for k in range(0, num_poses - 9, 3)]
    )


def _system(badly_scaled: bool, device: str, seed: int = 0) -> BlockSystem:
    """Random Gauss-Newton blocks ``J^T J`` over the edges of :func:`_edges`. Badly scaled:
    the 7 tangent columns of J weigh 1 to 10^3.5, so diagonal entries of H spread over 1e7
    (as ray and range weights do, C-Tab. 3), and edge weights spread over 1e1."""
    generator = torch.Generator().manual_seed(seed)
    edges = _edges(NUM_POSES)
    J = torch.randn(len(edges), 24, 14, generator=generator, dtype=torch.float64)
    e = torch.randn(len(edges), 24, generator=generator, dtype=torch.float64)
    if badly_scaled:
        J = J * torch.logspace(0, 3.5, 7, dtype=torch.float64).repeat(2)
        J = J * torch.logspace(0, 0.5, len(edges), dtype=torch.float64)[:, None, None]
    H = J.mT @ J
    g = (J.mT @ e[..., None])[..., 0]
    i = torch.tensor([a for a, _ in edges])
    j = torch.tensor([b for _, b in edges])
    blocks = EdgeBlocks(i, j, H[:, :7, :7], H[:, 7:, 7:], H[:, :7, 7:], g[:, :7], g[:, 7:])
    system = assemble(NUM_POSES, [blocks])
    return BlockSystem(
        *(t.to(device) for t in (system.H_diag, system.off_i, system.off_j, system.H_off, system.g))
    )


def _free(device: str) -> torch.Tensor:
    free = torch.ones(NUM_POSES, dtype=torch.bool, device=device)
    free[list(PINNED)] = False
    return free


def _relative_error(step: torch.Tensor, reference: torch.Tensor) -> float:
    return float((step.cpu() - reference).norm() / reference.norm())


def _cpu(system: BlockSystem) -> BlockSystem:
    return BlockSystem(
        *(t.cpu() for t in (system.H_diag, system.off_i, system.off_j, system.H_off, system.g))
    )


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("badly_scaled", [False, True], ids=["well_conditioned", "spread_1e7"])
def test_pcg_step_matches_the_factorised_steps(device, badly_scaled):
    system = _system(badly_scaled, device)
    if badly_scaled:  # the 1e7 spread is really there
        diagonal = system.H_diag.diagonal(dim1=-2, dim2=-1)
        assert float(diagonal.max() / diagonal.min()) > 1e7
    free = _free(device)
    dense = solve(_cpu(system), free.cpu(), backend="dense").step
    sparse = solve(_cpu(system), free.cpu(), backend="sparse").step
    assert _relative_error(sparse, dense) < 1e-13
    # To a tight tolerance CG reproduces the factorised step (measured relative errors
    # 1.1e-12 / 6.3e-13 in 21 / 23 iterations, well conditioned / spread).
    tight = solve(system, free, backend="pcg", cg_tolerance=1e-12)
    assert tight.status is SolveStatus.SUCCESS and tight.backend == "pcg"
    assert tight.step.device.type == device and tight.step.dtype == torch.float64
    assert _relative_error(tight.step, dense) < 1e-11
    assert 0 < tight.cg_iterations <= 30
    # At the default tolerance (1e-4) the step error is of that order (measured 1.1e-4 /
    # 6.8e-5 in 7 / 8 iterations): the block-Jacobi preconditioner absorbs the per-coordinate
    # scaling, so the spread costs no extra iterations.
    default = solve(system, free, backend="pcg")
    assert default.status is SolveStatus.SUCCESS
    assert _relative_error(default.step, dense) < 4e-4
    assert default.cg_iterations <= 10


@pytest.mark.parametrize("device", DEVICES)
def test_pinned_poses_get_a_zero_step(device):
    system = _system(True, device)
    free = _free(device)
    solution = solve(system, free, backend="pcg", lm_lambda=1e-2)
    assert torch.all(solution.step[~free] == 0)
    assert torch.all(solution.step[free].abs().sum(-1) > 0)
    # and the damped step is that of the factorised backends (measured 6.1e-5)
    dense = solve(_cpu(system), free.cpu(), backend="dense", lm_lambda=1e-2).step
    assert _relative_error(solution.step, dense) < 4e-4


def _indefinite_system(device: str, negative: float) -> BlockSystem:
    """The well-conditioned system with its Hessian shifted down by ``negative`` I: its
    smallest eigenvalue becomes negative and the gradient has components along it."""
    system = _system(False, device)
    H_diag = system.H_diag.clone()
    H_diag.diagonal(dim1=-2, dim2=-1).sub_(negative)
    return BlockSystem(H_diag, system.off_i, system.off_j, system.H_off, system.g)


def _smallest_free_eigenvalue(system: BlockSystem, free: torch.Tensor) -> float:
    index = torch.arange(7 * NUM_POSES).reshape(NUM_POSES, 7)[free.cpu()].reshape(-1)
    H = _cpu(system).to_dense()[index][:, index]
    return float(torch.linalg.eigvalsh(H)[0])


# the CG backends and their preconditioners: block-Jacobi, band + coarse (optim.band)
CG_BACKENDS = {"pcg": "jacobi", "band": "band"}


@pytest.mark.parametrize("backend", CG_BACKENDS)
@pytest.mark.parametrize("device", DEVICES)
def test_non_positive_definite_system_escalates_like_the_factorisations(device, backend):
    free = _free(device)
    lowest = _smallest_free_eigenvalue(_system(False, device), free)
    # shifted to lambda_min = -5e-5: not PD at eps = 1e-6, PD from eps = 1e-4 on
    system = _indefinite_system(device, lowest + 5e-5)
    outcomes = {}
    for name in ("dense", "sparse", backend):
        target = system if name == backend else _cpu(system)
        outcomes[name] = solve(
            target, free if name == backend else free.cpu(), backend=name, cg_tolerance=1e-10
        )
    for solution in outcomes.values():
        assert solution.status is SolveStatus.ESCALATED
        assert solution.attempts == 2 and solution.epsilon == pytest.approx(1e-4)
    # measured 6e-11 (pcg), 2e-12 (band)
    assert _relative_error(outcomes[backend].step, outcomes["dense"].step) < 1e-9
    # the first attempt stopped on a direction of negative curvature (after 14 / 9
    # iterations: the band level keeps this H's band positive definite)
    first, second = pcg.pcg_attempts(
        system, free, 0.0, 1e-6, 2, 1e-10, preconditioner=CG_BACKENDS[backend]
    )
    assert first.x is None and first.reason == "negative_curvature" and first.iterations > 0
    assert second.reason == "converged"
    assert outcomes[backend].cg_iterations == first.iterations + second.iterations


@pytest.mark.parametrize("backend", CG_BACKENDS)
@pytest.mark.parametrize("device", DEVICES)
def test_indefinite_diagonal_block_and_nan_fail_every_attempt(device, backend, caplog):
    free = _free(device)
    # a diagonal block with a negative eigenvalue below -eps_5 = -1e4: no CG iteration runs
    system = _indefinite_system(device, 1e6)
    with caplog.at_level(logging.WARNING, logger="como3r.optim.linear"):
        solution = solve(system, free, backend=backend, retries=6)
    assert solution.status is SolveStatus.FAILED and solution.attempts == 6
    assert solution.cg_iterations == 0 and torch.all(solution.step == 0)
    assert "zero step" in caplog.text
    reasons = {
        outcome.reason
        for outcome in pcg.pcg_attempts(
            system, free, 0.0, 1e-6, 3, preconditioner=CG_BACKENDS[backend]
        )
    }
    assert reasons == {"indefinite_block"}
    H_off = system.H_off.clone()
    H_off[3, 2, 5] = float("nan")
    broken = BlockSystem(_system(False, device).H_diag, system.off_i, system.off_j, H_off, system.g)
    solution = solve(broken, free, backend=backend, retries=3)
    assert solution.status is SolveStatus.FAILED and torch.all(solution.step == 0)


def test_iteration_cap_returns_the_last_iterate(caplog):
    system, free = _system(True, "cpu"), _free("cpu")
    dense = solve(system, free, backend="dense").step
    errors = []
    for cap in (1, 2, 4):
        with caplog.at_level(logging.DEBUG, logger="como3r.optim.pcg"):
            solution = solve(system, free, backend="pcg", cg_max_iterations=cap)
        assert solution.status is SolveStatus.SUCCESS and solution.attempts == 1
        assert solution.cg_iterations == cap
        errors.append(_relative_error(solution.step, dense))
    assert "at the cap" in caplog.text
    # truncated, but improving (measured 0.30, 0.094, 0.0083; 8 iterations converge)
    assert errors[0] > errors[1] > errors[2] > 4e-3
    # the default cap, max(100, 7F), is never reached here
    assert solve(system, free, backend="pcg", cg_tolerance=0.0).cg_iterations == max(
        pcg.CG_MIN_ITERATION_CAP, 7 * (NUM_POSES - len(PINNED))
    )


def test_pcg_arguments_are_validated():
    system, free = _system(False, "cpu"), _free("cpu")
    with pytest.raises(InputError, match="cg_max_iterations"):
        solve(system, free, backend="pcg", cg_max_iterations=0)
    with pytest.raises(InputError, match="cg_tolerance"):
        solve(system, free, backend="pcg", cg_tolerance=-1.0)
    with pytest.raises(InputError, match="pcg"):
        solve(system, free, backend="cg")
    # no free pose: a zero step without any iteration
    solution = solve(system, torch.zeros(NUM_POSES, dtype=torch.bool), backend="pcg")
    assert solution.status is SolveStatus.SUCCESS and solution.cg_iterations == 0
