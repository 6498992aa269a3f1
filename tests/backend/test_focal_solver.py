"""The joint pose and focal solve (backend.focal_factors, backend.focal_solver): the focal
rows of the normal equations against finite differences, and a focal length recovered."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from como3r.backend.focal_factors import (
    FocalEdgeFactors,
    FocalPrior,
    FocalValues,
    compiled_edge_blocks,
    edge_blocks,
    rescaled,
)
from como3r.backend.focal_solver import gauss_newton_focal, optimize_focal
from como3r.backend.global_graph import GlobalGraph
from como3r.backend.graph_link import GraphLink
from como3r.config import Config, GlobalBAConfig, TrackingConfig, apply_overrides
from como3r.coordination.focal_alignment import FocalAlignment
from como3r.coordination.stats import CoordinatorStats
from como3r.frontend.graph import Edge, build_factors
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.geometry.camera import rescale_focal
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_inverse
from como3r.geometry.residuals import huber_weight
from como3r.optim.values import PoseValues

H, W, F = 48, 64, 60.0


@dataclass(frozen=True)
class View:
    X_hat: torch.Tensor
    K: torch.Tensor | None


def _K(focal: float) -> torch.Tensor:
    return torch.tensor(
        [[focal, 0.0, (W - 1) / 2], [0.0, focal, (H - 1) / 2], [0.0, 0.0, 1.0]],
        dtype=torch.float64,
    )


def _render(T_WC: torch.Tensor) -> torch.Tensor:
    """``(H, W, 3)`` true camera-frame points of a room: a wall at z = 4 and a floor at
    y = 1, whichever a pixel's ray meets first."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    rays = torch.stack([(u - (W - 1) / 2) / F, (v - (H - 1) / 2) / F, torch.ones_like(u)], -1)
    centre = T_WC[:3]
    world = sim3_act(T_WC, rays.reshape(-1, 3)) - centre  # ray directions in the world
    to_wall = (4.0 - centre[2]) / world[:, 2]
    to_floor = torch.where(world[:, 1] > 1e-6, (1.0 - centre[1]) / world[:, 1], math.inf)
    depth = torch.minimum(to_wall, to_floor)  # along the z = 1 ray, so z = depth
    return (rays.reshape(-1, 3) * depth[:, None]).reshape(H, W, 3)


def _matches(T_WC_i: torch.Tensor, T_WC_j: torch.Tensor, X_j: torch.Tensor) -> DirectedMatches:
    """Pixel of i (nearest) for each pixel of j, valid where inside i's image."""
    x = sim3_act(sim3_inverse(T_WC_i), sim3_act(T_WC_j, X_j.reshape(-1, 3)))
    u = F * x[:, 0] / x[:, 2] + (W - 1) / 2
    v = F * x[:, 1] / x[:, 2] + (H - 1) / 2
    ui, vi = u.round().long(), v.round().long()
    valid = (x[:, 2] > 0) & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    idx = torch.where(valid, vi * W + ui, torch.zeros_like(ui))
    return DirectedMatches(idx, valid, torch.full((H * W,), 2.0, dtype=torch.float64))


def _scene(believed: list[float]) -> tuple[list[View], torch.Tensor, list[Edge]]:
    """Three keyframes, cameras 0, 0 and 1, panning and moving; keyframe k's pointmap on
    the rays of ``believed[camera]`` (a self-calibration that is off)."""
    tangents = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [0.3, 0.0, 0.1, 0.0, 0.15, 0.0, 0.0],
            [0.6, 0.1, 0.0, 0.05, 0.3, 0.0, 0.0],
        ],
        dtype=torch.float64,
    )
    poses = sim3_exp(tangents)
    cameras = [0, 0, 1]
    views = []
    for k, camera in enumerate(cameras):
        X_true = _render(poses[k])
        X, K = rescale_focal(X_true, _K(F), math.log(believed[camera] / F))
        views.append(View(X, K))
    edges = [
        Edge(i, j, _matches(poses[i], poses[j], _render(poses[j])))
        for i, j in ((0, 1), (1, 0), (1, 2), (2, 1), (0, 2), (2, 0))
    ]
    return views, poses, edges


@pytest.mark.parametrize("path", ["compiled", "pytorch"])
def test_focal_rows_match_finite_differences(path: str) -> None:
    """The focal gradient is the derivative of the robust energy of C-Eq. 17 with each
    camera's focal length moved (pointmap and intrinsics, :func:`rescale_focal`), and the
    focal Hessian is J^T W J of the whitened residuals' finite-difference Jacobian with the
    Huber-IRLS weights W; by the compiled CPU loop and by PyTorch."""
    views, poses, edges = _scene([F, F * 1.04])
    tracking = TrackingConfig()
    edge = [edges[2]]  # keyframe 1 (camera 0) <- keyframe 2 (camera 1)
    cameras = [0, 0, 1]
    row = {0: 0, 1: 1, 2: 2}.__getitem__

    def built(log_focal: list[float]):  # type: ignore[no-untyped-def]
        def view(k: int) -> View:
            X, K = rescale_focal(views[k].X_hat, views[k].K, log_focal[cameras[k]])
            return View(X, K)

        return build_factors(edge, view, row, tracking)

    factors = built([0.0, 0.0])
    if path == "compiled":
        one = torch.ones(1, dtype=torch.float64)
        Hb, g, _ = compiled_edge_blocks(factors, poses, one, one, tracking)
    else:
        Hb, g, _ = edge_blocks(factors, poses, slice(0, 1), tracking)
    h = 1e-5
    r0 = factors.whitened_residual(poses)[0].double()
    for side, camera in ((0, 0), (1, 1)):
        plus = [0.0, 0.0]
        minus = [0.0, 0.0]
        plus[camera], minus[camera] = h, -h
        numeric = (built(plus).cost(poses) - built(minus).cost(poses)) / (2 * h)
        assert float(g[0, 7 + side]) == pytest.approx(float(numeric), rel=1e-3)
        r_plus = built(plus).whitened_residual(poses)[0]
        r_minus = built(minus).whitened_residual(poses)[0]
        J = (r_plus - r_minus).double() / (2 * h)
        expected = (huber_weight(r0, tracking.huber_k) * J * J).sum()  # IRLS, C-Eq. 8
        assert float(Hb[0, 7 + side, 7 + side]) == pytest.approx(float(expected), rel=2e-2)


def test_blocks_at_trial_corrections_are_those_of_the_rescaled_keyframes() -> None:
    """The factors built once on the keyframes as held, at trial corrections (the compiled
    loop's per-edge factors, or :func:`rescaled`), give the blocks of factors built on the
    keyframes moved to those focal lengths (what the solve rebuilt every iteration before),
    the compiled loop and PyTorch alike (float64 pointmaps: to rounding)."""
    views, poses, edges = _scene([F, F * 1.04])
    tracking = TrackingConfig()
    cameras, row = [0, 0, 1], {0: 0, 1: 1, 2: 2}.__getitem__
    log_focal = [0.03, -0.05]

    def moved(k: int) -> View:
        X, K = rescale_focal(views[k].X_hat, views[k].K, log_focal[cameras[k]])
        return View(X, K)

    held = build_factors(edges, views.__getitem__, row, tracking)
    rebuilt = build_factors(edges, moved, row, tracking)
    phi = torch.tensor(log_focal, dtype=torch.float64)
    scale_i = phi[[cameras[e.i] for e in edges]].exp()
    scale_j = (-phi[[cameras[e.j] for e in edges]]).exp()
    every = slice(0, len(edges))
    H_ref, g_ref, _ = edge_blocks(rebuilt, poses, every, tracking)
    H_c, g_c, _ = compiled_edge_blocks(held, poses, scale_i, scale_j, tracking)
    H_t, g_t, _ = edge_blocks(rescaled(held, scale_i, scale_j), poses, every, tracking)
    scale = H_ref.abs().amax(dim=(1, 2), keepdim=True)
    for H, g in ((H_c, g_c), (H_t, g_t)):
        assert torch.allclose(H / scale, H_ref / scale, atol=1e-9)
        assert torch.allclose(g / scale[..., 0], g_ref / scale[..., 0], atol=1e-9)
    assert float(g_ref[:, 7:].abs().max()) > 1e-3 * float(scale.max())  # the focal rows count


@pytest.mark.parametrize("held", [True, False])
def test_recovers_a_camera_focal_length(held: bool) -> None:
    """Camera 1 self-calibrated 6 % long: the joint solve from the ground-truth poses brings
    it within 1 % of camera 0's focal length (held, or free under a loose prior: the edges
    fix the ratio), and a held camera keeps its own."""
    views, poses, edges = _scene([F, F * 1.06])
    cameras = [0, 0, 1]
    factors = FocalEdgeFactors(
        edges,
        views.__getitem__,
        {0: 0, 1: 1, 2: 2}.__getitem__,
        cameras.__getitem__,
        TrackingConfig(),
    )
    values = FocalValues(
        PoseValues.from_poses(poses.clone(), 1),
        torch.zeros(2, dtype=torch.float64),
        torch.tensor([held, False]),
    )
    prior = FocalPrior(torch.zeros(2, dtype=torch.float64), 0.2)
    solved, _, reason = gauss_newton_focal(factors, prior, values, GlobalBAConfig(), 20, 4.0)
    assert reason == "step_tol"
    focal = [
        F * math.exp(float(solved.log_focal[0])),
        F * 1.06 * math.exp(float(solved.log_focal[1])),
    ]
    assert focal[1] / focal[0] == pytest.approx(1.0, abs=0.01)
    assert (float(solved.log_focal[0]) == 0.0) == held


@pytest.mark.parametrize("path", ["compiled", "pytorch"])
def test_thinned_edges_weigh_their_blocks_back_and_solve_alike(path: str) -> None:
    """Edges built over an even third of their matches, weighed back: the joint normal
    equations keep the full ones' scale, and the recovered focal ratio is theirs within
    0.2 %."""
    views, poses, edges = _scene([F, F * 1.06])
    count = min(int(e.matches.valid.sum()) for e in edges)
    solved, systems = [], []
    for max_matches in (0, count // 3):
        factors = FocalEdgeFactors(
            edges,
            views.__getitem__,
            {0: 0, 1: 1, 2: 2}.__getitem__,
            [0, 0, 1].__getitem__,
            TrackingConfig(),
            compiled=path == "compiled",
            max_matches=max_matches,
        )
        assert (max_matches == 0) == all(b.weight is None for b in factors.batches)
        values = FocalValues(
            PoseValues.from_poses(poses.clone(), 1),
            torch.zeros(2, dtype=torch.float64),
            torch.tensor([True, False]),
        )
        systems.append(factors.linearize(values))
        prior = FocalPrior(torch.zeros(2, dtype=torch.float64), 0.2)
        solved.append(gauss_newton_focal(factors, prior, values, GlobalBAConfig(), 20, 4.0)[0])
    full, thin = systems
    assert float(thin.H_ff[1, 1]) == pytest.approx(float(full.H_ff[1, 1]), rel=0.2)
    ratios = [math.exp(float(v.log_focal[1])) for v in solved]
    assert ratios[1] == pytest.approx(ratios[0], rel=2e-3)
    assert ratios[0] == pytest.approx(1 / 1.06, abs=0.01)


def _graph() -> GlobalGraph:
    """The scene's three keyframes on the coordinator's graph (agents 0, 0, 1), linked."""
    views, poses, _ = _scene([F, F * 1.06])
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    for k, agent in enumerate([0, 0, 1]):
        X = views[k].X_hat.float()
        C = torch.ones(H, W)
        colors = np.zeros((H, W, 3), np.uint8)
        kf_id = len(graph.agent_keyframes(agent))
        K = views[k].K.float()
        graph.append(
            Keyframe(kf_id, k, float(k), None, poses[k].float(), X, C, X, C, colors, K=K), agent
        )
    renders = [_render(p) for p in poses]
    for i, j, kind in ((0, 1, "sequential"), (1, 2, "inter"), (0, 2, "inter")):
        link = PairLink(
            _matches(poses[i], poses[j], renders[j]), _matches(poses[j], poses[i], renders[i])
        )
        graph.links.append(GraphLink(i, j, kind, link))
    return graph


def test_optimize_focal_moves_each_agent_onto_its_solved_focal_length() -> None:
    """On the coordinator's graph: agent 1's keyframe, 6 % long, comes back within 1 % of
    agent 0's focal length; the keyframes' intrinsics and pointmaps are moved
    (:meth:`GlobalGraph.rescale_focal`) and the anchor keeps its pose."""
    graph = _graph()
    anchor = graph.poses([0]).clone()
    result = optimize_focal(graph, [0, 1], 0, 20, 0.2)
    assert result.reason == "step_tol"
    assert set(result.log_focal) == {0, 1}
    focal = [graph.agent_focal(0), graph.agent_focal(1)]
    assert focal[1] / focal[0] == pytest.approx(1.0, abs=0.01)
    assert float(graph.keyframes[2].K[1, 1]) == pytest.approx(focal[1])
    assert torch.equal(graph.poses([0]), anchor)


@pytest.mark.parametrize("focal_ba", [True, False])
def test_the_coordinators_terminal_focal_step_follows_gauge_focal_ba(focal_ba: bool) -> None:
    """``gauge.focal_ba``: the terminal focal step of a component is the joint solve (each
    moved agent counted as a refinement); without it, the chain over admitted candidates
    (none here: nothing moves)."""
    config = apply_overrides(Config(), [f"gauge.focal_ba={str(focal_ba).lower()}"])

    class Part(FocalAlignment):
        def __init__(self) -> None:
            self.config, self.graph, self.candidates = config, _graph(), []
            self.stats = CoordinatorStats()

        def _anchor(self, root: int) -> int:
            return self.graph.global_index(root, 0)

    part = Part()
    before = part.graph.agent_focal(1)
    part._refine_focals([0, 1])
    moved = part.graph.agent_focal(1) != before
    assert moved == focal_ba
    assert (part.stats.focal_refinements > 0) == focal_ba


def test_a_resumed_session_centres_the_prior_on_the_agents_own_focal_lengths(tmp_path) -> None:
    """Each agent's own self-calibration (the prior's centre) is kept in the session store:
    after a merge moved agent 1 onto agent 0's focal length, a session read back solves the
    focal BA to the uninterrupted result; centred on the focal lengths the agents hold (what
    a resumed run did before the store kept them) it ends elsewhere."""
    from como3r.coordination.coordinator import Coordinator
    from como3r.store.reader import read_session
    from como3r.store.writer import SessionStore

    graph = _graph()
    graph.own_focal = {0: F, 1: F * 1.06}  # as each agent's keyframes said (add_keyframe)
    graph.rescale_focal(1, math.log(1 / 1.06))  # a merge's alignment
    coordinator = Coordinator(None, Config(), None, 2)  # type: ignore[arg-type]
    coordinator.graph = graph
    coordinator.stats.keyframes = len(graph)
    path = tmp_path / "session.db"
    with SessionStore.create(path, Config(), coordinator):
        pass
    resumed, lost = read_session(path).graph, read_session(path).graph
    assert resumed.own_focal == graph.own_focal
    assert resumed.agent_focal(1) == pytest.approx(F, rel=1e-6)
    results = []
    for solved in (graph, resumed, lost):
        centres = {} if solved is lost else solved.own_focal
        optimize_focal(solved, [0, 1], 0, 20, 0.05, centres)
        results.append((solved.agent_focal(0), solved.agent_focal(1), solved.poses([0, 1, 2])))
    (f0, f1, poses), (g0, g1, resumed_poses), (h0, _, _) = results
    assert (g0, g1) == pytest.approx((f0, f1), rel=1e-9)
    assert torch.allclose(resumed_poses, poses, atol=1e-6)
    # the centre matters (the edges fix this scene's focal lengths but for 5e-4): centred
    # on the focal lengths held, the solve ends elsewhere
    assert abs(h0 / f0 - 1) > 1e-4
