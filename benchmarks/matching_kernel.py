"""Descriptor-refinement window search (C-Sec. 3.3 matching) per score dtype (not a test).

Times :func:`como3r.frontend.matching.refine_with_descriptors` on random unit descriptors
at one resolution, with the window search scoring in each dtype, and prints one table of
seconds per call, the ratio to float16 (MASt3R-SLAM's choice) and the share of refined
pixels equal to float16's. The default dtype is ``matching._SCORE_DTYPE``.

    python benchmarks/matching_kernel.py [--size 512x384] [--threads 1] [--repeats 3]
"""

from __future__ import annotations

import argparse
import time

import torch

from como3r.frontend import matching

DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32}


def problem(width: int, height: int, flow: int = 8, dim: int = 24,
            seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(D_search (1, H, W, d), D_query (1, H*W, d), pixel (1, H*W, 2))``: unit descriptors,
    queries near their search pixel, starting points up to ``flow`` pixels off."""
    gen = torch.Generator().manual_seed(seed)
    D = torch.nn.functional.normalize(torch.randn(1, height, width, dim, generator=gen), dim=-1)
    noise = 0.3 * torch.randn(1, height * width, dim, generator=gen)
    D_query = torch.nn.functional.normalize(D.reshape(1, -1, dim) + noise, dim=-1)
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixel = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[None]
    jitter = torch.randint(-flow, flow + 1, pixel.shape, generator=gen)
    pixel = (pixel + jitter).clamp(min=0).minimum(torch.tensor([width - 1, height - 1]))
    return D, D_query, pixel


def time_dtype(dtype: torch.dtype, inputs: tuple, repeats: int) -> tuple[float, torch.Tensor]:
    """Best-of-``repeats`` seconds of one refinement scoring in ``dtype``, and its output."""
    default = matching._SCORE_DTYPE
    matching._SCORE_DTYPE = dtype
    try:
        best, out = float("inf"), None
        for _ in range(repeats):
            start = time.perf_counter()
            out = matching.refine_with_descriptors(*inputs, radius=3, dilation_max=5)
            best = min(best, time.perf_counter() - start)
    finally:
        matching._SCORE_DTYPE = default
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="512x384")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.split("x"))
    inputs = problem(width, height)
    results = {name: time_dtype(dtype, inputs, args.repeats) for name, dtype in DTYPES.items()}
    base_seconds, base_out = results["float16"]
    print(f"refine_with_descriptors at {args.size}, radius 3, dilations 5..1, "
          f"{args.threads} thread(s); default {matching._SCORE_DTYPE}")
    print(f"{'dtype':<10} {'seconds':>8} {'fp16 / this':>12} {'same as fp16':>13}")
    for name, (seconds, out) in results.items():
        same = (out == base_out).all(-1).float().mean().item()
        print(f"{name:<10} {seconds:8.3f} {base_seconds / seconds:12.2f} {same:13.4f}")


if __name__ == "__main__":
    main()
