"""Tests of como3r.backend.depth_refinement (C-Eq. 19-24, C-Tab. 5)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest
import torch

from como3r.backend import cpu_kernels
from como3r.backend.depth_problem import build_problem, chunk_streams, match_streams
from como3r.backend.depth_refinement import _Refiner, refine_depths, refine_keyframes
from como3r.backend.segments import parameter_labels, segment_keyframe
from como3r.config import DepthRefinementConfig
from como3r.errors import ConfigError, InputError
from como3r.frontend.graph import Edge
from como3r.frontend.pairs import DirectedMatches
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_identity, sim3_inverse

H, W, F = 40, 56, 45.0
SHIFT = 4  # keyframe 1's pixel (v, u) sees keyframe 0's pixel (v, u + SHIFT)
# About 37 pixels per segment on these small images (C-Tab. 3's 200 suits 512-pixel images).
CONFIG = DepthRefinementConfig(slic_segments=60)


@dataclass
class FakeKeyframe:
    """The keyframe attributes the refinement reads."""

    X_hat: torch.Tensor
    X_init: torch.Tensor
    C: torch.Tensor

    def mean_confidence(self) -> torch.Tensor:
        return self.C


@dataclass
class Scene:
    keyframes: list[FakeKeyframe]
    truth: list[torch.Tensor]  # true pointmaps (H, W, 3) of both keyframes
    poses: torch.Tensor  # (2, 8)
    edges: list[Edge]
    labels: list[torch.Tensor]


def scene_points(width: int, dtype: torch.dtype) -> torch.Tensor:
    """A slanted floor-like plane with a box in front, seen by a pinhole camera."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij"
    )
    rays = torch.stack([(u - W / 2) / F, (v - H / 2) / F, torch.ones_like(u)], dim=-1)
    z = 3.0 - 0.02 * v + 0.005 * u
    box = (u >= 14) & (u < 30) & (v >= 10) & (v < 26)
    return rays * torch.where(box, 2.0, z)[..., None]


def shifted_matches(valid_columns: torch.Tensor, shift: int, q: float) -> DirectedMatches:
    """Pixel (v, u + shift) of i for every pixel (v, u) of j, valid where in the image."""
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    idx = (v * W + (u + shift).clamp(0, W - 1)).reshape(-1)
    valid = valid_columns(u).reshape(-1)
    return DirectedMatches(idx=idx, valid=valid, q=torch.full((H * W,), q))


def make_scene(
    dtype: torch.dtype, segment_error: float = 0.1, ref_noise: float = 0.0, seed: int = 0
) -> Scene:
    """Keyframe 0 (pinned, identity pose) and keyframe 1 whose ``X_init`` carries a
    multiplicative error that is constant on each of its segments; exact correspondences."""
    generator = torch.Generator().manual_seed(seed)
    wide = scene_points(W + SHIFT, torch.float64)
    T_WC1 = sim3_exp(torch.tensor([0.3, -0.1, 0.05, 0.02, -0.03, 0.01, 0.0], dtype=torch.float64))
    poses = torch.stack([sim3_identity(dtype=torch.float64), T_WC1])
    X0 = wide[:, :W]
    X1 = sim3_act(sim3_inverse(T_WC1), wide[:, SHIFT:])
    C = torch.full((H, W), 3.0, dtype=dtype)
    labels1 = segment_keyframe(X1.to(dtype), C, CONFIG)
    errors = segment_error * (
        2 * torch.rand(int(labels1.max()) + 1, generator=generator, dtype=torch.float64) - 1
    )
    X1_init = X1 * torch.where(labels1 >= 0, errors[labels1.clamp_min(0)], 0.0).exp()[..., None]
    X0_obs = X0 * (1 + ref_noise * torch.randn(H, W, 1, generator=generator, dtype=torch.float64))
    keyframes = [
        FakeKeyframe(X0_obs.to(dtype), X0_obs.to(dtype), C),
        FakeKeyframe(X1_init.to(dtype), X1_init.to(dtype), C),
    ]
    edges = [
        Edge(0, 1, shifted_matches(lambda u: u + SHIFT < W, SHIFT, 2.0)),
        Edge(1, 0, shifted_matches(lambda u: u >= SHIFT, -SHIFT, 2.0)),
    ]
    labels = [segment_keyframe(keyframes[0].X_hat, C, CONFIG), labels1]
    return Scene(keyframes, [X0.to(dtype), X1.to(dtype)], poses.to(dtype), edges, labels)


def log_depth_error(X: torch.Tensor, truth: torch.Tensor, labels: torch.Tensor) -> float:
    """Mean ``|log(||X|| / ||X_true||)|`` over labelled pixels."""
    ratio = (X.norm(dim=-1) / truth.norm(dim=-1)).log().abs()
    return float(ratio[labels >= 0].mean())


def refine(scene: Scene, config: DepthRefinementConfig, labels=None):
    return refine_depths(
        scene.keyframes,
        scene.poses,
        scene.edges,
        {0: 0, 1: 1},
        scene.labels if labels is None else labels,
        config,
        pinned=[0],
    )


def test_segment_refinement_removes_most_of_a_per_segment_error(dtype):
    scene = make_scene(dtype)
    assert (scene.labels[1] >= 0).float().mean() > 0.9
    before = log_depth_error(scene.keyframes[1].X_hat, scene.truth[1], scene.labels[1])
    X_new, log_scales, report = refine(scene, CONFIG)
    after = log_depth_error(X_new[1], scene.truth[1], scene.labels[1])
    assert before > 0.03
    assert after < 0.25 * before
    assert report.final_cost < report.initial_cost
    assert report.iterations == CONFIG.inner_iters
    assert len(report.cost_history) == CONFIG.inner_iters + 1
    assert log_scales[1].shape == (int(scene.labels[1].max()) + 1,)
    assert X_new[1].dtype == dtype


def test_pinned_keyframe_is_unchanged():
    scene = make_scene(torch.float32)
    before = scene.keyframes[0].X_hat.clone()
    X_new, _, report = refine(scene, CONFIG)
    assert X_new[0] is scene.keyframes[0].X_hat
    assert torch.equal(X_new[0], before)
    assert report.num_parameters == int(scene.labels[1].max()) + 1


def test_points_stay_on_the_snapshot_rays():
    scene = make_scene(torch.float64)
    X_new, _, _ = refine(scene, CONFIG)
    X_init = scene.keyframes[1].X_init
    cosine = (X_new[1] * X_init).sum(-1) / (X_new[1].norm(dim=-1) * X_init.norm(dim=-1))
    assert torch.allclose(cosine, torch.ones_like(cosine), atol=1e-9)


def test_step_clip_is_respected():
    scene = make_scene(torch.float64, segment_error=1.5)
    config = dataclasses.replace(CONFIG, inner_iters=1)
    _, log_scales, report = refine(scene, config)
    assert report.clipped_steps > 0
    assert report.max_step <= config.step_clip + 1e-12
    assert float(log_scales[1].abs().max()) <= config.step_clip + 1e-12


def test_per_pixel_is_noisier_than_per_segment_under_noise():
    scene = make_scene(torch.float64, ref_noise=0.01, seed=3)
    errors = {}
    for variant in ("pixel", "pixel_laplacian"):
        config = dataclasses.replace(CONFIG, variant=variant)
        labels = [parameter_labels(kf.X_hat, kf.C, config) for kf in scene.keyframes]
        X_new, _, _ = refine(scene, config, labels)
        errors[variant] = log_depth_error(X_new[1], scene.truth[1], scene.labels[1])
    X_new, _, _ = refine(scene, CONFIG)
    errors["segment"] = log_depth_error(X_new[1], scene.truth[1], scene.labels[1])
    # Per pixel, each depth copies the noise of its one match; a segment averages its matches.
    assert errors["segment"] < 0.5 * errors["pixel"]
    assert errors["pixel_laplacian"] < errors["pixel"]


def test_gradient_is_exact_and_hessian_is_positive():
    scene = make_scene(torch.float64)
    config = CONFIG
    problem, _, _ = build_problem(
        scene.keyframes, scene.poses, scene.edges, {0: 0, 1: 1}.get, scene.labels, config, {0}
    )
    refiner = _Refiner(problem, config, huber_k=1.345)
    generator = torch.Generator().manual_seed(0)
    s = (
        0.05 * torch.randn(problem.s_start.shape, generator=generator, dtype=torch.float64)
    ).requires_grad_()
    H, g, _ = refiner.normal_equations(s.detach())
    refiner.energy(s).backward()
    # The energies carry no 1/2 prefactor (C-Sec. A.6): g is half the energy's gradient.
    torch.testing.assert_close(g, 0.5 * s.grad, rtol=1e-8, atol=1e-8)
    assert (H >= config.lambda_prior).all()


def test_without_edges_the_prior_pulls_to_the_snapshot():
    scene = make_scene(torch.float64)
    # X_hat twice as far as the snapshot: the warm start is log 2, the prior pulls to 0.
    scene.keyframes[1].X_hat = 2.0 * scene.keyframes[1].X_init
    X_new, log_scales, report = refine_depths(
        scene.keyframes,
        scene.poses,
        [],
        {0: 0, 1: 1},
        scene.labels,
        dataclasses.replace(CONFIG, lambda_smooth=0.0),
        pinned=[0],
    )
    assert report.num_matches == 0
    assert float(log_scales[1].abs().max()) < 0.05 * torch.log(torch.tensor(2.0))
    assert report.max_change == pytest.approx(float(torch.log(torch.tensor(2.0))), rel=0.05)


def test_refine_keyframes_segments_refines_and_writes_back_in_place():
    scene = make_scene(torch.float32)
    labels = [segment_keyframe(kf.X_hat, kf.C, CONFIG) for kf in scene.keyframes]
    expected, _, _ = refine(scene, CONFIG, labels)
    before = log_depth_error(scene.keyframes[1].X_hat, scene.truth[1], scene.labels[1])
    report = refine_keyframes(
        scene.keyframes, scene.poses, scene.edges, {0: 0, 1: 1}, CONFIG, pinned=[0]
    )
    assert torch.equal(scene.keyframes[1].X_hat, expected[1])
    # Segments of the corrupted pointmap only roughly follow the error's segments.
    after = log_depth_error(scene.keyframes[1].X_hat, scene.truth[1], scene.labels[1])
    assert after < 0.8 * before
    assert report.max_change > 0.01


def test_bad_inputs_raise_clear_errors():
    scene = make_scene(torch.float32)
    with pytest.raises(InputError, match="not in key_to_index"):
        refine_depths(scene.keyframes, scene.poses, scene.edges, {0: 0}, scene.labels, CONFIG)
    with pytest.raises(InputError, match="poses"):
        refine_depths(
            scene.keyframes, scene.poses[:1], scene.edges, {0: 0, 1: 1}, scene.labels, CONFIG
        )
    with pytest.raises(InputError, match="label map"):
        refine_depths(
            scene.keyframes,
            scene.poses,
            scene.edges,
            {0: 0, 1: 1},
            [scene.labels[0], scene.labels[1][:-1]],
            CONFIG,
        )
    with pytest.raises(ConfigError, match="variant"):
        refine_depths(
            scene.keyframes,
            scene.poses,
            scene.edges,
            {0: 0, 1: 1},
            scene.labels,
            dataclasses.replace(CONFIG, variant="voxel"),
        )


def test_boundary_term_pairs_and_log_depth_ratios():
    # Two segments side by side on a 2 x 4 image: left half at range 1, right half at 2.
    X = torch.zeros(2, 4, 3, dtype=torch.float64)
    X[..., 2] = torch.tensor([[1.0, 1.0, 2.0, 2.0], [1.0, 1.0, 2.0, 2.0]])
    keyframe = FakeKeyframe(X, X.clone(), torch.full((2, 4), 3.0))
    labels = torch.tensor([[0, 0, 1, 1], [0, 0, 1, 1]])
    problem, _, _ = build_problem(
        [keyframe],
        torch.tensor([[0.0] * 6 + [1.0, 1.0]]),
        [],
        [0].__getitem__,
        [labels],
        CONFIG,
        set(),
    )
    assert problem.bnd_a.tolist() == [0] and problem.bnd_b.tolist() == [1]
    # default: the residual s_a - s_b keeps the prior's depth jump between the segments
    assert problem.delta.tolist() == [0.0]
    printed = dataclasses.replace(CONFIG, boundary_residual="log_depth")
    problem, _, _ = build_problem(
        [keyframe],
        torch.tensor([[0.0] * 6 + [1.0, 1.0]]),
        [],
        [0].__getitem__,
        [labels],
        printed,
        set(),
    )
    # C-Eq. 22 as printed: Delta_ab = mean over the boundary of log d_a - log d_b
    assert problem.delta.tolist() == pytest.approx([-float(torch.log(torch.tensor(2.0)))])
    pixel_config = dataclasses.replace(CONFIG, variant="pixel_laplacian")
    pixels = torch.arange(8).reshape(2, 4)
    problem, _, _ = build_problem(
        [keyframe],
        torch.tensor([[0.0] * 6 + [1.0, 1.0]]),
        [],
        [0].__getitem__,
        [pixels],
        pixel_config,
        set(),
    )
    assert problem.bnd_a.numel() == 2 * 3 + 4  # every 4-neighbour pair once
    no_boundary = dataclasses.replace(CONFIG, variant="pixel")
    problem, _, _ = build_problem(
        [keyframe],
        torch.tensor([[0.0] * 6 + [1.0, 1.0]]),
        [],
        [0].__getitem__,
        [pixels],
        no_boundary,
        set(),
    )
    assert problem.bnd_a.numel() == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_normal_equations_equal_the_pytorch_ones(dtype, monkeypatch):
    """The compiled CPU loop (every CPU problem) and PyTorch (CUDA, autograd) give the same
    Hessian, gradient and energy, with one thread or two (the matches cut into blocks)."""
    monkeypatch.setattr(cpu_kernels, "BLOCK", 256)
    scene = make_scene(dtype)
    problem, _, _ = build_problem(
        scene.keyframes, scene.poses, scene.edges, {0: 0, 1: 1}.get, scene.labels, CONFIG, {0}
    )
    refiner = _Refiner(problem, CONFIG, huber_k=1.345)
    s = 0.05 * torch.randn(
        problem.s_start.shape, generator=torch.Generator().manual_seed(3), dtype=dtype
    )
    before = torch.get_num_threads()
    try:
        compiled = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            compiled.append((*refiner.normal_equations(s), float(refiner.energy(s))))
    finally:
        torch.set_num_threads(before)
    monkeypatch.setattr(_Refiner, "_runs_compiled", lambda self, s: False)
    H, g, energy = refiner.normal_equations(s)
    tolerance = 1e-5 if dtype == torch.float32 else 1e-10
    for H_c, g_c, energy_c, final_c in compiled:
        torch.testing.assert_close(H_c, H, rtol=tolerance, atol=0)
        torch.testing.assert_close(g_c, g, rtol=tolerance, atol=tolerance * g.abs().max())
        assert energy_c == pytest.approx(energy, rel=tolerance)
        assert final_c == pytest.approx(float(refiner.energy(s)), rel=tolerance)
    assert torch.equal(compiled[0][0], compiled[1][0]) and compiled[0][2] == compiled[1][2]
    assert problem.match_a.numel() > 4 * 256 and (H > CONFIG.lambda_prior).any()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_chunk_streams_are_the_flattened_problems_streams(dtype):
    """The compiled packing writes the matches the flattened problem keeps (valid, finite
    q > 0, both pixels usable, one free), in its order, with its values: the data terms of
    both are the same."""
    scene = make_scene(dtype)
    edges = list(scene.edges)
    m = edges[0].matches  # a non-finite, a zero and a negative confidence, and an invalid match
    q = m.q.clone()
    valid_pixels = torch.nonzero(m.valid).flatten()
    q[valid_pixels[:3]] = torch.tensor([float("nan"), 0.0, -1.0])
    edges[0] = Edge(0, 1, DirectedMatches(m.idx, m.valid, q))
    args = (scene.keyframes, scene.poses, edges, {0: 0, 1: 1}.get, scene.labels, CONFIG, {0})
    problem, _, _ = build_problem(*args, data_only=True, ranges=[2.0, 3.0])
    reference = match_streams(problem)
    streams = chunk_streams(*args, ranges=[2.0, 3.0])
    assert streams.num_matches > 1000
    assert torch.equal(streams.param_a, reference.param_a)
    assert torch.equal(streams.param_b, reference.param_b)
    tolerance = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(streams.values, reference.values, rtol=tolerance, atol=tolerance)
    torch.testing.assert_close(streams.sqrt_w, reference.sqrt_w, rtol=tolerance, atol=0)

    m = edges[1].matches
    outside = m.idx.clone()
    outside[torch.nonzero(m.valid).flatten()[0]] = m.idx.numel()
    edges[1] = Edge(1, 0, DirectedMatches(outside, m.valid, m.q))
    with pytest.raises(InputError, match="outside"):
        chunk_streams(
            scene.keyframes, scene.poses, edges, {0: 0, 1: 1}.get, scene.labels, CONFIG, {0}
        )
