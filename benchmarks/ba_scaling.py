"""How one Gauss-Newton iteration of the keyframe-graph solve scales with the graph size.

Synthetic chain + loop keyframe graphs (edges (k, k+1), (k, k+2) and one loop closure every
``--loop-every`` keyframes to a random earlier one: 2 + 1/loop_every edges per keyframe)
with P = 256 correspondences per edge, keyframe 0 pinned, in two families by default: a
loop edge every 4 keyframes (many loop closures) and every 50 (nearly a chain). For N
keyframes it times, per GN iteration of ``como3r.optim`` (the first one, at the noisy
initial poses):

* linearize: residuals, Huber-IRLS weights, Jacobians and the scatter-add assembly of the
  block system (shared by all backends);
* solve (dense): dense Hessian of the free poses + Cholesky with Tikhonov eps_0;
* solve (sparse): CSC from block triplets + SuperLU in symmetric mode;
* solve (pcg): block-Jacobi preconditioned conjugate gradients on the blocks
  (``como3r.optim.pcg``);
* solve (band): conjugate gradients with the band + coarse two-level preconditioner
  (``como3r.optim.band``);
* the DEFAULT, ``backend="auto"``: which backend it takes at that size (dense up to
  ``linear.DENSE_MAX_FREE_POSES`` free poses, band above: ``linear.auto_backend``) and
  that backend's time.

Both CG backends run at the default tolerance; a second table gives their CG iterations and
the relative difference of their steps from the sparse one. It prints the log-log slopes
of time against N (the default's GN iteration is issue 16's "global BA cost per iteration"
figure) and the crossover between the dense Cholesky and what "auto" takes above
``linear.DENSE_MAX_FREE_POSES``, on a sweep of small graphs with a loop edge every 4. Dense
solves beyond ``--dense-max`` keyframes are skipped (a 7N x 7N float64 matrix is 1.5 GB at
N = 2000 and its Cholesky takes tens of seconds on one core).

    python benchmarks/ba_scaling.py [--sizes 100 500 2000] [--threads 1] [--loop-every 4 50]

Two runs of the defaults on a 2-core x86-64 CPU shared with two other jobs: the default's
GN iteration has a log-log slope of 0.99-1.06 with a loop edge every 4 keyframes (sparse:
1.33-1.46, its solve alone 1.70-1.79) and 0.95-0.97 with one every 50; band / sparse solve
time at N = 2000 is 0.24-0.25 and 0.92-1.62 (table in ``como3r.optim.band``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import platform
import statistics
import time

import torch

from como3r.geometry.lie import sim3_compose
from como3r.optim.linear import DENSE_MAX_FREE_POSES, auto_backend, solve
from como3r.optim.match_factors import RayRangeFactors
from como3r.optim.synthetic import chain_loop_edges, chain_poses, random_sim3, synthetic_graph
from como3r.optim.system import assemble
from como3r.optim.values import PoseValues

POINTS_PER_EDGE = 256
LOOP_EVERY = 4
CG_BACKENDS = ("pcg", "band")


def build_problem(
    num_poses: int, seed: int = 0, loop_every: int = LOOP_EVERY, device: str = "cpu"
) -> tuple[RayRangeFactors, PoseValues]:
    """A float32 factor batch (as the system stores pointmaps) and noisy initial poses, on
    ``device`` (the same problem on every device: drawn on the CPU, then moved)."""
    generator = torch.Generator().manual_seed(seed)
    truth = chain_poses(num_poses, generator)
    i, j = chain_loop_edges(num_poses, loop_every, generator)
    graph = synthetic_graph(truth, i, j, POINTS_PER_EDGE, generator)
    initial = sim3_compose(random_sim3(num_poses, 2.0, 0.2, 0.03, generator), truth)
    initial[0] = truth[0]
    factors = RayRangeFactors(
        *(t.to(device) for t in (graph.i, graph.j)),
        *(t.float().to(device) for t in (graph.X_i, graph.X_j, graph.q)),
        graph.valid.to(device),
    )
    return factors, PoseValues.from_poses(initial.float().to(device), num_pinned=1)


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
) -> dict[str, float | str]:
    """Best times of linearize and of each backend's solve, the number of edges, the
    backend ``"auto"`` picks, and for the CG backends their CG iterations and their step's
    relative difference from the sparse step."""
    factors, values = build_problem(num_poses, loop_every=loop_every)
    timings: dict[str, float | str] = {
        "edges": float(factors.num_edges),
        "linearize": best_time(
            lambda: assemble(num_poses, [factors.linearize(values.poses)]), repeats
        ),
    }
    system = assemble(num_poses, [factors.linearize(values.poses)])
    timings["auto"] = solve(system, values.free).backend
    steps = {}
    for backend in backends:
        timings[backend] = best_time(
            lambda b=backend: solve(system, values.free, backend=b), repeats
        )
        solution = solve(system, values.free, backend=backend)
        steps[backend] = solution.step
        if backend in CG_BACKENDS:
            timings[f"{backend}_iterations"] = float(solution.cg_iterations)
    if "dense" in steps and "sparse" in steps:
        timings["max_step_diff"] = float((steps["dense"] - steps["sparse"]).abs().max())
    for backend in CG_BACKENDS:
        if backend in steps and "sparse" in steps:
            timings[f"{backend}_step_diff"] = float(
                (steps[backend] - steps["sparse"]).norm() / steps["sparse"].norm()
            )
    return timings


def slope(sizes: list[int], times: list[float]) -> float:
    """Least-squares slope of log(time) against log(N)."""
    x = [math.log(n) for n in sizes]
    y = [math.log(t) for t in times]
    mx, my = statistics.fmean(x), statistics.fmean(y)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / sum((a - mx) ** 2 for a in x)


def crossover(
    sweep: list[int], repeats: int, large: str
) -> tuple[list[tuple[int, float, float]], float]:
    """Solve times of the dense backend and of ``large`` (what "auto" takes above
    ``DENSE_MAX_FREE_POSES``) on small graphs and the N where they cross (log-interp)."""
    rows = []
    for n in sweep:
        t = time_iteration(n, ["dense", large], repeats)
        rows.append((n, t["dense"], t[large]))
    for (n0, d0, s0), (n1, d1, s1) in itertools.pairwise(rows):
        r0, r1 = math.log(d0 / s0), math.log(d1 / s1)
        if r0 <= 0 < r1:
            return rows, math.exp(math.log(n0) + (math.log(n1) - math.log(n0)) * -r0 / (r1 - r0))
    return rows, float("nan")


def family(args: argparse.Namespace, loop_every: int) -> dict[int, dict[str, float | str]]:
    """Time every size of one graph family (a loop edge every ``loop_every`` keyframes),
    print its tables and slopes, and return the timings by N."""
    print(f"--- a loop edge every {loop_every} keyframes ---")
    header = (
        f"{'N':>6} {'edges':>6} {'linearize s':>12} {'dense s':>9} {'sparse s':>9} "
        f"{'pcg s':>8} {'band s':>8} {'auto':>6} {'GN iter auto s':>15} "
        f"{'GN iter sparse s':>17} {'band/sparse':>12} {'pcg/sparse':>11}"
    )
    print(header)
    print("-" * len(header))
    results = {}
    for n in args.sizes:
        backends = ["sparse", "pcg", "band"] + (["dense"] if n <= args.dense_max else [])
        t = time_iteration(n, backends, args.repeats, loop_every)
        results[n] = t
        dense = f"{t['dense']:9.4f}" if "dense" in t else f"{'skipped':>9}"
        print(
            f"{n:6d} {int(t['edges']):6d} {t['linearize']:12.4f} {dense} {t['sparse']:9.4f} "
            f"{t['pcg']:8.4f} {t['band']:8.4f} {t['auto']:>6} "
            f"{t['linearize'] + t[t['auto']]:15.4f} {t['linearize'] + t['sparse']:17.4f} "
            f"{t['band'] / t['sparse']:12.2f} {t['pcg'] / t['sparse']:11.2f}"
        )
    print()
    print(
        f"{'N':>6} {'pcg CG iters':>13} {'|pcg-sparse|/|sparse|':>22} {'band CG iters':>14} "
        f"{'|band-sparse|/|sparse|':>23}"
    )
    for n, t in results.items():
        print(
            f"{n:6d} {int(t['pcg_iterations']):13d} {t['pcg_step_diff']:22.1e} "
            f"{int(t['band_iterations']):14d} {t['band_step_diff']:23.1e}"
        )
    skipped = [n for n in args.sizes if n > args.dense_max]
    if skipped and any(n <= args.dense_max for n in args.sizes):
        largest = max(n for n in args.sizes if n <= args.dense_max)
        estimate = results[largest]["dense"] * (max(skipped) / largest) ** 3
        print(
            f"dense skipped for N = {skipped}: a (7N)^2 float64 matrix is "
            f"{8 * (7 * max(skipped)) ** 2 / 1e9:.1f} GB (x3 while factorising) and the "
            f"O(N^3) Cholesky would take ~{estimate:.0f} s (extrapolated from N = {largest})"
        )
    diffs = [t["max_step_diff"] for t in results.values() if "max_step_diff" in t]
    if diffs:
        print(f"max |dense step - sparse step| = {max(diffs):.2e}")
    print()
    sizes = list(results)
    if len(sizes) < 2:
        return results
    for key, label in (
        ("linearize", "linearize time"),
        ("sparse", "sparse solve time"),
        ("pcg", "pcg solve time"),
        ("band", "band solve time"),
        ("pcg_iterations", "pcg CG iteration count"),
        ("band_iterations", "band CG iteration count"),
    ):
        fitted = slope(sizes, [results[n][key] for n in sizes])
        print(f"log-log slope of {label} vs N: {fitted:.2f}")
    for backend in ("sparse", "pcg", "band"):
        total = [results[n]["linearize"] + results[n][backend] for n in sizes]
        print(f"log-log slope of a {backend} GN iteration vs N: {slope(sizes, total):.2f}")
    dense_sizes = [n for n in sizes if "dense" in results[n]]
    if len(dense_sizes) >= 2:
        dense_times = [results[n]["dense"] for n in dense_sizes]
        print(f"log-log slope of dense solve time vs N: {slope(dense_sizes, dense_times):.2f}")
    total = [results[n]["linearize"] + results[n][results[n]["auto"]] for n in sizes]
    picked = sorted({results[n]["auto"] for n in sizes})
    print(
        f'log-log slope of a DEFAULT (backend="auto": {"/".join(picked)}) GN iteration '
        f"vs N: {slope(sizes, total):.2f}"
    )
    print()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 500, 2000])
    parser.add_argument(
        "--sweep",
        type=int,
        nargs="*",
        default=[10, 20, 30, 40, 60, 80, 120, 160, 240],
        help="sizes of the dense/auto crossover sweep (none: skip it)",
    )
    parser.add_argument(
        "--dense-max", type=int, default=1000, help="largest N for which the dense backend is timed"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--loop-every",
        type=int,
        nargs="+",
        default=[LOOP_EVERY, 50],
        help="graph families: one loop edge every this many keyframes",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} thread(s); P = {POINTS_PER_EDGE} matches per edge, float32 factors, "
        f"float64 solves; best of {args.repeats}"
    )
    print()
    for loop_every in args.loop_every:
        family(args, loop_every)
    if len(args.sweep) < 2:
        return
    large = auto_backend(DENSE_MAX_FREE_POSES + 1)
    rows, n_cross = crossover(args.sweep, args.repeats, large)
    print(f"{'N':>6} {'dense solve s':>14} {large + ' solve s':>14} {'dense/' + large:>13}")
    for n, d, s in rows:
        print(f"{n:6d} {d:14.5f} {s:14.5f} {d / s:13.2f}")
    print(
        f"dense/{large} crossover: N = {n_cross:.0f} keyframes ({7 * n_cross:.0f} unknowns; "
        f"auto switches above DENSE_MAX_FREE_POSES = {DENSE_MAX_FREE_POSES} free poses)"
    )


if __name__ == "__main__":
    main()
