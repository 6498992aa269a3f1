"""The joint pose and focal solve of the global BA (:mod:`como3r.backend.focal_factors`).

:func:`solve_focal_step` solves the normal equations of a :class:`FocalSystem` by the Schur
complement on the few focal variables: with ``Y = H_pp^-1 [H_pf, g_p]`` from ``A + 1``
solves of the pose system (:func:`como3r.optim.linear.solve`, any backend, Tikhonov
escalation of C-Sec. B.2), ``S = H_ff - H_pf^T Y_f`` and ``b = g_f - H_pf^T Y_g`` give the
focal step ``delta = -S^-1 b`` and the pose step ``tau = -(Y_g + Y_f delta)`` (C-Eq. 25).
:func:`gauss_newton_focal` iterates it (Gauss-Newton with Huber IRLS, as
:func:`~como3r.optim.optimizer.gauss_newton_irls`); :func:`optimize_focal` runs it over a
component of the :class:`~como3r.backend.global_graph.GlobalGraph`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from como3r.backend.focal_factors import FocalEdgeFactors, FocalPrior, FocalSystem, FocalValues
from como3r.backend.global_graph import GlobalGraph
from como3r.config import GlobalBAConfig
from como3r.errors import InputError
from como3r.frontend.paging import KeyframeParking, solve_points
from como3r.optim.linear import Backend, SolveStatus, solve
from como3r.optim.values import PoseValues

logger = logging.getLogger(__name__)

#: A focal step larger than this in log focal (about 35 %) is the product of a blown-up
#: system, not a linearization step: the solve stops and keeps the previous values.
MAX_LOG_FOCAL_STEP = 0.3

#: The joint solve stops once no focal length moves by more than this (log focal, 0.1 %):
#: the poses then converge in the component's ordinary pose passes (C-Sec. A.7), whose
#: iterations cost a tenth of a joint one (the compiled pose blocks alone).
FOCAL_STEP_TOL = 1e-3


@dataclass(frozen=True)
class FocalBAResult:
    """What a joint solve did.

    Attributes:
        log_focal: per agent, the log correction of its focal length (0 where held).
        iterations: Gauss-Newton iterations run.
        seconds: wall-clock time.
        reason: ``"step_tol"``, ``"max_iters"``, ``"solve_failed"``, ``"diverged"`` or
            ``"no_edges"``.
        max_translation_change: largest camera-centre move [world units].
    """

    log_focal: dict[int, float]
    iterations: int
    seconds: float
    reason: str
    max_translation_change: float


def solve_focal_step(
    system: FocalSystem,
    values: FocalValues,
    config: GlobalBAConfig,
    backend: Backend = "auto",
) -> tuple[Tensor, Tensor] | None:
    """The Gauss-Newton step ``(tau (N, 7), delta (A,))`` of a joint system, or None when a
    pose solve failed at every Tikhonov attempt."""
    free = values.poses.free
    keep = ~values.held
    columns = [int(c) for c in torch.nonzero(keep).flatten()]
    solves = []
    # solve() takes H tau = -g: the gradient -v gives H^-1 v
    for rhs in [system.poses.g] + [-system.H_pf[:, :, c] for c in columns]:
        solution = solve(
            replace(system.poses, g=rhs),
            free,
            lm_lambda=config.lm_lambda,
            tikhonov_base=config.tikhonov_base,
            retries=config.tikhonov_retries,
            backend=backend,
        )
        if solution.status is SolveStatus.FAILED:
            return None
        solves.append(solution.step)
    Y_g = -solves[0]  # H^-1 g_p
    delta = torch.zeros_like(system.g_f)
    tau = -Y_g
    if columns:
        Y_f = torch.stack(solves[1:], dim=-1)  # (N, 7, F)
        H_pf = system.H_pf[:, :, columns] * free[:, None, None]
        S = system.H_ff[columns][:, columns] - torch.einsum("nkc,nkd->cd", H_pf, Y_f)
        b = system.g_f[columns] - torch.einsum("nkc,nk->c", H_pf, Y_g)
        step = -torch.linalg.solve(0.5 * (S + S.T), b)
        delta[columns] = step
        tau = -(Y_g + Y_f @ step)
    return tau, delta


def gauss_newton_focal(
    factors: FocalEdgeFactors,
    prior: FocalPrior | None,
    values: FocalValues,
    config: GlobalBAConfig,
    max_iters: int,
    length_scale: float,
) -> tuple[FocalValues, int, str]:
    """Gauss-Newton with Huber IRLS over poses and focal corrections.

    Stops when ``||tau||`` (translations in units of ``length_scale``) and ``|delta|`` are
    both below ``config.step_tol`` or ``|delta|`` is below :data:`FOCAL_STEP_TOL`, or
    refuses a non-finite or implausibly large step (:data:`MAX_LOG_FOCAL_STEP`) and keeps
    the previous values.

    Returns:
        The values, the iterations run and the stop reason.
    """
    if max_iters < 1:
        raise InputError(f"gauss_newton_focal: max_iters must be >= 1, got {max_iters}")
    reason = "max_iters"
    iteration = 0
    for iteration in range(1, max_iters + 1):
        system = factors.linearize(values)
        if prior is not None:
            system = prior.add_to(system, values)
        step = solve_focal_step(system, values, config, config.linear_solver)
        if step is None:
            reason = "solve_failed"
            break
        tau, delta = step
        largest = float(torch.linalg.vector_norm(delta, ord=math.inf))
        finite = bool(tau.isfinite().all()) and math.isfinite(largest)
        if not finite or largest > MAX_LOG_FOCAL_STEP:
            logger.warning("joint focal BA: step %d refused; previous values kept", iteration)
            reason = "diverged"
            break
        values = values.retract(tau, delta)
        size = torch.cat([tau[:, :3] / length_scale, tau[:, 3:]], dim=-1).norm()
        logger.debug("joint focal BA %d: |tau| %.3e, |delta| %.3e", iteration, size, largest)
        if largest < FOCAL_STEP_TOL or (
            float(size) < config.step_tol and largest < config.step_tol
        ):
            reason = "step_tol"
            break
    return values, iteration, reason


def optimize_focal(
    graph: GlobalGraph,
    agents: Sequence[int],
    anchor: int,
    max_iters: int,
    prior_sigma: float,
    centres: dict[int, float] | None = None,
    max_matches: int = 0,
    parking: KeyframeParking | None = None,
) -> FocalBAResult:
    """Poses and one focal length per agent of a component in one solve (C-Eq. 5 with the
    residual of C-Eq. 17), then every agent moved onto its focal length
    (:meth:`GlobalGraph.rescale_focal`) and the poses written.

    Args:
        graph: the global graph (its keyframes carry intrinsics).
        agents: the component's agents; ``anchor``: its pinned keyframe.
        max_iters: Gauss-Newton iterations.
        prior_sigma: standard deviation [log focal] of the prior on each agent's focal
            length at its ``centres`` value (see :class:`FocalPrior`).
        centres: per agent, the focal length [px] the prior is centred on (its own
            self-calibration); missing agents: the focal length it holds now.
        max_matches: each edge built over an even subset of about this many of its valid
            matches, weighed by the share left out (``gauge.focal_max_matches``); 0: all.
        parking: where paged-out keyframes' rescaled pointmaps go
            (:meth:`GlobalGraph.rescale_focal`; None: into the keyframes).
    """
    start = time.perf_counter()
    nodes = graph.connected(agents, anchor)
    chosen = set(nodes)
    links = [link for link in graph.links if link.i in chosen and link.j in chosen]
    if not links:
        return FocalBAResult({}, 0, 0.0, "no_edges", 0.0)
    row = {g: r for r, g in enumerate(nodes)}
    cameras = sorted({graph.agent_of[g] for g in nodes})
    column = {agent: c for c, agent in enumerate(cameras)}
    factors = FocalEdgeFactors(
        [e for link in links for e in link.edges()],
        solve_points(graph.keyframes.__getitem__),
        row.__getitem__,
        lambda g: column[graph.agent_of[g]],
        graph.tracking,
        max_matches=max_matches,
    )
    stored = graph.poses(nodes)
    before = stored.double()
    pinned = torch.tensor([g == anchor or g in graph.fixed for g in nodes], device=before.device)
    held = torch.tensor(
        [any(g in graph.fixed for g in graph.agent_keyframes(a)) for a in cameras],
        device=before.device,
    )
    current = [graph.agent_focal(a) or math.nan for a in cameras]
    centre = torch.tensor(
        [math.log((centres or {}).get(a, f) / f) for a, f in zip(cameras, current)],
        dtype=torch.float64,
        device=before.device,
    )
    values = FocalValues(PoseValues(before, pinned), torch.zeros_like(centre), held)
    solved, iterations, reason = gauss_newton_focal(
        factors,
        FocalPrior(centre, prior_sigma),
        values,
        graph.config,
        max_iters,
        graph.scene_depth(agents),
    )
    if reason in ("diverged", "solve_failed") and iterations <= 1:
        return FocalBAResult({}, iterations, time.perf_counter() - start, reason, 0.0)
    after = solved.poses.poses
    graph.set_poses(nodes, after.to(stored.dtype))
    corrections = {a: float(solved.log_focal[column[a]]) for a in cameras}
    for agent, log_focal in corrections.items():
        if log_focal != 0.0:
            graph.rescale_focal(agent, log_focal, parking)
    change = float((after[:, :3] - before[:, :3]).norm(dim=-1).max())
    return FocalBAResult(corrections, iterations, time.perf_counter() - start, reason, change)
