"""Tests of como3r.optim.factors: linearization against an independent autograd computation."""

from __future__ import annotations

import pytest
import torch

from como3r.errors import InputError
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse, sim3_log
from como3r.optim.cpu_loops import MIN_DEPTH_RATIO
from como3r.optim.factors import RelativePoseFactors
from como3r.optim.match_factors import CalibratedFactors, RayRangeFactors
from como3r.optim.synthetic import chain_poses, random_sim3, synthetic_graph
from como3r.optim.system import assemble

HUBER_K = 1.345


@pytest.fixture(params=["compiled", "vectorised"])
def path(request, monkeypatch):
    """Linearize through the compiled CPU loops (what CPU tensors take) or through PyTorch
    (what CUDA tensors take, forced here on the CPU)."""
    if request.param == "vectorised":
        monkeypatch.setattr(RelativePoseFactors, "_runs_compiled", lambda self, poses: False)
    return request.param


# ---------------------------------------------------------------------------------------------
# An independent reference: 4x4 matrices, first-order left perturbations, autograd.
# ---------------------------------------------------------------------------------------------


def _matrix(T: torch.Tensor) -> torch.Tensor:
    """(N, 8) poses -> (N, 4, 4) matrices [[s R, t], [0, 1]], R from the quaternion."""
    x, y, z, w = T[:, 3], T[:, 4], T[:, 5], T[:, 6]
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    R = torch.stack(
        [
            torch.stack([ww + xx - yy - zz, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), ww - xx + yy - zz, 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), ww - xx - yy + zz], -1),
        ],
        -2,
    )
    M = torch.zeros(T.shape[0], 4, 4, dtype=T.dtype)
    M[:, :3, :3] = T[:, 7, None, None] * R
    M[:, :3, 3] = T[:, :3]
    M[:, 3, 3] = 1
    return M


def _perturbed(M: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """(I + hat(tau)) M: exact to first order in tau, so its derivative at tau = 0 is the
    derivative of the left perturbation Exp(tau) M (hat(v, w, z) = [[z I + [w]x, v], [0, 0]])."""
    v, w, z = tau[:, :3], tau[:, 3:6], tau[:, 6]
    hat = torch.zeros(M.shape[0], 4, 4, dtype=M.dtype)
    hat[:, :3, :3] = torch.stack(
        [
            torch.stack([z, -w[:, 2], w[:, 1]], -1),
            torch.stack([w[:, 2], z, -w[:, 0]], -1),
            torch.stack([-w[:, 1], w[:, 0], z], -1),
        ],
        -2,
    )
    hat[:, :3, 3] = v
    return (torch.eye(4, dtype=M.dtype) + hat) @ M


def _transformed(poses, i, j, X_j, tau):
    """T_ij X_j for every edge, T_ij = M_i^-1 M_j under the perturbation tau (N, 7)."""
    M = _perturbed(_matrix(poses), tau)
    M_ij = torch.linalg.inv(M[i]) @ M[j]
    return (M_ij[:, None, :3, :3] @ X_j[..., None])[..., 0] + M_ij[:, None, :3, 3]


def _ray_range_whitened(poses, i, j, X_i, X_j, q, valid, sigmas, tau):
    x = _transformed(poses, i, j, X_j, tau)
    d = x.norm(dim=-1)
    e = torch.cat(
        [
            x / d[..., None] - X_i / X_i.norm(dim=-1, keepdim=True),
            (d - X_i.norm(dim=-1))[..., None],
        ],
        -1,
    )
    r = e * q.sqrt()[..., None] / torch.tensor(sigmas, dtype=e.dtype)
    return torch.where(valid[..., None], r, torch.zeros_like(r))


def _calibrated_whitened(poses, i, j, X_j, p_i, z_i, K, q, valid, sigmas, tau):
    x = _transformed(poses, i, j, X_j, tau)
    Kx = (K[:, None] @ x[..., None])[..., 0]
    e = torch.cat([Kx[..., :2] / x[..., 2:] - p_i, (x[..., 2].log() - z_i.log())[..., None]], -1)
    r = e * q.sqrt()[..., None] / torch.tensor(sigmas, dtype=e.dtype)
    return torch.where(valid[..., None], r, torch.zeros_like(r))


def _reference_system(whitened, num_poses):
    """H = J^T diag(w) J, g = J^T diag(w) r, and the robust cost, by autograd at tau = 0."""
    tau0 = torch.zeros(num_poses, 7, dtype=torch.float64)
    r = whitened(tau0).reshape(-1)
    J = torch.autograd.functional.jacobian(lambda t: whitened(t).reshape(-1), tau0)
    J = J.reshape(r.numel(), num_poses * 7)
    w = torch.clamp(HUBER_K / r.abs(), max=1.0)
    H = J.T @ (w[:, None] * J)
    g = J.T @ (w * r)
    a = r.abs()
    cost = torch.where(a <= HUBER_K, 0.5 * a * a, HUBER_K * (a - 0.5 * HUBER_K)).sum()
    return H, g.reshape(num_poses, 7), cost


# ---------------------------------------------------------------------------------------------
# A tiny graph: 4 poses, edges in both directions and a loop, P = 20, perturbed so that the
# residual is non-zero and part of the components sit beyond the Huber breakpoint.
# ---------------------------------------------------------------------------------------------


def _tiny_graph(dtype=torch.float64):
    generator = torch.Generator().manual_seed(7)
    truth = chain_poses(4, generator)
    i = torch.tensor([0, 1, 2, 3, 2])
    j = torch.tensor([1, 2, 3, 0, 0])
    graph = synthetic_graph(truth, i, j, 20, generator)
    poses = sim3_compose(random_sim3(4, 1.0, 0.05, 0.02, generator), truth)
    valid = graph.valid.clone()
    valid[1, 3] = False
    valid[4, :5] = False
    X_j = graph.X_j.clone()
    X_j[1, 3] = float("nan")  # garbage behind an invalid match must not leak
    return poses.to(dtype), graph, X_j, valid


def test_ray_range_linearization_matches_autograd(path):
    poses, graph, X_j, valid = _tiny_graph()
    sigmas = (3e-3,) * 3 + (0.05,)
    factors = RayRangeFactors(
        graph.i,
        graph.j,
        graph.X_i,
        X_j,
        graph.q,
        valid,
        sigma_ray=3e-3,
        sigma_dist=0.05,
        huber_k=HUBER_K,
    )
    system = assemble(4, [factors.linearize(poses)])

    X_j_clean = torch.where(valid[..., None], X_j, graph.X_i)
    H_ref, g_ref, cost_ref = _reference_system(
        lambda t: _ray_range_whitened(
            poses, graph.i, graph.j, graph.X_i, X_j_clean, graph.q, valid, sigmas, t
        ),
        4,
    )
    r = _ray_range_whitened(
        poses,
        graph.i,
        graph.j,
        graph.X_i,
        X_j_clean,
        graph.q,
        valid,
        sigmas,
        torch.zeros(4, 7, dtype=torch.float64),
    )
    beyond = (r.abs() > HUBER_K).float().mean()
    assert 0.1 < beyond < 0.9, "the test must exercise both Huber regimes"

    H = system.to_dense()
    torch.testing.assert_close(H, H_ref, rtol=1e-9, atol=1e-9 * H_ref.abs().max().item())
    torch.testing.assert_close(system.g, g_ref, rtol=1e-9, atol=1e-9 * g_ref.abs().max().item())
    torch.testing.assert_close(factors.cost(poses), cost_ref, rtol=1e-12, atol=0)


def test_calibrated_linearization_matches_autograd(path):
    poses, graph, X_j, valid = _tiny_graph()
    K = torch.tensor([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]], dtype=torch.float64)
    K = K.expand(5, 3, 3).clone()
    K[2, 0, 0] = 450.0  # intrinsics are per edge
    truth_x = graph.X_i
    p_i = (K[:, None] @ truth_x[..., None])[..., 0]
    p_i = p_i[..., :2] / p_i[..., 2:]
    z_i = truth_x[..., 2]
    sigmas = (1.0, 1.0, 0.01)
    factors = CalibratedFactors(
        graph.i,
        graph.j,
        X_j,
        p_i,
        z_i,
        K,
        graph.q,
        valid,
        sigma_pixel=1.0,
        sigma_depth=0.01,
        huber_k=HUBER_K,
    )
    system = assemble(4, [factors.linearize(poses)])

    X_j_clean = torch.where(valid[..., None], X_j, graph.X_i)
    H_ref, g_ref, cost_ref = _reference_system(
        lambda t: _calibrated_whitened(
            poses, graph.i, graph.j, X_j_clean, p_i, z_i, K, graph.q, valid, sigmas, t
        ),
        4,
    )

    H = system.to_dense()
    torch.testing.assert_close(H, H_ref, rtol=1e-9, atol=1e-9 * H_ref.abs().max().item())
    torch.testing.assert_close(system.g, g_ref, rtol=1e-9, atol=1e-9 * g_ref.abs().max().item())
    torch.testing.assert_close(factors.cost(poses), cost_ref, rtol=1e-12, atol=0)


@pytest.mark.parametrize("depth_ratio", [-1.0, 1e-6, 0.2])
def test_calibrated_points_near_or_behind_camera_i_get_no_weight(path, depth_ratio):
    """A match that T_ij brings behind camera i, or nearer it than MIN_DEPTH_RATIO of its
    observed depth, counts nothing, in both linearisation paths: its pixel Jacobian grows as
    1 / z^2 there (on a 5,000-frame loop such loop-edge matches left every later local solve
    numerically indefinite). Fails with the former mask (depth > 0) at 1e-6 and 0.2."""
    assert depth_ratio < MIN_DEPTH_RATIO
    poses, graph, _, valid = _tiny_graph()
    K = torch.tensor([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]], dtype=torch.float64)
    p_i = torch.zeros(*graph.q.shape, 2, dtype=torch.float64)
    z_i = graph.X_i[..., 2]
    X_j = graph.X_j.clone()
    # Move one match of edge 0 along its ray to depth_ratio times its observed depth in i.
    T_ij = sim3_compose(sim3_inverse(poses[0]), poses[1])
    X_j[0, 0] = sim3_act(sim3_inverse(T_ij), depth_ratio * graph.X_i[0, 0])
    moved = CalibratedFactors(graph.i, graph.j, X_j, p_i, z_i, K, graph.q, valid)
    r = moved.whitened_residual(poses, slice(0, 1))[0]
    assert torch.all(r[0, 0] == 0) and torch.all(r[0, 1] != 0)
    blocks = moved.linearize(poses)
    # Exactly as if the match were invalid: only edge 0 changed, and only by dropping it.
    without = valid.clone()
    without[0, 0] = False
    dropped = CalibratedFactors(graph.i, graph.j, X_j, p_i, z_i, K, graph.q, without)
    reference = dropped.linearize(poses)
    for name in ("H_ii", "H_ij", "H_jj", "g_i", "g_j"):
        torch.testing.assert_close(getattr(blocks, name), getattr(reference, name))
    torch.testing.assert_close(moved.cost(poses), dropped.cost(poses))


def test_calibrated_points_beyond_the_depth_ratio_keep_their_weight(path):
    """Just above MIN_DEPTH_RATIO of its observed depth a match still counts."""
    poses, graph, _, valid = _tiny_graph()
    K = torch.tensor([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]], dtype=torch.float64)
    p_i = torch.zeros(*graph.q.shape, 2, dtype=torch.float64)
    X_j = graph.X_j.clone()
    T_ij = sim3_compose(sim3_inverse(poses[0]), poses[1])
    X_j[0, 0] = sim3_act(sim3_inverse(T_ij), 1.2 * MIN_DEPTH_RATIO * graph.X_i[0, 0])
    factors = CalibratedFactors(graph.i, graph.j, X_j, p_i, graph.X_i[..., 2], K, graph.q, valid)
    assert torch.all(factors.whitened_residual(poses, slice(0, 1))[0][0, 0] != 0)


def test_gradient_is_the_gradient_of_the_robust_cost():
    """LM relies on g = d cost / d tau; check it by autograd through the factor's own cost."""
    poses, graph, _, valid = _tiny_graph()  # finite points: autograd of where() needs them
    factors = RayRangeFactors(
        graph.i, graph.j, graph.X_i, graph.X_j, graph.q, valid, sigma_ray=3e-3, sigma_dist=0.05
    )
    tau = torch.zeros(4, 7, dtype=torch.float64, requires_grad=True)
    factors.cost(sim3_compose(sim3_exp(tau), poses)).backward()
    g = assemble(4, [factors.linearize(poses)]).g
    torch.testing.assert_close(tau.grad, g, rtol=1e-8, atol=1e-8 * g.abs().max().item())


def test_chunking_does_not_change_the_blocks(path):
    poses, graph, X_j, valid = _tiny_graph()
    whole = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid)
    chunked = RayRangeFactors(
        graph.i, graph.j, graph.X_i, X_j, graph.q, valid, chunk_matches=40
    )  # two edges per chunk, last chunk ragged
    a, b = whole.linearize(poses), chunked.linearize(poses)
    for name in ("i", "j", "H_ii", "H_jj", "H_ij", "g_i", "g_j"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-12, atol=0)
    torch.testing.assert_close(whole.cost(poses), chunked.cost(poses), rtol=1e-12, atol=0)


def test_linearization_in_each_dtype(dtype):
    poses, graph, X_j, valid = _tiny_graph()
    reference = assemble(
        4, [RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid).linearize(poses)]
    )
    factors = RayRangeFactors(
        graph.i, graph.j, graph.X_i.to(dtype), X_j.to(dtype), graph.q.to(dtype), valid
    )
    blocks = factors.linearize(poses.to(dtype))
    assert blocks.H_ii.dtype == dtype
    system = assemble(4, [blocks])
    H = system.to_dense()
    tolerance = 1e-3 if dtype == torch.float32 else 1e-10
    scale = reference.to_dense().abs().max()
    assert (H - reference.to_dense()).abs().max() <= tolerance * scale
    torch.testing.assert_close(H, H.T)
    assert torch.linalg.eigvalsh(H).min() > -1e-6 * scale


def test_invalid_inputs_raise_input_error():
    poses, graph, X_j, valid = _tiny_graph()
    args = (graph.i, graph.j, graph.X_i, X_j, graph.q, valid)
    with pytest.raises(InputError, match="X_i"):
        RayRangeFactors(graph.i, graph.j, graph.X_i[:, :5], X_j, graph.q, valid)
    with pytest.raises(InputError, match="itself"):
        RayRangeFactors(graph.i, graph.i, *args[2:])
    with pytest.raises(InputError, match="valid"):
        RayRangeFactors(*args[:5], valid.float())
    with pytest.raises(InputError, match="sigma"):
        RayRangeFactors(*args, sigma_ray=0.0)
    with pytest.raises(InputError, match="integer"):
        RayRangeFactors(graph.i.float(), *args[1:])
    with pytest.raises(InputError, match="refers to pose 3"):
        RayRangeFactors(*args).linearize(poses[:3])


def test_non_positive_confidence_means_no_information():
    poses, graph, X_j, valid = _tiny_graph()
    q = graph.q.clone()
    q[0] = 0.0
    blocks = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, q, valid).linearize(poses)
    assert torch.all(blocks.H_ii[0] == 0) and torch.all(blocks.g_j[0] == 0)
    assert torch.any(blocks.H_ii[1] != 0)


def test_invalid_padding_changes_nothing_and_is_dropped():
    """Matches invalid at every pose (unmatched pixels, garbage behind them) weigh zero:
    appending them leaves the blocks and the cost unchanged, and the batch does not grow."""
    poses, graph, X_j, valid = _tiny_graph()
    base = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid)
    E, P = graph.q.shape
    pad = 30
    garbage = torch.full((E, pad, 3), float("nan"), dtype=X_j.dtype)
    padded = RayRangeFactors(
        graph.i,
        graph.j,
        torch.cat([garbage, graph.X_i], 1),
        torch.cat([garbage, X_j], 1),
        torch.cat([torch.rand(E, pad, dtype=graph.q.dtype), graph.q], 1),
        torch.cat([torch.zeros(E, pad, dtype=torch.bool), valid], 1),
    )
    assert padded.q.shape == base.q.shape
    a, b = base.linearize(poses), padded.linearize(poses)
    for name in ("i", "j", "H_ii", "H_jj", "H_ij", "g_i", "g_j"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-12, atol=0)
    torch.testing.assert_close(base.cost(poses), padded.cost(poses), rtol=1e-12, atol=0)


@pytest.mark.parametrize("factor_type", ["ray_range", "calibrated"])
def test_compiled_blocks_do_not_depend_on_the_thread_count(factor_type):
    """The compiled loops add their per-block sums in block order: one thread and two give
    the same bits (a run is reproducible on any machine's core count)."""
    poses, graph, X_j, valid = _tiny_graph(torch.float32)
    P = 3 * 4096 + 17  # several blocks per edge
    repeat = -(-P // graph.q.shape[1])
    tiled = [x.repeat_interleave(repeat, dim=1)[:, :P] for x in (graph.X_i, X_j, graph.q, valid)]
    X_i, X_j, q, valid = tiled[0].float(), tiled[1].float(), tiled[2].float(), tiled[3]
    if factor_type == "ray_range":
        factors = RayRangeFactors(graph.i, graph.j, X_i, X_j, q, valid)
    else:
        K = torch.tensor([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]])
        p_i = (K @ X_i[..., None])[..., 0]
        factors = CalibratedFactors(
            graph.i, graph.j, X_j, p_i[..., :2] / p_i[..., 2:], X_i[..., 2], K, q, valid
        )
    before = torch.get_num_threads()
    try:
        results = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results.append((factors.linearize(poses.float()), factors.cost(poses.float())))
    finally:
        torch.set_num_threads(before)
    (one, cost_one), (two, cost_two) = results
    assert torch.equal(one.H_ij, two.H_ij) and torch.equal(one.g_i, two.g_i)
    assert torch.equal(cost_one, cost_two) and cost_one > 0


def test_quadratic_edges_equal_the_dense_edges_at_their_linearization(path):
    """At the poses it was made at, an edge's quadratic model has the dense edge's blocks and
    energy, edge by edge (the compiled and PyTorch paths alike)."""
    poses, graph, X_j, valid = _tiny_graph()
    dense = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid)
    model = dense.quadratic_model(poses)
    a, b = dense.linearize(poses), model.linearize(poses)
    for name in ("i", "j", "H_ii", "H_jj", "H_ij", "g_i", "g_j"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(model.cost(poses), dense.cost(poses), rtol=1e-12, atol=0)
    torch.testing.assert_close(model.c.sum(), dense.cost(poses), rtol=1e-12, atol=0)
    assert model.motion(poses).abs().max() < 1e-12


def test_quadratic_edges_match_the_dense_energy_to_first_order():
    """Moved away from its linearization, an edge's model keeps the dense energy and its
    slope: the gap is second order in the step (halving the step about quarters it)."""
    poses, graph, _, valid = _tiny_graph()
    dense = RayRangeFactors(
        graph.i, graph.j, graph.X_i, graph.X_j, graph.q, valid, sigma_ray=3e-3, sigma_dist=0.05
    )
    model = dense.quadratic_model(poses)
    tau = sim3_log(random_sim3(4, 10.0, 0.5, 0.05, torch.Generator().manual_seed(1)))
    gaps = []
    for step in (2e-3, 1e-3):
        moved = sim3_compose(sim3_exp(step * tau), poses)
        gaps.append(float((dense.cost(moved) - model.cost(moved)).abs()))
    assert 0 < gaps[1] < 0.35 * gaps[0], gaps  # 0.25 measured; a first-order gap: 0.5


def test_edge_weights_scale_each_edges_blocks_and_energy(path):
    """Weighed edges (a thinned edge standing for all its matches): each edge's blocks,
    relative blocks and energy times its weight, its Huber weights unchanged."""
    poses, graph, X_j, valid = _tiny_graph()
    plain = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid)
    weighed = RayRangeFactors(graph.i, graph.j, graph.X_i, X_j, graph.q, valid, chunk_matches=40)
    weight = torch.linspace(1.0, 7.0, plain.num_edges, dtype=torch.float64)
    weighed.weigh_edges(weight)
    a, b = plain.linearize(poses), weighed.linearize(poses)
    for name, shape in (("H_ii", (-1, 1, 1)), ("H_ij", (-1, 1, 1)), ("g_j", (-1, 1))):
        expected = getattr(a, name) * weight.reshape(shape).to(getattr(a, name))
        torch.testing.assert_close(getattr(b, name), expected, rtol=1e-10, atol=1e-12)
    every = slice(0, plain.num_edges)
    torch.testing.assert_close(
        weighed.edge_costs(poses, every), plain.edge_costs(poses, every) * weight
    )
    torch.testing.assert_close(weighed.cost(poses), (plain.edge_costs(poses, every) * weight).sum())
    model = weighed.quadratic_model(poses)
    torch.testing.assert_close(model.c, plain.edge_costs(poses, every) * weight)
    with pytest.raises(InputError, match="edge weights"):
        plain.weigh_edges(torch.zeros(plain.num_edges))
    with pytest.raises(InputError, match="edge weights"):
        plain.weigh_edges(torch.ones(plain.num_edges + 1))
