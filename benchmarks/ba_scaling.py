"""How one Gauss-Newton iteration of the keyframe-graph solve scales with the graph size.

Synthetic chain + loop keyframe graphs (edges (k, k+1), (k, k+2) and one loop closure every
``--loop-every`` = 4 keyframes to a random earlier one: 2.25 edges per keyframe) with
P = 256 correspondences per edge, keyframe 0 pinned. For N keyframes it times, per GN
iteration of ``como3r.optim`` (the first one, at the noisy initial poses):

* linearize: residuals, Huber-IRLS weights, Jacobians and the scatter-add assembly of the
  block system (shared by all backends);
* solve (dense): dense Hessian of the free poses + Cholesky with Tikhonov eps_0;
* solve (sparse): CSC from block triplets + SuperLU in symmetric mode;
* solve (pcg): block-Jacobi preconditioned conjugate gradients on the blocks, at the
  default tolerance (``como3r.optim.pcg``); the table gives its CG iterations and the
  relative difference of its step from the sparse one.

It prints a table, the log-log slopes of time against N, and the dense/sparse crossover
measured on a sweep of small graphs (the value behind ``linear.DENSE_MAX_FREE_POSES``).
Dense solves beyond ``--dense-max`` keyframes are skipped (a 7N x 7N float64 matrix is
1.5 GB at N = 2000 and its Cholesky takes tens of seconds on one core). A larger
``--loop-every`` makes the graph nearly a chain: SuperLU's fill vanishes and pcg's
iteration count grows with N (see ``como3r.optim.pcg``).

    python benchmarks/ba_scaling.py [--sizes 100 500 2000] [--threads 1] [--loop-every 4]
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time

import torch

from como3r.geometry.lie import sim3_compose
from como3r.optim.factors import RayRangeFactors
from como3r.optim.linear import assemble, solve
from como3r.optim.synthetic import chain_loop_edges, chain_poses, random_sim3, synthetic_graph
from como3r.optim.values import PoseValues

POINTS_PER_EDGE = 256
LOOP_EVERY = 4


def build_problem(
    num_poses: int, seed: int = 0, loop_every: int = LOOP_EVERY
) -> tuple[RayRangeFactors, PoseValues]:
    """A float32 factor batch (as the system stores pointmaps) and noisy initial poses."""
    generator = torch.Generator().manual_seed(seed)
    truth = chain_poses(num_poses, generator)
    i, j = chain_loop_edges(num_poses, loop_every, generator)
    graph = synthetic_graph(truth, i, j, POINTS_PER_EDGE, generator)
    initial = sim3_compose(random_sim3(num_poses, 2.0, 0.2, 0.03, generator), truth)
    initial[0] = truth[0]
    factors = RayRangeFactors(graph.i, graph.j, graph.X_i.float(), graph.X_j.float(),
                              graph.q.float(), graph.valid)
    return factors, PoseValues.from_poses(initial.float(), num_pinned=1)


def best_time(function, repeats: int) -> float:
    """Minimum wall-clock time of ``repeats`` calls (the least disturbed by other load)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def time_iteration(
    num_poses: int, backends: list[str], repeats: int, loop_every: int = LOOP_EVERY
) -> dict[str, float]:
    """Best times of linearize and of each backend's solve, the number of edges, and for
    pcg its CG iterations and its step's relative difference from the sparse step."""
    factors, values = build_problem(num_poses, loop_every=loop_every)
    timings = {
        "edges": float(factors.num_edges),
        "linearize": best_time(
            lambda: assemble(num_poses, [factors.linearize(values.poses)]), repeats
        ),
    }
    system = assemble(num_poses, [factors.linearize(values.poses)])
    steps = {}
    for backend in backends:
        timings[backend] = best_time(
            lambda b=backend: solve(system, values.free, backend=b), repeats
        )
        solution = solve(system, values.free, backend=backend)
        steps[backend] = solution.step
        if backend == "pcg":
            timings["cg_iterations"] = float(solution.cg_iterations)
    if "dense" in steps and "sparse" in steps:
        timings["max_step_diff"] = float((steps["dense"] - steps["sparse"]).abs().max())
    if "pcg" in steps and "sparse" in steps:
        timings["pcg_step_diff"] = float((steps["pcg"] - steps["sparse"]).norm()
                                         / steps["sparse"].norm())
    return timings


def slope(sizes: list[int], times: list[float]) -> float:
    """Least-squares slope of log(time) against log(N)."""
    x = [math.log(n) for n in sizes]
    y = [math.log(t) for t in times]
    mx, my = statistics.fmean(x), statistics.fmean(y)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / sum((a - mx) ** 2 for a in x)


def crossover(sweep: list[int], repeats: int) -> tuple[list[tuple[int, float, float]], float]:
    """Solve times of both backends on small graphs and the N where they cross (log-interp)."""
    rows = []
    for n in sweep:
        t = time_iteration(n, ["dense", "sparse"], repeats)
        rows.append((n, t["dense"], t["sparse"]))
    for (n0, d0, s0), (n1, d1, s1) in zip(rows, rows[1:]):
        r0, r1 = math.log(d0 / s0), math.log(d1 / s1)
        if r0 <= 0 < r1:
            return rows, math.exp(math.log(n0) + (math.log(n1) - math.log(n0)) * -r0 / (r1 - r0))
    return rows, float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 500, 2000])
    parser.add_argument("--sweep", type=int, nargs="+",
                        default=[10, 20, 30, 40, 60, 80, 120, 160, 240])
    parser.add_argument("--dense-max", type=int, default=1000,
                        help="largest N for which the dense backend is timed")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--loop-every", type=int, default=LOOP_EVERY,
                        help="one loop edge every this many keyframes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{args.threads} thread(s); P = {POINTS_PER_EDGE} matches per edge, float32 factors, "
          f"float64 solves; best of {args.repeats}; a loop edge every {args.loop_every} keyframes")
    print()
    header = (f"{'N':>6} {'edges':>6} {'linearize s':>12} {'dense solve s':>14} "
              f"{'sparse solve s':>15} {'GN iter dense s':>16} {'GN iter sparse s':>17} "
              f"{'pcg solve s':>12} {'GN iter pcg s':>14} {'CG iters':>9} {'pcg/sparse':>11} "
              f"{'|pcg-sparse|/|sparse|':>22}")
    print(header)
    print("-" * len(header))
    results = {}
    for n in args.sizes:
        backends = ["sparse", "pcg"] + (["dense"] if n <= args.dense_max else [])
        t = time_iteration(n, backends, args.repeats, args.loop_every)
        results[n] = t
        dense = f"{t['dense']:14.4f}" if "dense" in t else f"{'skipped':>14}"
        dense_total = (f"{t['linearize'] + t['dense']:16.4f}" if "dense" in t
                       else f"{'skipped':>16}")
        print(f"{n:6d} {int(t['edges']):6d} {t['linearize']:12.4f} {dense} "
              f"{t['sparse']:15.4f} {dense_total} {t['linearize'] + t['sparse']:17.4f} "
              f"{t['pcg']:12.4f} {t['linearize'] + t['pcg']:14.4f} "
              f"{int(t['cg_iterations']):9d} {t['pcg'] / t['sparse']:11.2f} "
              f"{t['pcg_step_diff']:22.1e}")
    skipped = [n for n in args.sizes if n > args.dense_max]
    if skipped and any(n <= args.dense_max for n in args.sizes):
        largest = max(n for n in args.sizes if n <= args.dense_max)
        estimate = results[largest]["dense"] * (max(skipped) / largest) ** 3
        print(f"dense skipped for N = {skipped}: a (7N)^2 float64 matrix is "
              f"{8 * (7 * max(skipped)) ** 2 / 1e9:.1f} GB (x3 while factorising) and the "
              f"O(N^3) Cholesky would take ~{estimate:.0f} s (extrapolated from N = {largest})")
    diffs = [t["max_step_diff"] for t in results.values() if "max_step_diff" in t]
    if diffs:
        print(f"max |dense step - sparse step| = {max(diffs):.2e}")
    print()
    sizes = list(results)
    for key, label in (("linearize", "linearize"), ("sparse", "sparse solve"),
                       ("pcg", "pcg solve"), ("cg_iterations", "CG iteration count")):
        fitted = slope(sizes, [results[n][key] for n in sizes])
        print(f"log-log slope of {label} {'' if key == 'cg_iterations' else 'time '}vs N: "
              f"{fitted:.2f}")
    for backend in ("sparse", "pcg"):
        total = [results[n]["linearize"] + results[n][backend] for n in sizes]
        print(f"log-log slope of a {backend} GN iteration vs N: {slope(sizes, total):.2f}")
    dense_sizes = [n for n in sizes if "dense" in results[n]]
    if len(dense_sizes) >= 2:
        dense_times = [results[n]["dense"] for n in dense_sizes]
        print(f"log-log slope of dense solve time vs N: {slope(dense_sizes, dense_times):.2f}")
    print()
    rows, n_cross = crossover(args.sweep, args.repeats)
    print(f"{'N':>6} {'dense solve s':>14} {'sparse solve s':>15} {'dense/sparse':>13}")
    for n, d, s in rows:
        print(f"{n:6d} {d:14.5f} {s:15.5f} {d / s:13.2f}")
    print(f"dense/sparse crossover: N = {n_cross:.0f} keyframes ({7 * n_cross:.0f} unknowns)")


if __name__ == "__main__":
    main()
