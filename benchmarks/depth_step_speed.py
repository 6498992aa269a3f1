"""The terminal cleanup's depth step and the session store's pages: speed of the pieces
(a script, not a test; issue 16 speed claims).

Prints one table of wall milliseconds (median of ``--repeats``, ``--threads`` torch threads
for rows 1-2), ratios within one run, on synthetic 512x384 keyframes:

1. one data pass of the depth refinement (C-Eq. 21-24, the compiled loop of
   :mod:`como3r.backend.cpu_kernels`) over ``--matches`` random matches: ms and ns per match;
2. a working set's match streams: :func:`~como3r.backend.depth_problem.chunk_streams` (one
   compiled pass) against ``match_streams(build_problem(...))`` (the flattened problem's
   tensors, then gathered), 8 keyframes and their 26 edges;
3. SLIC label maps of six keyframes (:func:`~como3r.backend.segments.labels_in_order`) on
   one thread and on two;
4. 15 session-store transactions of 13 + 4 x 1.8 MB of blobs into SQLite in WAL mode at
   the default 4 KiB pages and at the store's :data:`~como3r.store.schema.PAGE_SIZE`.

    python benchmarks/depth_step_speed.py [--repeats 3] [--threads 1] [--matches 6000000]
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from como3r.backend import cpu_kernels
from como3r.backend.depth_problem import build_problem, chunk_streams, match_streams
from como3r.backend.segments import labels_in_order
from como3r.config import DepthRefinementConfig
from como3r.frontend.graph import Edge
from como3r.frontend.pairs import DirectedMatches
from como3r.store.schema import PAGE_SIZE

HEIGHT, WIDTH = 384, 512
KEYFRAMES = 8


def _wall_ms(work: Callable[[], object], repeats: int) -> float:
    work()  # compiles or warms what it uses
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(1000.0 * (time.perf_counter() - start))
    return statistics.median(times)


def data_pass(matches: int, repeats: int) -> tuple[float, float]:
    """ms of one data pass over ``matches`` random matches, and ns per match."""
    rng = np.random.default_rng(0)
    params = 3000
    runs = np.repeat(rng.integers(-1, params, matches // 20 + 1), 20)[:matches]
    rays = rng.normal(size=(matches, 3)).astype(np.float32)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    streams = cpu_kernels.MatchStreams(
        torch.from_numpy(
            np.concatenate(
                [
                    rng.uniform(1, 3, (2, matches)),
                    rays.T,
                    (rays + rng.normal(scale=0.01, size=rays.shape)).T,
                    rng.normal(scale=0.1, size=(3, matches)),
                ]
            ).astype(np.float32)
        ),
        torch.from_numpy(rng.uniform(1, 20, matches).astype(np.float32)),
        torch.from_numpy(runs.astype(np.int64)),
        torch.from_numpy(np.roll(runs, matches // 3).astype(np.int64)),
    )
    s = torch.from_numpy(rng.normal(scale=0.01, size=params))
    ms = _wall_ms(lambda: cpu_kernels.depth_normal_equations(s, streams, 1.345), repeats)
    return ms, 1e6 * ms / matches


@dataclass
class _Keyframe:
    X_hat: torch.Tensor
    X_init: torch.Tensor


def working_set(
    seed: int = 0,
) -> tuple[list[_Keyframe], torch.Tensor, list[Edge], list[torch.Tensor]]:
    """8 keyframes, their poses, edges between keyframes at most 2 apart, label maps."""
    g = torch.Generator().manual_seed(seed)
    keyframes = []
    for _ in range(KEYFRAMES):
        X = torch.randn(HEIGHT, WIDTH, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 2.5])
        keyframes.append(_Keyframe(X, X.clone()))
    labels = [torch.randint(0, 200, (HEIGHT, WIDTH), generator=g) for _ in range(KEYFRAMES)]
    pixels = HEIGHT * WIDTH
    edges = [
        Edge(
            i,
            j,
            DirectedMatches(
                idx=torch.randint(0, pixels, (pixels,), generator=g),
                valid=torch.rand(pixels, generator=g) < 0.6,
                q=torch.rand(pixels, generator=g) + 0.5,
            ),
        )
        for i in range(KEYFRAMES)
        for j in range(KEYFRAMES)
        if i != j and abs(i - j) <= 2
    ]
    poses = torch.tensor([[0.1 * k, 0, 0, 0, 0, 0, 1, 1] for k in range(KEYFRAMES)])
    return keyframes, poses, edges, labels


def streams_table(repeats: int) -> tuple[float, float, int]:
    keyframes, poses, edges, labels = working_set()
    args = (
        keyframes,
        poses,
        edges,
        list(range(KEYFRAMES)).__getitem__,
        labels,
        DepthRefinementConfig(),
        {0},
    )
    ranges = [2.5] * KEYFRAMES
    fused = _wall_ms(lambda: chunk_streams(*args, ranges=ranges), repeats)
    flattened = _wall_ms(
        lambda: match_streams(build_problem(*args, data_only=True, ranges=ranges)[0]), repeats
    )
    return fused, flattened, chunk_streams(*args, ranges=ranges).num_matches


def segmentation(threads: int, repeats: int) -> float:
    keyframes, _, _, _ = working_set()
    v, u = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    depth = 2 + 0.5 * torch.sin(u / 50.0) + 0.3 * torch.cos(v / 30.0) + 0.7 * (u > 300)
    X = torch.stack([(u - WIDTH / 2) / 400 * depth, (v - HEIGHT / 2) / 400 * depth, depth], -1)
    C = torch.full((HEIGHT, WIDTH), 3.0)
    config = DepthRefinementConfig()
    return _wall_ms(
        lambda: list(
            labels_in_order(((k, X * (1 + 0.01 * k), C) for k in range(6)), config, threads)
        ),
        repeats,
    )


def store_pages(page_size: int, repeats: int) -> float:
    big, small = os.urandom(13_000_000), os.urandom(1_800_000)

    def write() -> None:
        with tempfile.TemporaryDirectory() as folder:
            connection = sqlite3.connect(Path(folder) / "store.db", isolation_level=None)
            connection.execute(f"PRAGMA page_size={page_size}")
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute("PRAGMA synchronous=NORMAL")
            connection.execute("CREATE TABLE blobs (id INTEGER PRIMARY KEY, data BLOB)")
            for _ in range(15):
                connection.execute("BEGIN IMMEDIATE")
                for blob in (big, small, small, small, small):
                    connection.execute("INSERT INTO blobs (data) VALUES (?)", (blob,))
                connection.execute("COMMIT")
            connection.close()

    return _wall_ms(write, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--matches", type=int, default=6_000_000)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"{os.cpu_count()} CPUs, torch {torch.__version__}, {args.threads} torch "
        f"thread(s), median of {args.repeats}\n"
    )
    print("| step | ms | |\n|---|---|---|")
    ms, ns = data_pass(args.matches, args.repeats)
    print(f"| 1. depth data pass, {args.matches:,} matches | {ms:.1f} | {ns:.1f} ns a match |")
    fused, flattened, matches = streams_table(args.repeats)
    print(
        f"| 2. working-set streams, {matches:,} matches: chunk_streams | {fused:.0f} | "
        f"{flattened / fused:.2f}x faster |"
    )
    print(f"| 2. ... match_streams(build_problem(...)) | {flattened:.0f} | |")
    one, two = segmentation(1, args.repeats), segmentation(2, args.repeats)
    print(f"| 3. SLIC labels of 6 keyframes, 2 threads | {two:.0f} | {one / two:.2f}x faster |")
    print(f"| 3. ... 1 thread | {one:.0f} | |")
    default, store = store_pages(4096, args.repeats), store_pages(PAGE_SIZE, args.repeats)
    print(
        f"| 4. 15 store transactions, {PAGE_SIZE // 1024} KiB pages | {store:.0f} | "
        f"{default / store:.2f}x faster |"
    )
    print(f"| 4. ... 4 KiB pages (SQLite's default) | {default:.0f} | |")


if __name__ == "__main__":
    main()
