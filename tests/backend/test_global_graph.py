"""The unified multi-agent factor graph and its global Sim(3) BA (C-Sec. 3.5, A.3)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

import como3r.backend.global_graph as global_graph
import como3r.frontend.graph as graph_module
from como3r.backend.global_graph import GlobalGraph
from como3r.config import DepthRefinementConfig, GlobalBAConfig, TrackingConfig
from como3r.errors import InputError
from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse, sim3_log
from como3r.geometry.units import scene_depth
from como3r.optim.optimizer import SolveReport
from como3r.optim.values import PoseValues
from como3r.prior.base import Encoding

H, W = 6, 8


def _world_points() -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.randn(H * W, 3, generator=g) * torch.tensor([3.0, 2.0, 1.0]) + torch.tensor(
        [0.0, 0.0, 8.0]
    )


def _identity_matches(valid: bool = True) -> DirectedMatches:
    """Every pixel of j matched to the same pixel of i (all views see the same points)."""
    return DirectedMatches(
        idx=torch.arange(H * W), valid=torch.full((H * W,), valid), q=torch.full((H * W,), 2.0)
    )


def _packet(
    agent: int, kf_id: int, T_true: torch.Tensor, T_init: torch.Tensor, sequential: bool = True
) -> KeyframePacket:
    X = sim3_act(sim3_inverse(T_true)[None], _world_points()).reshape(H, W, 3)
    link = _identity_matches() if sequential and kf_id > 0 else None
    return KeyframePacket(
        agent=agent,
        kf_id=kf_id,
        frame_index=kf_id,
        timestamp=float(kf_id),
        T_WC=T_init,
        X_hat=X,
        C_hat=torch.full((H, W), 5.0),
        colors=np.zeros((H, W, 3), np.uint8),
        encoding=Encoding(agent, kf_id, (H, W)),
        retrieval=None,
        sequential_ij=link,
        sequential_ji=link,
        previous=None,
    )


def _true_pose(agent: int, kf_id: int) -> torch.Tensor:
    tau = torch.tensor([0.3 * kf_id + agent, 0.1 * agent, 0.0, 0.0, 0.02 * kf_id, 0.0, 0.0])
    return sim3_exp(tau)


def _perturbation(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return sim3_exp(
        torch.randn(7, generator=g) * torch.tensor([0.1, 0.1, 0.1, 0.02, 0.02, 0.02, 0.02])
    )


@pytest.fixture
def two_agents() -> tuple[GlobalGraph, dict[tuple[int, int], torch.Tensor]]:
    """Agents 0 and 1 with three keyframes each, perturbed, and one inter-agent link."""
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    truth = {}
    for kf_id in range(3):
        for agent in (0, 1):
            T = _true_pose(agent, kf_id)
            truth[(agent, kf_id)] = T
            noisy = (
                T
                if (agent, kf_id) == (0, 0)
                else sim3_compose(_perturbation(10 * agent + kf_id), T)
            )
            graph.add_keyframe(_packet(agent, kf_id, T, noisy))
    link = PairLink(_identity_matches(), _identity_matches())
    graph.add_inter_link(graph.global_index(0, 2), graph.global_index(1, 0), link, 0.1)
    return graph, truth


def _pose_errors(graph: GlobalGraph, truth) -> torch.Tensor:
    errors = []
    for g, kf in enumerate(graph.keyframes):
        T_true = truth[(graph.agent_of[g], kf.kf_id)]
        errors.append(sim3_log(sim3_compose(kf.T_WC, sim3_inverse(T_true)).double()).norm())
    return torch.stack(errors)


def test_flat_index_side_map_and_local_to_global(two_agents) -> None:
    graph, _ = two_agents
    assert len(graph) == 6
    assert graph.agent_of == [0, 1, 0, 1, 0, 1]
    assert graph.local_to_global == {0: [0, 2, 4], 1: [1, 3, 5]}
    kinds = [link.kind for link in graph.links]
    assert kinds.count("sequential") == 4 and kinds.count("inter") == 1
    assert [(link.i, link.j) for link in graph.inter_links()] == [(4, 1)]


@pytest.mark.parametrize("linear_solver", ["auto", "pcg", "band"])
def test_global_ba_reduces_error_with_keyframe_zero_pinned(two_agents, linear_solver) -> None:
    graph, truth = two_agents
    graph.config = GlobalBAConfig(linear_solver=linear_solver)
    anchor_before = graph.keyframes[0].T_WC.clone()
    before = _pose_errors(graph, truth)
    result = graph.optimize([0, 1], anchor=0, max_iters=30)
    after = _pose_errors(graph, truth)
    assert result.moved and not result.restored
    assert result.keyframes == tuple(range(6))
    assert torch.equal(graph.keyframes[0].T_WC, anchor_before)
    assert float(after.max()) < 1e-3 < float(before.max())


def test_only_keyframes_connected_to_the_anchor_move(two_agents) -> None:
    graph, truth = two_agents
    T = _true_pose(0, 3)
    cut = graph.add_keyframe(_packet(0, 3, T, sim3_compose(_perturbation(7), T), sequential=False))
    pose = graph.keyframes[cut].T_WC.clone()
    result = graph.optimize([0, 1], anchor=0, max_iters=5)
    assert cut not in result.keyframes
    assert torch.equal(graph.keyframes[cut].T_WC, pose)


def test_divergence_guard_restores_the_previous_poses(two_agents, monkeypatch) -> None:
    graph, _ = two_agents
    before = graph.poses(range(6)).clone()

    def blow_up(factors, values, config, max_iters, backend, length_scale):
        poses = values.poses.clone()
        poses[3, 0] = float("nan")
        return PoseValues(poses, values.pinned), SolveReport(iterations=1)

    monkeypatch.setattr(global_graph, "gauss_newton_irls", blow_up)
    result = graph.optimize([0, 1], anchor=0, max_iters=5)
    assert result.restored and not result.moved
    assert torch.equal(graph.poses(range(6)), before)


def test_divergence_guard_rejects_implausible_jumps(two_agents, monkeypatch) -> None:
    graph, _ = two_agents
    before = graph.poses(range(6)).clone()

    def jump(factors, values, config, max_iters, backend, length_scale):
        poses = values.poses.clone()
        poses[5, :3] += 1e4
        return PoseValues(poses, values.pinned), SolveReport(iterations=3)

    monkeypatch.setattr(global_graph, "gauss_newton_irls", jump)
    assert graph.optimize([0, 1], anchor=0, max_iters=5).restored
    assert torch.equal(graph.poses(range(6)), before)


def test_depth_step_pulls_a_distorted_keyframe_back_and_keeps_the_anchor(two_agents) -> None:
    graph, truth = two_agents
    for g, kf in enumerate(graph.keyframes):
        kf.T_WC = truth[(graph.agent_of[g], kf.kf_id)].clone()
    distorted = graph.global_index(1, 1)
    X_true = graph.keyframes[distorted].X_hat.clone()
    graph.keyframes[distorted].X_hat = X_true * 1.05
    graph.freeze_refinement_base([0, 1])
    anchor_X = graph.keyframes[0].X_hat
    config = DepthRefinementConfig(variant="pixel")
    labels = graph.segment([0, 1], 0, config)
    assert sorted(labels) == list(range(6))

    for _ in range(5):
        report = graph.refine_depths([0, 1], 0, config, labels)

    log_error = (graph.keyframes[distorted].X_hat.norm(dim=-1) / X_true.norm(dim=-1)).log()
    assert float(log_error.abs().max()) < 0.01  # from log(1.05) = 0.049
    assert report.max_change < 0.01
    assert graph.keyframes[0].X_hat is anchor_X


def test_calibrated_keyframes_use_the_pixel_and_log_depth_residual(monkeypatch) -> None:
    """Packets of a calibrated run carry K: the global BA then solves C-Eq. 17."""
    K = torch.tensor([[40.0, 0.0, 4.0], [0.0, 40.0, 3.0], [0.0, 0.0, 1.0]])
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    truth = {}
    for kf_id in range(3):
        T = _true_pose(0, kf_id)
        truth[(0, kf_id)] = T
        noisy = T if kf_id == 0 else sim3_compose(_perturbation(kf_id), T)
        graph.add_keyframe(dataclasses.replace(_packet(0, kf_id, T, noisy), K=K))
    assert all(torch.equal(kf.K, K) for kf in graph.keyframes)
    seen = []
    build = global_graph.build_factors

    def spy(*args, **kwargs):
        factors = build(*args, **kwargs)
        seen.append(type(factors).__name__)
        return factors

    monkeypatch.setattr(global_graph, "build_factors", spy)
    result = graph.optimize([0], anchor=0, max_iters=50)
    assert seen and set(seen) == {"CalibratedFactors"}
    assert result.moved and float(_pose_errors(graph, truth).max()) < 1e-3


def test_keyframes_must_arrive_in_order() -> None:
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    T = _true_pose(0, 0)
    graph.add_keyframe(_packet(0, 0, T, T))
    with pytest.raises(InputError, match="agent 0 sent keyframe 2"):
        graph.add_keyframe(_packet(0, 2, T, T))
    with pytest.raises(InputError, match="never received"):
        graph.global_index(1, 0)
    with pytest.raises(InputError, match="two agents"):
        graph.add_inter_link(0, 0, PairLink(_identity_matches(), _identity_matches()), 0.0)


def _uncached_depth(graph: GlobalGraph, agents: list[int]) -> float:
    members = [graph.keyframes[g] for a in agents for g in graph.agent_keyframes(a)]
    return scene_depth([kf.T_WC for kf in members], [kf.X_hat for kf in members])


def test_scene_depth_keeps_median_ranges_until_a_pointmap_changes(two_agents) -> None:
    """The graph's scene depth equals geometry.units.scene_depth bit for bit, after poses
    move (scales are read each time) and after a refresh or a pointmap written by the depth
    step (each makes the keyframe's median range again); a pointmap swapped without a new
    version keeps the kept range (what the version is for)."""
    graph, _ = two_agents
    own = graph.agent_keyframes(1)
    first = graph.scene_depth([1])
    assert first == _uncached_depth(graph, [1])
    for g in own:
        graph.keyframes[g].T_WC = graph.keyframes[g].T_WC.clone()
        graph.keyframes[g].T_WC[7] *= 3.0
    assert graph.scene_depth([1]) == _uncached_depth(graph, [1]) == pytest.approx(3 * first)
    for kf_id, g in enumerate(own):
        kf = graph.keyframes[g]
        graph.refresh(1, PointmapRefresh(kf_id, kf.X_hat * 4.0, kf.C_hat, 2))
    assert graph.scene_depth([1]) == _uncached_depth(graph, [1]) == pytest.approx(12 * first)
    assert graph.scene_depth([0, 1]) == _uncached_depth(graph, [0, 1])
    for g in own:  # no new version: the kept ranges stay
        graph.keyframes[g].X_hat = graph.keyframes[g].X_hat * 0.5
    assert graph.scene_depth([1]) == pytest.approx(12 * first)
    for g in own:
        graph._set_pointmaps(g, {"X_hat": graph.keyframes[g].X_hat}, None)  # the depth step
    assert graph.scene_depth([1]) == _uncached_depth(graph, [1]) == pytest.approx(6 * first)


@pytest.mark.parametrize("max_matches", [0, 48, 20, 7, 1])
def test_thinned_edges_keep_an_even_subset_and_weigh_the_rest(max_matches) -> None:
    valid = torch.ones(H * W, dtype=torch.bool)
    valid[::5] = False  # 38 valid matches of 48
    edge = graph_module.Edge(0, 1, DirectedMatches(torch.arange(H * W), valid, torch.ones(H * W)))
    kept, weight = graph_module.thinned(edge, max_matches)
    count = int(kept.matches.valid.sum())
    if max_matches in (0, 48):
        assert kept is edge and weight == 1.0
        return
    assert count <= max_matches and bool((kept.matches.valid <= valid).all())
    assert weight == pytest.approx(38 / count)
    positions = torch.nonzero(kept.matches.valid).flatten()
    assert int(positions[0]) <= 1  # from the first valid match on, spread evenly
    if count > 1:
        assert int(positions.diff().max()) <= 2 * 38 // count + 2


def test_a_thinned_solve_lands_near_the_full_one_and_keeps_its_own_models(two_agents) -> None:
    """Thinned to a third of each edge's matches (weighed back), the BA ends within a
    small fraction of the full solve's correction; its edge models are stamped with the
    thinning, so a full solve after it linearizes every edge over all matches again."""
    graph, truth = two_agents
    full = copy.deepcopy(graph)
    before = _pose_errors(graph, truth)
    full.optimize([0, 1], anchor=0, max_iters=30)
    thin = graph.optimize([0, 1], anchor=0, max_iters=30, max_matches=16)
    assert thin.moved and not thin.restored
    after_full, after_thin = _pose_errors(full, truth), _pose_errors(graph, truth)
    assert float(after_thin.max()) < 1e-3 < float(before.max())
    assert float((after_thin - after_full).abs().max()) < 1e-3
    linearized = []
    original = global_graph.GlobalGraph._factors

    def counted(self, edges, positions, row, max_matches, points):
        linearized.append((len(positions), max_matches))
        return original(self, edges, positions, row, max_matches, points)

    global_graph.GlobalGraph._factors = counted
    try:
        graph.optimize([0, 1], anchor=0, max_iters=1)
    finally:
        global_graph.GlobalGraph._factors = original
    assert linearized and linearized[0] == (2 * len(graph.links), 0)
