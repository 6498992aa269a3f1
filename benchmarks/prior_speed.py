"""Speed of the MASt3R prior on this machine, float32 and bfloat16 (a script, not a test).

Builds the full released configuration (ViT-L encoder, ViT-B decoders, catmlp+dpt heads) with
seeded random weights (no checkpoint needed) and prints, per image size and precision:

* ms per ``encode`` of one image (wall-clock, and process CPU time over all threads);
* ms per ``decode`` of one ordered pair (both decoders and both heads);
* ms per ``decode_symmetric`` of one pair ((i, j) and (j, i) in one batched call);
* for bfloat16, the relative error ``||x_bf16 - x_fp32|| / ||x_fp32||`` of the encoder tokens
  and of every output map.

Usage::

    python benchmarks/prior_speed.py [--threads 2] [--repeats 2] [--sizes 512x384 512x288]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from dataclasses import fields
from typing import Callable

import torch

from como3r.prior.base import PairPrediction
from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, MASt3RPrior


def milliseconds(run: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall-clock and process CPU time of ``run`` in ms, after one warm-up call.

    The CPU time (all threads) is less sensitive to other processes sharing the cores.
    """
    run()
    wall, cpu = [], []
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        run()
        wall.append((time.perf_counter() - start_wall) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    return statistics.median(wall), statistics.median(cpu)


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    """``||value - reference|| / ||reference||`` in float64."""
    reference = reference.double()
    return float((value.double() - reference).norm() / reference.norm())


def measure(
    prior: MASt3RPrior, images: torch.Tensor, repeats: int
) -> tuple[dict[str, tuple[float, float]], torch.Tensor, PairPrediction]:
    """Timings of one prior on two images ``(2, 3, H, W)``, its tokens and prediction."""
    encodings = prior.encode(images)
    timings = {
        "encode": milliseconds(lambda: prior.encode(images[:1]), repeats),
        "decode": milliseconds(lambda: prior.decode(*encodings), repeats),
        "symmetric": milliseconds(lambda: prior.decode_symmetric([tuple(encodings)]), repeats),
    }
    return timings, encodings[0].tokens, prior.decode(*encodings)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--sizes", nargs="+", default=["512x384", "512x288"],
                        help="W x H image sizes, multiples of 16")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    start = time.perf_counter()
    network = MASt3RNetwork(MASt3RConfig())
    build_s = time.perf_counter() - start
    parameters = sum(p.numel() for p in network.parameters())
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"torch {torch.__version__}, {args.threads} threads, median of {args.repeats} runs, "
          f"load average {os.getloadavg()[0]:.1f} (other processes share the cores)")
    print(f"network: full configuration, {parameters:,} parameters, random weights "
          f"(built in {build_s:.1f} s)\n")

    header = (f"{'W x H':>8} {'dtype':>9} {'encode ms':>15} {'decode ms':>15} "
              f"{'sym. pair ms':>15}  rel. error bf16 vs fp32")
    print("times: wall-clock (process CPU time over all threads)")
    print(header)
    print("-" * len(header) + "-" * 40)
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        generator = torch.Generator().manual_seed(1)
        images = torch.rand(2, 3, height, width, generator=generator) * 2 - 1
        results = {}
        for dtype in (torch.float32, torch.bfloat16):
            prior = MASt3RPrior(network, dtype=dtype)
            results[dtype] = measure(prior, images, args.repeats)
            timings = results[dtype][0]
            errors = ""
            if dtype == torch.bfloat16:
                _, tokens32, pred32 = results[torch.float32]
                _, tokens16, pred16 = results[dtype]
                parts = [f"tokens {relative_error(tokens16, tokens32):.1e}"]
                for f in fields(pred32):
                    error = relative_error(getattr(pred16, f.name), getattr(pred32, f.name))
                    parts.append(f"{f.name} {error:.1e}")
                errors = ", ".join(parts)
            columns = " ".join(f"{f'{wall:.0f} ({cpu:.0f})':>15}" for wall, cpu in
                               (timings["encode"], timings["decode"], timings["symmetric"]))
            print(f"{size:>8} {str(dtype).removeprefix('torch.'):>9} {columns}  {errors}",
                  flush=True)


if __name__ == "__main__":
    main()
