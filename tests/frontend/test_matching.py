"""Projective matching (C-Eq. 1) against brute force, occlusion and descriptor refinement."""

from __future__ import annotations

import math

import torch

from como3r.config import MatchingConfig
from como3r.frontend import match_consensus
from como3r.frontend.match_consensus import consensus_window
from como3r.frontend.matching import match_confidence, match_pointmaps
from como3r.geometry.camera import intrinsics_matrix, unproject_depth
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_inverse
from como3r.geometry.residuals import psi

H, W = 30, 40


def _smooth_depth(generator: torch.Generator) -> torch.Tensor:
    """A tilted, gently curved surface 4-7 m away: ``(H, W)`` metres."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    phase = torch.rand(2, generator=generator, dtype=torch.float64) * 2 * math.pi
    return 5.0 + 0.03 * u + 0.3 * torch.sin(u / 9 + phase[0]) * torch.cos(v / 7 + phase[1])


def _descriptors(X_world: torch.Tensor, projection: torch.Tensor) -> torch.Tensor:
    """Unit descriptors as a smooth random-feature function of the world point."""
    return psi(torch.cos(X_world @ projection))


def _two_views(seed: int, depth_search: torch.Tensor | None = None):
    g = torch.Generator().manual_seed(seed)
    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    depth = _smooth_depth(g) if depth_search is None else depth_search
    X_search = unproject_depth(depth, K)  # search view = world frame
    T_qs = sim3_exp(torch.tensor([0.05, -0.03, 0.08, 0.01, 0.02, -0.01, 0.0], dtype=torch.float64))
    # query view sees the same surface from a slightly moved camera: express its points
    # (here simply the search surface seen through the moved camera's pixel grid) in the
    # search frame by rendering depth of a plane-like surface through T.
    depth_q = _smooth_depth(g)
    X_query_own = unproject_depth(depth_q, K)
    X_query = sim3_act(T_qs[None, None], X_query_own)
    return K, X_search, X_query


def _brute_force(X_search: torch.Tensor, X_query: torch.Tensor) -> torch.Tensor:
    rays_s = psi(X_search.reshape(-1, 3))
    rays_q = psi(X_query.reshape(-1, 3))
    return (rays_q @ rays_s.T).argmax(dim=1)


def test_matching_agrees_with_brute_force_nearest_ray() -> None:
    config = MatchingConfig(descriptor_radius=0, occlusion_ratio=1e9)
    agree, total = 0, 0
    for seed in range(4):
        _, X_search, X_query = _two_views(seed)
        D = torch.nn.functional.normalize(torch.ones(1, H, W, 4, dtype=torch.float64), dim=-1)
        m = match_pointmaps(X_search[None], X_query[None], D, D, config)
        ref = _brute_force(X_search, X_query)
        ok = m.valid[0]
        # brute force picks the pixel centre with the closest ray: the continuous optimum
        # rounds to it (or a neighbour on an exact tie at the half pixel)
        du = (m.idx[0] % W - ref % W).abs()
        dv = (m.idx[0] // W - ref // W).abs()
        agree += int(((du == 0) & (dv == 0))[ok].sum())
        total += int(ok.sum())
        assert ok.float().mean() > 0.5
    assert agree / total >= 0.99


def test_occluded_points_are_rejected() -> None:
    depth = torch.full((H, W), 6.0, dtype=torch.float64)
    depth[8:22, 12:28] = 2.0  # a box in front of the wall hides the wall behind it
    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    X_search = unproject_depth(depth, K)
    X_wall = unproject_depth(torch.full((H, W), 6.0, dtype=torch.float64), K)
    config = MatchingConfig(descriptor_radius=0)
    D = torch.nn.functional.normalize(torch.ones(1, H, W, 4, dtype=torch.float64), dim=-1)
    m = match_pointmaps(X_search[None], X_wall[None], D, D, config)
    hidden = torch.zeros(H, W, dtype=torch.bool)
    hidden[9:21, 13:27] = True  # strictly inside the box: the wall point is occluded
    visible = torch.zeros(H, W, dtype=torch.bool)
    visible[:, :8] = True
    valid = m.valid[0].reshape(H, W)
    assert not valid[hidden].any()
    assert valid[visible].float().mean() > 0.95


def test_descriptor_refinement_recovers_true_pixel_and_validity_follows_it() -> None:
    g = torch.Generator().manual_seed(7)
    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    X_search = unproject_depth(_smooth_depth(g), K)
    projection = torch.randn(3, 32, generator=g, dtype=torch.float64)
    D_search = _descriptors(X_search, projection)
    # the prior's geometry is off by two pixels (each query point is the surface point
    # two columns to the right) while its descriptors are right: projection lands two
    # pixels off, the descriptor window must pull the match back to the true pixel
    X_query = torch.roll(X_search, shifts=-2, dims=1)[:, 4:-4]
    D_query = D_search[:, 4:-4]
    grid_v, grid_u = torch.meshgrid(torch.arange(H), torch.arange(4, W - 4), indexing="ij")
    p_true = torch.stack([grid_u, grid_v], -1).reshape(-1, 2)
    # 3 samples and a dilation of 5 pixels at this image size (the config gives the dilation
    # at 512 px)
    window = dict(descriptor_radius=3, descriptor_dilation_max=round(5 * 512 / W))
    loose = MatchingConfig(occlusion_ratio=10.0, **window)
    m = match_pointmaps(X_search[None], X_query[None], D_search[None], D_query[None], loose)
    exact = (m.pixel[0] == p_true).all(-1)
    assert exact.float().mean() > 0.95
    unrefined = match_pointmaps(
        X_search[None],
        X_query[None],
        D_search[None],
        D_query[None],
        MatchingConfig(descriptor_radius=0, occlusion_ratio=0.01),
    )
    assert unrefined.valid.float().mean() > 0.9
    # validity is decided on the refined match, whose 3-D points are two pixels apart
    strict = MatchingConfig(occlusion_ratio=0.01, **window)
    m_strict = match_pointmaps(X_search[None], X_query[None], D_search[None], D_query[None], strict)
    gap = (X_search.reshape(-1, 3)[m_strict.idx[0]] - X_query.reshape(-1, 3)).norm(dim=-1)
    ranges = X_query.reshape(-1, 3).norm(dim=-1)
    assert bool((gap[m_strict.valid[0]] < strict.occlusion_ratio * ranges[m_strict.valid[0]]).all())
    assert m_strict.valid.float().mean() < 0.05


def test_consensus_keeps_flat_paint_at_its_projection() -> None:
    """Where descriptors are one flat colour plus per-pixel noise, the window search follows
    the noise (MatchingConfig's docstring: the v2 prior's low-texture family); the median of
    its moves over the consensus window (13 pixels at this size) does not, and a move shared
    by the neighbourhood (the prior's geometry two pixels off) survives it."""
    g = torch.Generator().manual_seed(3)
    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    X_search = unproject_depth(_smooth_depth(g), K)
    flat = torch.nn.functional.normalize(torch.ones(H, W, 16, dtype=torch.float64), dim=-1)

    def noisy() -> torch.Tensor:
        return torch.nn.functional.normalize(
            flat + 0.3 * torch.randn(H, W, 16, generator=g, dtype=torch.float64), dim=-1
        )

    grid_v, grid_u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    p_true = torch.stack([grid_u, grid_v], -1).reshape(-1, 2)
    assert consensus_window(W) == 13 and consensus_window(512) == 1

    def matched(consensus: bool) -> torch.Tensor:
        config = MatchingConfig(occlusion_ratio=10.0, descriptor_consensus=consensus)
        m = match_pointmaps(X_search[None], X_search[None], noisy()[None], noisy()[None], config)
        return ((m.pixel[0] - p_true).abs() <= 1).all(-1).float().mean()

    # within a pixel of the true one: the search alone wanders up to 5 pixels off
    assert matched(consensus=False) < 0.3
    assert matched(consensus=True) > 0.95
    # textured descriptors and geometry two pixels off: the consensus keeps the shared move
    D_search = _descriptors(X_search, torch.randn(3, 32, generator=g, dtype=torch.float64))
    X_query = torch.roll(X_search, shifts=-2, dims=1)[:, 4:-4]
    m = match_pointmaps(
        X_search[None],
        X_query[None],
        D_search[None],
        D_search[:, 4:-4][None],
        MatchingConfig(occlusion_ratio=10.0, descriptor_dilation_max=round(5 * 512 / W)),
    )
    inner = torch.stack(torch.meshgrid(torch.arange(H), torch.arange(4, W - 4), indexing="ij"))
    assert (m.pixel[0] == inner.flip(0).reshape(2, -1).T).all(-1).float().mean() > 0.95


def test_compiled_move_medians_equal_the_pytorch_ones() -> None:
    """The CPU loop counts the moves of each window, the PyTorch path sorts them: the same
    lower median per axis, borders and inactive matches included."""
    from como3r.frontend import cpu_kernels

    g = torch.Generator().manual_seed(0)
    moves = torch.randint(-9, 10, (2, 11 * 13, 2), generator=g)
    active = torch.rand(2, 11 * 13, generator=g) > 0.3
    for window in (3, 5, 9):
        want = match_consensus._move_medians(moves, active, (11, 13), window)
        got = cpu_kernels.move_medians(moves, active, (11, 13), window)
        assert torch.equal(got[active], want[active])


def test_match_confidence_is_geometric_mean() -> None:
    Q_query = torch.tensor([[4.0, 9.0]])
    Q_search = torch.tensor([[[1.0, 16.0]]])
    idx = torch.tensor([[1, 0]])
    q = match_confidence(Q_query, Q_search, idx)
    assert torch.allclose(q, torch.tensor([[8.0, 3.0]]))


def test_warm_start_converges_with_fewer_iterations() -> None:
    _, X_search, X_query = _two_views(3)
    D = torch.nn.functional.normalize(torch.ones(1, H, W, 4, dtype=torch.float64), dim=-1)
    cold = match_pointmaps(
        X_search[None],
        X_query[None],
        D,
        D,
        MatchingConfig(descriptor_radius=0, occlusion_ratio=1e9),
    )
    warm = match_pointmaps(
        X_search[None],
        X_query[None],
        D,
        D,
        MatchingConfig(descriptor_radius=0, occlusion_ratio=1e9, max_iters=1),
        p_init=cold.pixel.double(),
    )
    both = cold.valid & warm.valid
    assert both.float().mean() > 0.5
    assert torch.equal(cold.idx[both], warm.idx[both])


def test_inverse_pose_helper_is_consistent() -> None:
    T = sim3_exp(torch.tensor([0.1, 0.2, 0.3, 0.01, 0.02, 0.03, 0.1], dtype=torch.float64))
    x = torch.randn(5, 3, dtype=torch.float64)
    assert torch.allclose(sim3_act(sim3_inverse(T)[None], sim3_act(T[None], x)), x, atol=1e-12)


def test_rays_outside_the_view_leave_the_projection_early(monkeypatch) -> None:
    """Query rays outside the searched view stop once the border stops them, and every
    match inside the view is the one the brute force finds."""
    from como3r.frontend import matching

    K = intrinsics_matrix(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, dtype=torch.float64)
    X_search = unproject_depth(torch.full((H, W), 5.0, dtype=torch.float64), K)
    # the query camera is turned by 30 degrees: the rays of about a third of its pixels
    # miss the searched view
    turn = sim3_exp(
        torch.tensor([0.0, 0.0, 0.0, 0.0, math.radians(30), 0.0, 0.0], dtype=torch.float64)
    )
    X_query = sim3_act(
        turn[None, None], unproject_depth(torch.full((H, W), 5.0, dtype=torch.float64), K)
    )
    evaluated = [0]
    ray_cost = matching._ray_cost

    def counted(*args):
        evaluated[0] += args[4].shape[0]
        return ray_cost(*args)

    monkeypatch.setattr(matching, "_ray_cost", counted)

    # the PyTorch path, whose ray evaluations can be counted; the compiled CPU loop follows
    # the same exit rule and gives the same pixels (tests/frontend/test_cpu_kernels.py)
    def vectorised(rays_grad, target, *rest):
        p, converged = matching._project_vectorised(rays_grad, target, *rest)
        return p, matching._nearest_ray_pixel(rays_grad[..., :3], p, target), converged

    monkeypatch.setattr(matching.cpu_kernels, "project_rays", vectorised)
    config = MatchingConfig(descriptor_radius=0, occlusion_ratio=1e9)
    D = torch.nn.functional.normalize(torch.ones(1, H, W, 4, dtype=torch.float64), dim=-1)
    m = match_pointmaps(X_search[None], X_query[None], D, D, config)
    outside = (_brute_force_outside(X_search, X_query, K)).reshape(-1)
    assert 0.2 < outside.float().mean() < 0.5
    assert not m.valid[0][outside].any()
    assert (m.idx[0] == _brute_force(X_search, X_query))[m.valid[0]].float().mean() >= 0.99
    assert m.valid[0][~outside].float().mean() > 0.95
    # 3.1 H W ray evaluations; without the early exit the outside pixels ran all
    # max_iters iterations (7.2 H W)
    assert H * W < evaluated[0] < 4 * H * W


def _brute_force_outside(
    X_search: torch.Tensor, X_query: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """``(H, W)`` query points whose projection falls outside the searched image."""
    uvw = X_query @ K.T
    u, v = uvw[..., 0] / uvw[..., 2], uvw[..., 1] / uvw[..., 2]
    return (uvw[..., 2] <= 0) | (u < -0.5) | (u > W - 0.5) | (v < -0.5) | (v > H - 0.5)
