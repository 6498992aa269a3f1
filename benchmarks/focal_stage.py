"""The end-of-run focal stage (issue 41: the joint pose and focal BA) on stored sessions.

For each run folder given (a self-calibrated centralized run's output with its
``session.db``, e.g. ``benchmarks/team_scale.py``'s ``run_a4_s0``) the session is read, every
agent's focal length moved by ``--perturb`` times -1, -1/2, 0, 1/2 or 1 (by agent id) so that
the solve has work, and the focal stage run as the coordinator's cleanup runs it
(:func:`~como3r.backend.focal_solver.optimize_focal`: ``global_ba.max_iters_stream``
iterations, the prior ``gauge.focal_prior`` on the agents' own focal lengths), on a fresh
copy per path: ``compiled`` (the CPU loop of ``optim/focal_kernels.py``) and ``pytorch``
(the path of every other device). Per run and path: agents, keyframes, directed edges,
matches, iterations, CPU seconds (one thread) of building the edges' dense factors (once per
solve), of the linearizations and of the solves (``A + 1`` pose solves of the Schur
complement) per iteration, the stage's total, and the largest change of a focal length
(relative) and of a keyframe position (scene units) against the first path.

    python benchmarks/focal_stage.py /tmp/team_scale/run_a4_s0 /tmp/team_scale/run_a16_s0

Measured on the stores of ``benchmarks/team_scale.py --sizes 4 16`` (160x120, long side 512,
seed 0; made before 8fbf070), ``--perturb 0.03``, one thread on 2 shared cores under a load
of 13 falling to 6 (commit 8fbf070):

    run         path      agents  kf  edges  matches  it  build s  lin s/it  solve s/it  total s
    run_a4_s0   compiled       4  20     80    7.4 M   4    0.475     0.199     0.00481     1.42
    run_a4_s0   pytorch        4  20     80    7.4 M   4    0.432      3.42      0.0106     14.3
    run_a16_s0  compiled      16  42    156     17 M   4     1.04     0.426       0.022     3.06
    run_a16_s0  pytorch       16  42    156     17 M   4    0.951      7.51      0.0265     31.3

The paths agree within 2e-6 (4 agents) and 3.9e-5 (16) in focal length and 0.013 and 0.25 mm
in keyframe position (the PyTorch path computes in the pointmaps' float32, the loop in
float64). Before 8fbf070 each iteration built the factors again and added PyTorch focal rows
to the compiled pose loop: on the same stores, back to back with the compiled path at a load
of 4-6, the stage took 9.4 s (4 agents) and 19.8 s (16) of CPU against 1.9 and 3.5 s.
"""

from __future__ import annotations

import argparse
import functools
import math
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from _tables import print_table
from rich.console import Console

import como3r.backend.focal_solver as focal_solver
from como3r.backend.focal_factors import FocalEdgeFactors
from como3r.optim.focal_kernels import focal_blocks
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME

COLUMNS = [
    "run",
    "path",
    "agents",
    "kf",
    "edges",
    "matches",
    "it",
    "build s",
    "lin s/it",
    "solve s/it",
    "total s",
    "focal diff",
    "position diff",
]


class _Clock:
    """CPU seconds spent in wrapped functions, by name."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def wrap(self, name: str, function: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(function)
        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.process_time() - start

        return timed


def _warm_up() -> None:
    """Load (or compile) the loop before anything is timed."""
    T = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]], dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    X = torch.ones(1, 1, 3)
    focal_blocks(
        T, torch.eye(3)[None], one, one, X, X[..., :2], X[..., 0], X[..., 0], X[..., 0] > 0,
        (1.0, 1.0, 1.0), 1.0,
    )  # fmt: skip


def stage(run: Path, path: str, perturb: float) -> tuple[dict, list[float], torch.Tensor]:
    """One focal stage on a fresh copy of ``run``'s session: the table row, the agents'
    focal lengths after it and the keyframe poses ``(K, 8)``."""
    session = read_session(run / STORE_NAME)
    graph, config = session.graph, session.config
    agents = sorted(graph.local_to_global)
    for agent in agents:
        graph.rescale_focal(agent, perturb * ((agent * 7) % 5 - 2) / 2)
    clock, sizes = _Clock(), []

    class Counted(FocalEdgeFactors):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, compiled=path == "compiled", **kwargs)
            factors = [b.factors for b in self.batches]
            sizes.append(
                (sum(f.num_edges for f in factors), sum(int(f.valid.sum()) for f in factors))
            )

    Counted.__init__ = clock.wrap("build", Counted.__init__)  # type: ignore[method-assign]
    Counted.linearize = clock.wrap("linearize", Counted.linearize)  # type: ignore[method-assign]
    saved = (focal_solver.FocalEdgeFactors, focal_solver.solve_focal_step)
    focal_solver.FocalEdgeFactors = Counted  # type: ignore[misc]
    focal_solver.solve_focal_step = clock.wrap("solve", focal_solver.solve_focal_step)
    try:
        start = time.process_time()
        result = focal_solver.optimize_focal(
            graph,
            agents,
            graph.global_index(agents[0], 0),
            config.global_ba.max_iters_stream,
            config.gauge.focal_prior,
            graph.own_focal,
        )
        total = time.process_time() - start
    finally:
        focal_solver.FocalEdgeFactors, focal_solver.solve_focal_step = saved
    iterations = max(1, result.iterations)
    edges, matches = sizes[0] if sizes else (0, 0)
    row = {
        "run": run.name,
        "path": path,
        "agents": len(agents),
        "kf": len(graph),
        "edges": edges,
        "matches": f"{matches / 1e6:.2g} M",
        "it": result.iterations,
        "build s": clock.seconds.get("build", 0.0),
        "lin s/it": clock.seconds.get("linearize", 0.0) / iterations,
        "solve s/it": clock.seconds.get("solve", 0.0) / iterations,
        "total s": total,
    }
    focals = [graph.agent_focal(a) or math.nan for a in agents]
    return row, focals, graph.poses(range(len(graph))).double()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders with a session.db")
    parser.add_argument("--perturb", type=float, default=0.03, help="log focal moved at most")
    parser.add_argument("--paths", nargs="+", default=["compiled", "pytorch"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    _warm_up()
    console = Console(width=200)
    console.print(
        f"# {platform.processor() or platform.machine()}; one thread; --perturb {args.perturb}"
    )
    rows = []
    for run in args.runs:
        first: tuple[list[float], torch.Tensor] | None = None
        for path in args.paths:
            row, focals, poses = stage(run, path, args.perturb)
            if first is None:
                first = (focals, poses)
            row["focal diff"] = max(abs(a / b - 1) for a, b in zip(focals, first[0]))
            row["position diff"] = float((poses[:, :3] - first[1][:, :3]).norm(dim=-1).max())
            rows.append(row)
    print_table(console, rows, COLUMNS, "focal stage", left=["run", "path"])


if __name__ == "__main__":
    main()
