"""Time of one global Sim(3) BA solve (``GlobalGraph.optimize``) on a synthetic two-agent graph.

Two agents' keyframe chains of ``--keyframes`` keyframes each at ``--width x --height``,
sequential links plus an inter-agent link every fourth keyframe; every link matches a random
share (30-100 %) of its pixels, as real links do, so edges differ in size. Poses start
perturbed; the solve runs a fixed ``--iters`` Gauss-Newton iterations (the step tolerance is
set to 0) in float64 poses, like the coordinator's cleanup passes. It prints the seconds per
iteration (best of ``--repeats``). Run it against two checkouts to compare them:

    PYTHONPATH=src python benchmarks/global_ba_speed.py [--keyframes 8] [--iters 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch

from como3r.backend.global_graph import GlobalGraph
from como3r.config import GlobalBAConfig, TrackingConfig
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.geometry.lie import sim3_act, sim3_compose, sim3_exp, sim3_inverse
from como3r.prior.base import Encoding


def _matches(pixels: int, gen: torch.Generator) -> DirectedMatches:
    share = 0.3 + 0.7 * float(torch.rand(1, generator=gen))
    return DirectedMatches(
        idx=torch.arange(pixels),
        valid=torch.rand(pixels, generator=gen) < share,
        q=1.5 + torch.rand(pixels, generator=gen) * 10,
    )


def build_graph(keyframes: int, height: int, width: int) -> GlobalGraph:
    gen = torch.Generator().manual_seed(0)
    world = torch.randn(height * width, 3, generator=gen) * torch.tensor([4.0, 2.0, 1.0])
    world[:, 2] += 10.0
    graph = GlobalGraph(TrackingConfig(), dataclasses.replace(GlobalBAConfig(), step_tol=0.0))
    for kf_id in range(keyframes):
        for agent in (0, 1):
            T = sim3_exp(torch.tensor([0.2 * kf_id, 0.3 * agent, 0.0, 0.0, 0.01 * kf_id, 0.0, 0.0]))
            noisy = (
                T
                if (agent, kf_id) == (0, 0)
                else sim3_compose(sim3_exp(torch.randn(7, generator=gen) * 0.01), T)
            )
            X = sim3_act(sim3_inverse(T)[None], world).reshape(height, width, 3)
            link = (
                None
                if kf_id == 0
                else PairLink(_matches(height * width, gen), _matches(height * width, gen))
            )
            graph.add_keyframe(
                KeyframePacket(
                    agent=agent,
                    kf_id=kf_id,
                    frame_index=kf_id,
                    timestamp=float(kf_id),
                    T_WC=noisy,
                    X_hat=X,
                    C_hat=torch.full((height, width), 5.0),
                    colors=np.zeros((height, width, 3), np.uint8),
                    encoding=Encoding(agent, kf_id, (height, width)),
                    retrieval=None,
                    sequential_ij=None if link is None else link.ij,
                    sequential_ji=None if link is None else link.ji,
                    previous=None,
                )
            )
        if kf_id % 4 == 0:
            link = PairLink(_matches(height * width, gen), _matches(height * width, gen))
            graph.add_inter_link(
                graph.global_index(0, kf_id), graph.global_index(1, kf_id), link, 0.1
            )
    return graph


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=112)
    parser.add_argument("--iters", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    times = []
    for _ in range(args.repeats):
        graph = build_graph(args.keyframes, args.height, args.width)
        start = time.perf_counter()
        result = graph.optimize([0, 1], anchor=0, max_iters=args.iters)
        times.append((time.perf_counter() - start) / max(1, result.iterations))
    print(
        f"{platform.machine()}, torch {torch.__version__}, {args.threads} thread(s); "
        f"{2 * args.keyframes} keyframes at {args.width}x{args.height}, "
        f"{len(graph.links)} links, {result.iterations} iterations"
    )
    print(f"{'seconds per GN iteration (best of ' + str(args.repeats) + ')':<44}{min(times):.4f}")


if __name__ == "__main__":
    main()
