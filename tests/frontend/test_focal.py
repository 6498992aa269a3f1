"""One focal length across agents: the estimate at a merge and the graph's rescaling."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from como3r.backend.global_graph import GlobalGraph
from como3r.config import Config, GlobalBAConfig, TrackingConfig, apply_overrides
from como3r.coordination.association import Candidate, Verification
from como3r.coordination.coordinator import Coordinator
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.frontend import focal as focal_module
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.calibration import keyframe_pairs
from como3r.frontend.focal import FocalPair, estimate_log_focal, relative_pose
from como3r.frontend.keyframes import apply_pose_update
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PoseUpdate
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.geometry.camera import intrinsics_matrix, project, rescale_focal, unproject_depth
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_identity
from como3r.optim.optimizer import gauss_newton_irls
from como3r.prior.base import Encoding
from como3r.prior.simulated import SimulatedPrior

H, W = 36, 48


def _camera() -> torch.Tensor:
    return intrinsics_matrix(40.0, 40.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)


def _depth(shift: float) -> torch.Tensor:
    """A smooth non-planar surface about 3 units away (depth varies by a third)."""
    v, u = torch.meshgrid(
        torch.linspace(-1, 1, H, dtype=torch.float64),
        torch.linspace(-1, 1, W, dtype=torch.float64),
        indexing="ij",
    )
    return 3.0 + 0.6 * torch.sin(2.0 * u + shift) * torch.cos(1.5 * v) + 0.4 * u


def _pair(moving_focal_error: float, anchor_focal_error: float = 0.0) -> FocalPair:
    """Two views of one surface; each pointmap on the rays of its own wrong focal length.

    The moving keyframe sees a smooth surface; each of its pixels lands on an anchor pixel,
    which holds that very point (so both match directions are exact up to the pixel
    rounding, which the calibrated residual does not see): only the focal lengths disagree.
    """
    K = _camera()
    T_am = sim3_exp(torch.tensor([0.4, 0.05, 0.1, 0.02, -0.12, 0.03, 0.0], dtype=torch.float64))
    X_m = unproject_depth(_depth(0.3), K).reshape(-1, 3)
    X_m_in_a = sim3_act(T_am, X_m)
    uv = project(X_m_in_a, K).round().long()
    landed = (
        (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H) & (X_m_in_a[:, 2] > 0)
    )
    idx = uv[:, 1].clamp(0, H - 1) * W + uv[:, 0].clamp(0, W - 1)
    owner = torch.full((H * W,), -1, dtype=torch.int64)
    pixels = torch.nonzero(landed).flatten()
    owner[idx[pixels]] = pixels  # one moving pixel per anchor pixel
    X_a = unproject_depth(_depth(0.0), K).reshape(-1, 3).clone()
    X_a[owner >= 0] = X_m_in_a[owner[owner >= 0]]
    q = torch.full((H * W,), 2.0, dtype=torch.float64)
    in_anchor = DirectedMatches(idx=idx, valid=landed & (owner[idx] == torch.arange(H * W)), q=q)
    in_moving = DirectedMatches(idx=owner.clamp_min(0), valid=owner >= 0, q=q)
    X_a_wrong, K_a = rescale_focal(X_a.reshape(H, W, 3), K, anchor_focal_error)
    X_m_wrong, K_m = rescale_focal(X_m.reshape(H, W, 3), K, moving_focal_error)
    return FocalPair(X_a_wrong, X_m_wrong, K_a, K_m, T_am, in_anchor, in_moving)


def test_rescale_focal_keeps_pixels_and_depths() -> None:
    K = _camera()
    X = unproject_depth(_depth(0.0), K)
    X2, K2 = rescale_focal(X, K, 0.1)
    assert torch.allclose(project(X2, K2), project(X, K), atol=1e-9)
    assert torch.equal(X2[..., 2], X[..., 2])
    assert float(K2[0, 0]) == pytest.approx(40.0 * math.exp(0.1))
    assert torch.equal(K2[:2, 2], K[:2, 2])
    X0, K0 = rescale_focal(X, K, 0.0)
    assert torch.equal(X0, X) and torch.equal(K0, K)


@pytest.mark.parametrize("error", [0.08, -0.1])
def test_estimate_recovers_the_moving_focal_error(error: float) -> None:
    estimate = estimate_log_focal([_pair(error)], TrackingConfig())
    # the moving keyframe believes in f exp(error): the correction is -error
    assert estimate.log_focal == pytest.approx(-error, abs=0.01)
    assert estimate.energy_gain > 0
    # 6 Gauss-Newton iterations here (the relative solve at zero's 3, then the joint
    # solve's); Brent's search over the correction ran 8 relative solves of 2-4 each
    assert estimate.evaluations <= 12


def _scaled(pair: FocalPair, scale: float) -> FocalPair:
    """The same pair in a scene ``scale`` times as large."""
    T = pair.T_anchor_moving.clone()
    T[:3] *= scale
    return replace(
        pair, X_anchor=scale * pair.X_anchor, X_moving=scale * pair.X_moving, T_anchor_moving=T
    )


@pytest.mark.parametrize("scale", [0.001, 1000.0])
def test_estimate_is_the_same_at_every_scene_scale(scale: float, monkeypatch) -> None:
    """The relative solves stop at a step measured in the pairs' depths: the same
    Gauss-Newton iterations at every scale (an absolute tolerance took 2-5 per solve at
    1000 times the scene, 2-4 at 1)."""
    iterations: list[int] = []
    solve = focal_module.gauss_newton_irls

    def counted(*args, **kwargs):
        result = solve(*args, **kwargs)
        iterations.append(result[1].iterations)
        return result

    monkeypatch.setattr(focal_module, "gauss_newton_irls", counted)
    pair = _pair(0.08)
    reference = estimate_log_focal([pair], TrackingConfig())
    reference_iterations, iterations[:] = list(iterations), []
    estimate = estimate_log_focal([_scaled(pair, scale)], TrackingConfig())
    assert estimate.log_focal == pytest.approx(reference.log_focal, abs=1e-4)
    assert iterations == reference_iterations
    assert estimate.evaluations == reference.evaluations  # the joint solve's too


def test_the_correction_column_is_the_energy_gradient() -> None:
    """The joint solve's focal entries (the compiled focal blocks, optim.focal_kernels): its
    gradient entry is the energy's derivative in ``delta`` at fixed poses, for a merge's
    reading (the moving side alone) and an agent's own pair (both sides), away from the
    solution (residuals past the Huber breakpoint) and at a correction. (The joint solve's
    fixed point is where this gradient vanishes; the column's Hessian entries only set how
    fast it gets there.)"""
    for shared in (False, True):
        pair = replace(_pair(0.06, anchor_focal_error=-0.03), shared=shared)
        problem = focal_module._PairProblem([pair], TrackingConfig(), 4096)
        poses = problem.start.poses.clone()
        poses[1, :3] += torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64)
        for delta in (0.0, 0.04):
            H, g = problem.linearize(poses, delta)
            step = 1e-5
            slope = (
                problem.energy(poses, delta + step, math.inf)
                - problem.energy(poses, delta - step, math.inf)
            ) / (2 * step)
            # measured: within 3e-9 (a wrong term of the column is off by percents)
            assert float(g[-1]) == pytest.approx(slope, rel=1e-8)
            assert float(H[-1, -1]) > 0
            assert torch.equal(H, H.T)


@pytest.fixture(scope="module")
def agent_pairs(tmp_path_factory, process_frames) -> list[FocalPair]:
    """An agent's own keyframe pairs on the realistic simulated prior (noisy pointmaps,
    imperfect matches: the Huber kernel matters), its moving keyframes put on a focal
    length 6 % long."""
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=0,
        overlap=0.2,
        frames=12,
        preset="default",
        width=96,
        height=72,
        progress=None,
    )
    agent = open_agent(root / "agent_0")
    config = apply_overrides(Config(), ["input.long_side=96"])
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    process_frames(frontend, agent, 96, range(0, 12, 2))
    pairs = keyframe_pairs(frontend.keyframes.keyframes, frontend.edges)
    assert pairs
    return [
        replace(pair, X_moving=X, K_moving=K)
        for pair in pairs
        for X, K in [rescale_focal(pair.X_moving, pair.K_moving, 0.06)]
    ]


def _converged_search(pairs: list[FocalPair], search: float = 0.3) -> float:
    """The reference: the correction minimising the energy with every relative solve run
    from the pairs' own poses until it stops moving (the search's trial corrections put
    on the pointmaps by geometry.camera.rescale_focal, not by the joint solve's factors;
    in float64: float32 pointmaps rescaled at each trial make the energy jump by more than
    its change within 1e-4 of the minimum), by Brent's bounded search to 1e-6."""
    from scipy.optimize import minimize_scalar

    def energy(delta: float) -> float:
        moved = []
        for pair in pairs:
            X_m, K_m = rescale_focal(pair.X_moving.double(), pair.K_moving.double(), delta)
            X_a, K_a = pair.X_anchor.double(), pair.K_anchor.double()
            if pair.shared:
                X_a, K_a = rescale_focal(X_a, K_a, delta)
            moved.append(replace(pair, X_anchor=X_a, K_anchor=K_a, X_moving=X_m, K_moving=K_m))
        problem = focal_module._PairProblem(moved, TrackingConfig(), 4096)
        solved, _ = gauss_newton_irls(
            problem.factors,
            problem.start,
            GlobalBAConfig(),
            max_iters=1000,
            step_tol=1e-10,
            length_scale=problem.length,
        )
        return problem.energy(solved.poses, 0.0, 0.1) + 0.5 * (delta / 0.1) ** 2

    found = minimize_scalar(
        energy, bounds=(-search, search), method="bounded", options={"xatol": 1e-6}
    )
    return float(found.x)


@pytest.mark.slow
@pytest.mark.parametrize("shared", [True, False])
def test_estimate_is_the_minimum_a_converged_search_finds(agent_pairs, shared: bool) -> None:
    """The joint solve against Brent's search over fully converged relative solves, on an
    agent's real pairs read as one camera and as a merge would read them (measured: within
    2.2e-5; Brent's search over 10-iteration solves, the estimate before issue 41, 1.0e-4
    and 1.1e-4 off here, up to 5.2e-4 on a 16-agent replay's merges)."""
    pairs = [replace(pair, shared=shared) for pair in agent_pairs]
    reference = _converged_search(pairs)
    estimate = estimate_log_focal(pairs, TrackingConfig())
    assert abs(reference) > 0.02  # the 6 % put on the moving keyframes is seen
    assert estimate.log_focal == pytest.approx(reference, abs=5e-5)
    assert estimate.energy_gain > 0


def test_estimate_is_relative_to_the_anchor() -> None:
    estimate = estimate_log_focal([_pair(0.05, anchor_focal_error=-0.05)], TrackingConfig())
    # towards the anchor's focal length (-0.10), not the true one (-0.05); two views on one
    # wrong focal length are not exactly Sim(3)-consistent, hence the looser bound
    assert estimate.log_focal == pytest.approx(-0.10, abs=0.025)


@pytest.mark.parametrize("error", [0.1, -0.12])
def test_one_camera_pair_recovers_the_shared_focal_error(error: float) -> None:
    """An agent's own pair (both keyframes on one wrong camera) observes the true focal
    length: the rotation between the views turns the stretch of one into a misfit of the
    other."""
    pair = replace(_pair(error, anchor_focal_error=error), shared=True)
    estimate = estimate_log_focal([pair], TrackingConfig())
    assert estimate.log_focal == pytest.approx(-error, abs=0.02)
    # the merge's reading of the same pair (the moving side alone) sees two cameras that
    # nearly agree: what it corrects is a fraction of the shared error
    merge = estimate_log_focal([replace(pair, shared=False)], TrackingConfig())
    assert abs(merge.log_focal) < 0.4 * abs(error)


def test_agreeing_focal_lengths_need_no_correction() -> None:
    estimate = estimate_log_focal([_pair(0.0)], TrackingConfig())
    assert abs(estimate.log_focal) < 0.005


def _packet(agent: int, kf_id: int, X: torch.Tensor, K: torch.Tensor) -> KeyframePacket:
    return KeyframePacket(
        agent=agent,
        kf_id=kf_id,
        frame_index=kf_id,
        timestamp=float(kf_id),
        encoding=Encoding(agent=agent, index=kf_id, shape=(H, W)),
        T_WC=sim3_identity(dtype=torch.float64),
        X_hat=X,
        C_hat=torch.ones(H, W),
        colors=torch.zeros(H, W, 3, dtype=torch.uint8).numpy(),
        retrieval=None,
        sequential_ij=None,
        sequential_ji=None,
        previous=None,
        K=K,
    )


def test_graph_rescales_an_agent_now_and_on_receipt() -> None:
    K = _camera()
    X = unproject_depth(_depth(0.0), K)
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    graph.add_keyframe(_packet(0, 0, X, K))
    graph.add_keyframe(_packet(1, 0, X, K))
    graph.rescale_focal(1, 0.1)
    moved, kept = graph.keyframes[1], graph.keyframes[0]
    assert torch.equal(kept.X_hat, X) and torch.equal(kept.K, K)
    assert torch.allclose(moved.X_hat[..., 0], X[..., 0] * math.exp(-0.1))
    assert torch.allclose(moved.X_init, moved.X_hat)
    assert float(moved.K[0, 0]) == pytest.approx(40.0 * math.exp(0.1))
    # a later keyframe and a refresh of agent 1 arrive on its own camera
    graph.add_keyframe(_packet(1, 1, X, K))
    assert torch.allclose(graph.keyframes[2].X_hat, moved.X_hat)
    assert float(graph.keyframes[2].K[0, 0]) == pytest.approx(40.0 * math.exp(0.1))
    # a refresh on the agent's former camera is moved, one on the map's camera is not
    graph.refresh(
        1, PointmapRefresh(kf_id=0, X_hat=2 * X, C_hat=torch.ones(H, W), fused_frames=2, K=K)
    )
    assert torch.allclose(graph.keyframes[1].X_hat[..., 1], 2 * X[..., 1] * math.exp(-0.1))
    graph.refresh(
        1,
        PointmapRefresh(
            kf_id=1, X_hat=3 * X, C_hat=torch.ones(H, W), fused_frames=2, K=graph.keyframes[2].K
        ),
    )
    assert torch.equal(graph.keyframes[2].X_hat, 3 * X)
    assert graph.focal == {1: pytest.approx(40.0 * math.exp(0.1))}


def test_a_pose_update_with_a_focal_length_moves_the_agents_keyframes() -> None:
    K = _camera()
    X = unproject_depth(_depth(0.0), K)
    graph = GlobalGraph(TrackingConfig(), GlobalBAConfig())
    graph.add_keyframe(_packet(1, 0, X, K))
    agent_side = graph.keyframes[0]
    kf = type(agent_side)(
        **{**agent_side.__dict__, "X_hat": X.clone(), "X_init": X.clone(), "K": K.clone()}
    )
    focal = 40.0 * math.exp(-0.05)
    apply_pose_update(
        [kf],
        PoseUpdate(
            agent=1,
            kf_ids=torch.tensor([0]),
            T_WC=sim3_identity(1, dtype=torch.float64),
            reason="gauge",
            focal=focal,
        ),
    )
    assert float(kf.K[0, 0]) == pytest.approx(focal)
    assert torch.allclose(project(kf.X_hat, kf.K), project(X, K), atol=1e-9)
    assert torch.allclose(kf.X_init, kf.X_hat)


def test_relative_pose_of_the_same_pose_is_the_identity() -> None:
    T = sim3_exp(torch.tensor([0.1, 0.2, 0.3, 0.1, 0.0, -0.1, 0.2], dtype=torch.float64))
    assert torch.allclose(relative_pose(T, T), sim3_identity(dtype=torch.float64), atol=1e-12)


def _admitted(
    coordinator: Coordinator,
    anchor: tuple[int, int],
    moving: tuple[int, int],
    pair: FocalPair,
    similarity: float,
) -> None:
    """Record ``pair`` as an admitted cross-agent edge (anchor = endpoint i)."""
    graph = coordinator.graph
    i, j = graph.global_index(*anchor), graph.global_index(*moving)
    link = PairLink(ij=pair.in_anchor, ji=pair.in_moving)
    verification = Verification(
        candidate=anchor,
        query=moving,
        similarity=similarity,
        ij=link.ij,
        link=link,
        covisible_i=1.0,
        covisible_j=1.0,
        accepted=True,
    )
    coordinator.candidates.append(Candidate(verification, i, j, status="admitted"))


def test_terminal_refinement_settles_focal_lengths_outwards_from_the_anchor() -> None:
    """Agent 1 meets agent 0, agent 2 meets only agent 1, both focal lengths off: the
    refinement settles agent 1 on its edge to agent 0 first, then agent 2 on its edge to
    the corrected agent 1, so all three end on agent 0's camera."""
    error_1, error_2 = 0.08, -0.06
    to_agent_0 = _pair(error_1)
    to_agent_1 = _pair(error_2, anchor_focal_error=error_1)
    # the chain (gauge.focal_ba=false; the joint solve is tests/backend/test_focal_solver.py)
    config = apply_overrides(Config(), ["gauge.focal_ba=false"])
    coordinator = Coordinator(None, config, None, 3)
    T_am = to_agent_0.T_anchor_moving
    for agent, kf_id, X, K, T in (
        (0, 0, to_agent_0.X_anchor, to_agent_0.K_anchor, sim3_identity(dtype=torch.float64)),
        (1, 0, to_agent_0.X_moving, to_agent_0.K_moving, T_am),
        (1, 1, to_agent_1.X_anchor, to_agent_1.K_anchor, sim3_identity(dtype=torch.float64)),
        (2, 0, to_agent_1.X_moving, to_agent_1.K_moving, T_am),
    ):
        coordinator.graph.add_keyframe(replace(_packet(agent, kf_id, X, K), T_WC=T))
    _admitted(coordinator, (0, 0), (1, 0), to_agent_0, similarity=0.5)
    _admitted(coordinator, (1, 1), (2, 0), to_agent_1, similarity=0.4)
    coordinator._refine_focals([0, 1, 2])
    focal = coordinator.metrics()["focal_lengths"]
    assert focal["0"] == pytest.approx(40.0)
    assert focal["1"] == pytest.approx(40.0, rel=0.01)
    assert focal["2"] == pytest.approx(40.0, rel=0.02)
    assert coordinator.stats.focal_refinements == 2


@pytest.mark.slow
def test_terminal_refinement_closes_a_ring_of_agents() -> None:
    """Four agents in a ring (0-1, 1-2, 2-3 and 3-0 meet), focal lengths off by up to 7 %:
    the chain settles them outwards from agent 0, and since their pairs close a loop the
    least-squares sweep (gauge.focal_loops) re-measures every pair; all end on agent 0's camera, and the
    sweep counts one refinement per agent it moved."""
    errors = {0: 0.0, 1: 0.06, 2: -0.05, 3: 0.07}
    pairs = {
        (0, 1): _pair(errors[1], anchor_focal_error=errors[0]),
        (1, 2): _pair(errors[2], anchor_focal_error=errors[1]),
        (2, 3): _pair(errors[3], anchor_focal_error=errors[2]),
        (0, 3): _pair(errors[3], anchor_focal_error=errors[0]),
    }
    config = apply_overrides(Config(), ["gauge.focal_loops=true", "gauge.focal_ba=false"])
    coordinator = Coordinator(None, config, None, 4)
    identity, T_am = sim3_identity(dtype=torch.float64), pairs[(0, 1)].T_anchor_moving
    keyframes: dict[int, list] = {a: [] for a in errors}
    for (a, b), pair in pairs.items():
        keyframes[a].append((pair.X_anchor, pair.K_anchor, identity))
        keyframes[b].append((pair.X_moving, pair.K_moving, T_am))
    for agent in sorted(keyframes):
        for kf_id, (X, K, T) in enumerate(keyframes[agent]):
            coordinator.graph.add_keyframe(replace(_packet(agent, kf_id, X, K), T_WC=T))
    used = dict.fromkeys(errors, 0)
    for (a, b), pair in pairs.items():
        _admitted(coordinator, (a, used[a]), (b, used[b]), pair, similarity=0.5)
        used[a] += 1
        used[b] += 1
    # the sweep alone, from the focal lengths as they came (6-7 % off): one pass of it
    coordinator._close_focal_loops([0, 1, 2, 3])
    focal = coordinator.metrics()["focal_lengths"]
    assert focal["0"] == pytest.approx(40.0)
    for agent in ("1", "2", "3"):
        assert focal[agent] == pytest.approx(40.0, rel=0.03), agent
    assert coordinator.stats.focal_refinements == 3
    # then the whole refinement (the chain, then the sweep): on agent 0's camera
    coordinator._refine_focals([0, 1, 2, 3])
    focal = coordinator.metrics()["focal_lengths"]
    for agent in ("1", "2", "3"):
        assert focal[agent] == pytest.approx(40.0, rel=0.02), agent
    assert coordinator.stats.focal_refinements == 3 + 3 + 3
