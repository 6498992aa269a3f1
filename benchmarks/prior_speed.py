"""Speed of the MASt3R prior on this machine, per precision (a script, not a test).

Builds the full released configuration (ViT-L encoder, ViT-B decoders, catmlp+dpt heads) with
seeded random weights (no checkpoint needed) and prints one table per precision: float32, and
bfloat16 where the CPU multiplies it natively (AMX/AVX512-BF16; ``--dtypes`` forces a list).
Per image size:

* ms per ``encode`` of one image (wall-clock, and process CPU time over all threads);
* ms per ``decode`` of one ordered pair (both decoders and both heads);
* ms per ``decode_symmetric`` of one pair ((i, j) and (j, i) in one batched call);
* for bfloat16, the relative error ``||x_bf16 - x_fp32|| / ||x_fp32||`` of the encoder tokens
  and of every output map;
* with ``--official DIR`` (an extracted naver/mast3r, see ``prior_vs_official.py``), the
  official code's float32 encode and decode on the same weights, and ours / official time.

Ours and the official code run alternately in the same process (median of ``--repeats``).

Usage::

    python benchmarks/prior_speed.py [--threads 2] [--repeats 2] [--sizes 512x384 512x288]
        [--dtypes fp32 bf16] [--official /tmp/official/mast3r [--deps /tmp/official/deps]]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import torch

from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, MASt3RPrior
from como3r.prior.mast3r.precision import cpu_supports_bf16

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}
Timing = tuple[float, float]


def interleaved(runs: dict[str, Callable[[], object]], repeats: int) -> dict[str, Timing]:
    """Median wall-clock and process CPU time in ms of each run, after one warm-up call each;
    the runs alternate so that changes of the machine's load hit them alike.

    The CPU time (all threads) is less sensitive to other processes sharing the cores.
    """
    for run in runs.values():
        run()
    samples: dict[str, list[Timing]] = {key: [] for key in runs}
    for _ in range(repeats):
        for key, run in runs.items():
            start_wall, start_cpu = time.perf_counter(), time.process_time()
            run()
            samples[key].append(
                ((time.perf_counter() - start_wall) * 1e3, (time.process_time() - start_cpu) * 1e3)
            )
    return {
        key: (statistics.median(w for w, _ in s), statistics.median(c for _, c in s))
        for key, s in samples.items()
    }


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    """``||value - reference|| / ||reference||`` in float64."""
    reference = reference.double()
    return float((value.double() - reference).norm() / reference.norm())


def errors_vs_fp32(network: MASt3RNetwork, images: torch.Tensor) -> str:
    """Relative errors of bfloat16 against float32: encoder tokens and every output map."""
    outputs = {}
    for dtype in (torch.float32, torch.bfloat16):
        prior = MASt3RPrior(network, dtype=dtype)
        encodings = prior.encode(images)
        outputs[dtype] = encodings[0].tokens, prior.decode(*encodings)
    (tokens32, pred32), (tokens16, pred16) = outputs[torch.float32], outputs[torch.bfloat16]
    parts = [f"tokens {relative_error(tokens16, tokens32):.1e}"]
    for f in fields(pred32):
        parts.append(
            f"{f.name} {relative_error(getattr(pred16, f.name), getattr(pred32, f.name)):.1e}"
        )
    return ", ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--sizes",
        nargs="+",
        default=["512x384", "512x288"],
        help="W x H image sizes, multiples of 16",
    )
    parser.add_argument(
        "--dtypes",
        nargs="+",
        choices=list(DTYPES),
        help="default: fp32, and bf16 on a CPU with AMX/AVX512-BF16",
    )
    parser.add_argument("--official", type=Path, help="extracted naver/mast3r (optional)")
    parser.add_argument(
        "--deps",
        type=Path,
        default=Path("/tmp/official/deps"),
        help="extra import path for the official code's einops",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    dtypes = args.dtypes or (["fp32", "bf16"] if cpu_supports_bf16() else ["fp32"])

    start = time.perf_counter()
    official = None
    if args.official is None:
        network = MASt3RNetwork(MASt3RConfig())
    else:
        # the sibling script (this directory is on sys.path when run as a script)
        from prior_vs_official import Official, build_pair, import_official

        official_model, network = build_pair(
            import_official(args.official.resolve(), args.deps), MASt3RConfig(), seed=0
        )
        official = Official(official_model)
    build_s = time.perf_counter() - start
    parameters = sum(p.numel() for p in network.parameters())
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__}, {args.threads} threads, median of {args.repeats} "
        f"interleaved runs, load average {os.getloadavg()[0]:.1f} (other processes share "
        f"the cores), bf16 instructions: {'yes' if cpu_supports_bf16() else 'no'}"
    )
    print(
        f"network: full configuration, {parameters:,} parameters, random weights "
        f"(built in {build_s:.1f} s){', official code on the same weights' if official else ''}"
    )

    # the priors share one network, whose compute dtype is set by the prior about to run
    priors = {name: MASt3RPrior(network, dtype=DTYPES[name]) for name in dtypes}

    def use(name: str) -> MASt3RPrior:
        network.set_compute_dtype(DTYPES[name])
        return priors[name]

    results: dict[str, dict[str, Timing]] = {}
    notes: dict[str, str] = {}
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        generator = torch.Generator().manual_seed(1)
        images = torch.rand(2, 3, height, width, generator=generator) * 2 - 1
        runs: dict[str, Callable[[], object]] = {}
        for name in dtypes:
            encodings = use(name).encode(images)
            runs[f"{name} encode"] = lambda n=name: use(n).encode(images[:1])
            runs[f"{name} decode"] = lambda n=name, e=encodings: use(n).decode(*e)
            runs[f"{name} symmetric"] = lambda n=name, e=encodings: use(n).decode_symmetric(
                [tuple(e)]
            )
        if official is not None:
            off_enc = [official.encode(images[b : b + 1]) for b in range(2)]
            runs["official encode"] = lambda: official.encode(images[:1])
            runs["official decode"] = lambda: official.decode(*off_enc)
        results[size] = interleaved(runs, args.repeats)
        if "bf16" in dtypes:
            notes[size] = errors_vs_fp32(network, images)
        print(f"measured {size} (load average {os.getloadavg()[0]:.1f})", flush=True)

    for name in dtypes:
        header = f"{'W x H':>8} {'encode ms':>15} {'decode ms':>15} {'sym. pair ms':>15}" + (
            f" {'enc. ours/off.':>15} {'dec. ours/off.':>15}" if official else ""
        )
        print(
            f"\n{name}: wall-clock ms (process CPU time over all threads)"
            + ("; ours / official float32 time (CPU-time ratio)" if official else "")
        )
        print(header)
        print("-" * len(header))
        for size, timing in results.items():
            columns = " ".join(
                f"{f'{wall:.0f} ({cpu:.0f})':>15}"
                for wall, cpu in (
                    timing[f"{name} {step}"] for step in ("encode", "decode", "symmetric")
                )
            )
            if official is not None:
                for step in ("encode", "decode"):
                    (ours_w, ours_c), (off_w, off_c) = (
                        timing[f"{name} {step}"],
                        timing[f"official {step}"],
                    )
                    columns += f" {f'{ours_w / off_w:.2f} ({ours_c / off_c:.2f})':>15}"
            print(f"{size:>8} {columns}")
    for size, note in notes.items():
        print(f"\n{size} bf16 vs fp32 relative error: {note}")


if __name__ == "__main__":
    main()
