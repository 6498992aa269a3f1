"""Dense matching's per-pixel work, its CPU path vs the PyTorch one (not a test).

Times the descriptor-refinement window search (:func:`como3r.frontend.matching.
refine_with_descriptors`, radius 3, dilations 5..1) on random unit descriptors, and the
iterative ray projection (:func:`~como3r.frontend.matching.project_iteratively`, C-Eq. 1) on
a smooth surface seen from a moved camera with the nearest pixel centre of each optimum, both
at one resolution, through the compiled
loops of :mod:`como3r.frontend.cpu_kernels` (what CPU tensors take) and the vectorised
PyTorch path (what CUDA tensors take); and the field-of-view bounds of a pair's
co-visibility test (:func:`como3r.frontend.pairs.covisible_fraction`: the 1 % and 99 %
quantiles of a view's rays on ``z = 1``) by numpy's selection (CPU) vs ``torch.quantile``.
Prints seconds per call (best of ``--repeats``, after one warm-up call that compiles), the
ratio, and the share of equal results (quantiles: equal to float rounding).

    python benchmarks/matching_kernel.py [--size 512x384] [--threads 1] [--repeats 3]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import torch

from como3r.frontend import cpu_kernels, cpu_window_search, matching, pairs
from como3r.geometry.camera import intrinsics_matrix, unproject_depth
from como3r.geometry.lie import sim3_act, sim3_exp


def descriptor_problem(
    width: int, height: int, flow: int = 8, dim: int = 24, seed: int = 0
) -> tuple:
    """``(D_search (1, H, W, d), D_query (1, H*W, d), pixel (1, H*W, 2), radius,
    dilation_max, active)``: unit descriptors, queries near their search pixel, starting
    points up to ``flow`` pixels off."""
    gen = torch.Generator().manual_seed(seed)
    D = torch.nn.functional.normalize(torch.randn(1, height, width, dim, generator=gen), dim=-1)
    noise = 0.3 * torch.randn(1, height * width, dim, generator=gen)
    D_query = torch.nn.functional.normalize(D.reshape(1, -1, dim) + noise, dim=-1)
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixel = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[None]
    jitter = torch.randint(-flow, flow + 1, pixel.shape, generator=gen)
    pixel = (pixel + jitter).clamp(min=0).minimum(torch.tensor([width - 1, height - 1]))
    return D, D_query, pixel, 3, 5, None


def ray_problem(width: int, height: int) -> tuple:
    """``(rays_grad (1, H, W, 9), target_rays (1, H*W, 3), p_init (1, H*W, 2), max_iters,
    lambda_init, convergence_tol)`` float32: a curved surface 4-7 focal lengths away seen
    by a camera moved by 5 % of its depth and turned by 3 degrees."""
    focal = 0.8 * width
    K = intrinsics_matrix(focal, focal, (width - 1) / 2, (height - 1) / 2, dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64),
        torch.arange(width, dtype=torch.float64),
        indexing="ij",
    )
    depth = 5.0 + u / width + 0.3 * torch.sin(u / (0.2 * width)) * torch.cos(v / (0.15 * height))
    X = unproject_depth(depth, K)
    T = sim3_exp(
        torch.tensor([0.25, -0.1, 0.1, 0.01, math.radians(3.0), 0.0, 0.0], dtype=torch.float64)
    )
    X_moved = sim3_act(T[None, None], X)
    rays_grad = matching.ray_image_with_gradients(X[None].float())
    target = torch.nn.functional.normalize(X_moved.reshape(1, -1, 3), dim=-1).float()
    p_init = torch.stack([u, v], -1).reshape(1, -1, 2).float()
    return rays_grad, target, p_init, 10, 1e-8, 1e-6


def plane_problem(width: int, height: int) -> tuple:
    """A view's rays on the plane ``z = 1`` ``(H W, 2)`` and the two bounds' quantiles."""
    rays, _ = ray_problem(width, height)[:2]
    plane = rays[0, ..., :2].reshape(-1, 2) / rays[0, ..., 2:3].reshape(-1, 1)
    return plane, (pairs.FIELD_OF_VIEW_QUANTILE, 1.0 - pairs.FIELD_OF_VIEW_QUANTILE)


def sorted_quantiles(x: torch.Tensor, qs: tuple[float, ...]) -> torch.Tensor:
    """What covisible_fraction did before: one torch.quantile (a sort) per bound."""
    return torch.stack([torch.quantile(x, q, dim=0) for q in qs])


def vectorised_projection(rays_grad: torch.Tensor, target: torch.Tensor, *rest) -> tuple:
    """The PyTorch path of what the compiled projection does: the iterative projection, then
    the nearest pixel centre by ray."""
    p, converged = matching._project_vectorised(rays_grad, target, *rest)
    return p, matching._nearest_ray_pixel(rays_grad[..., :3], p, target), converged


def best_of(function: Callable, inputs: tuple, repeats: int) -> tuple[float, object]:
    """Best-of-``repeats`` seconds of ``function(*inputs)`` after one warm-up call."""
    out = function(*inputs)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        out = function(*inputs)
        best = min(best, time.perf_counter() - start)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="512x384")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.split("x"))
    loops = {
        "descriptor window search": (
            cpu_window_search.refine_windows,
            matching._refine_vectorised,
            descriptor_problem(width, height),
        ),
        "ray projection": (
            cpu_kernels.project_rays,
            vectorised_projection,
            ray_problem(width, height),
        ),
        "field-of-view bounds": (pairs._quantiles, sorted_quantiles, plane_problem(width, height)),
    }
    print(f"dense matching loops at {args.size}, {args.threads} thread(s)")
    print(f"{'loop':<26} {'CPU path s':>10} {'PyTorch s':>10} {'ratio':>6} {'equal':>6}")
    for name, (compiled, vectorised, inputs) in loops.items():
        compiled_s, compiled_out = best_of(compiled, inputs, args.repeats)
        vectorised_s, vectorised_out = best_of(vectorised, inputs, args.repeats)
        if isinstance(compiled_out, tuple):  # projection: the same nearest pixel
            equal = (compiled_out[1] == vectorised_out[1]).all(-1)
        elif compiled_out.is_floating_point():  # quantiles: interpolated in other orders
            equal = torch.isclose(compiled_out, vectorised_out, rtol=1e-6, atol=0.0).all(-1)
        else:
            equal = (compiled_out == vectorised_out).all(-1)
        print(
            f"{name:<26} {compiled_s:10.3f} {vectorised_s:10.3f} "
            f"{vectorised_s / compiled_s:6.2f} {equal.float().mean().item():6.3f}"
        )


if __name__ == "__main__":
    main()
