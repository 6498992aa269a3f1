"""End-to-end terminal refinement on synthetic scenes: before/after, C-Tab. 5 and C-Tab. 6.

For every seed it synthesizes a multi-agent scene (``como3r synth``: ground-truth depth,
poses and calibration), then runs the whole system (``como3r run --single-process``, the
simulated prior with its low-frequency depth distortion) once per configuration:

* ``poses only``: ``depth.alternation_rounds=0`` (cleanup pose passes, no depth step);
* ``per-pixel``, ``per-pixel + Laplacian``, ``per-segment``: ``depth.variant`` (C-Tab. 5),
  the Laplacian also on log-depth as C-Sec. C.1 defines it (``boundary_residual=log_depth``);
* ``per-segment, C-Eq. 22 as printed``: the boundary residual with ``Delta_ab``;
* ``per-segment, insertion base``: C-Eq. 19 from the insertion-time prediction as the paper
  writes it (``depth.refine_from=insertion``) instead of the fused pointmap;
* ``calibrated ...``: the same with ``--calib`` (C-Tab. 6).

and prints one table row per configuration: merged ATE RMSE, the fused map's accuracy,
completeness, Chamfer distance and F-score against the ground-truth cloud (after the
trajectory's Sim(3) alignment; ``metrics.json`` ``map_accuracy``), the same accuracy before
the depth refinement of that run, the alternation's rounds and stop reason, and its time.
Means over seeds are printed last.

    python benchmarks/map_refinement.py [--seeds 0 1] [--agents 2] [--frames 30]
        [--width 160] [--height 120] [--work /tmp/como3r_map_refinement]

Every run uses the default ``input.long_side`` (the 160x120 scenes are enlarged to it), as
a user's run would.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path
from statistics import mean

import torch

CONFIGURATIONS: list[tuple[str, list[str]]] = [
    ("poses only", ["--set", "depth.alternation_rounds=0"]),
    ("per-pixel", ["--set", "depth.variant=pixel"]),
    ("per-pixel + Laplacian", ["--set", "depth.variant=pixel_laplacian"]),
    (
        "per-pixel + log-depth Lapl.",
        ["--set", "depth.variant=pixel_laplacian", "--set", "depth.boundary_residual=log_depth"],
    ),
    ("per-segment", []),
    ("per-segment, C-Eq. 22 as printed", ["--set", "depth.boundary_residual=log_depth"]),
    ("per-segment, insertion base", ["--set", "depth.refine_from=insertion"]),
    ("calibrated, poses only", ["--calib", "--set", "depth.alternation_rounds=0"]),
    ("calibrated, per-segment", ["--calib"]),
]
COLUMNS = (
    "ATE mm",
    "acc mm",
    "acc before",
    "compl mm",
    "chamfer mm",
    "F@5cm",
    "rounds",
    "stop",
    "alt s",
    "run s",
)


def _como3r(*args: str) -> None:
    subprocess.run(
        [sys.executable, "-m", "como3r.cli", *args], check=True, stdout=subprocess.DEVNULL
    )


def _row(run: Path, seconds: float) -> dict[str, object]:
    metrics = json.loads((run / "metrics.json").read_text())
    maps = metrics["map_accuracy"][0]
    final, before = maps["final"], maps.get("before_refinement")
    alternation = metrics["coordinator"]["alternation"]
    rounds = alternation[0]["rounds"] if alternation else 0
    return {
        "ATE mm": 1e3 * metrics["ate"]["merged"]["ate"]["rmse"],
        "acc mm": 1e3 * final["accuracy"],
        "acc before": 1e3 * before["accuracy"] if before else float("nan"),
        "compl mm": 1e3 * final["completeness"],
        "chamfer mm": 1e3 * final["chamfer"],
        "F@5cm": final["fscore"],
        "rounds": rounds,
        "stop": alternation[0]["reason"] if alternation else "-",
        "alt s": sum(a["seconds"] for a in alternation),
        "run s": seconds,
    }


def _print_table(title: str, rows: dict[str, dict[str, object]]) -> None:
    print(f"\n{title}")
    widths = {c: 16 if c == "stop" else 11 for c in COLUMNS}
    header = f"{'configuration':<34}" + "".join(f"{c:>{widths[c]}}" for c in COLUMNS)
    print(header)
    print("-" * len(header))
    for name, row in rows.items():
        cells = []
        for column in COLUMNS:
            value, width = row[column], widths[column]
            cells.append(
                f"{value:>{width}.4f}"
                if column == "F@5cm"
                else f"{value:>{width}.1f}"
                if isinstance(value, float)
                else f"{value!s:>{width}}"
            )
        print(f"{name:<34}" + "".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--agents", type=int, default=2)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--work", type=Path, default=Path("/tmp/como3r_map_refinement"))
    args = parser.parse_args()
    print(
        f"python {platform.python_version()}, torch {torch.__version__}, "
        f"{platform.processor() or platform.machine()}; scenes: {args.agents} agents x "
        f"{args.frames} frames at {args.width}x{args.height}"
    )
    shutil.rmtree(args.work, ignore_errors=True)
    common = ["--prior", "simulated", "--single-process"]
    by_seed: list[dict[str, dict[str, object]]] = []
    for seed in args.seeds:
        scene = args.work / f"scene_{seed}"
        _como3r(
            "synth",
            "--out",
            str(scene),
            "--agents",
            str(args.agents),
            "--seed",
            str(seed),
            "--frames",
            str(args.frames),
            "--width",
            str(args.width),
            "--height",
            str(args.height),
        )
        agent_args = [a for k in range(args.agents) for a in ("--agent", str(scene / f"agent_{k}"))]
        rows = {}
        for index, (name, extra) in enumerate(CONFIGURATIONS):
            run = args.work / f"run_{seed}_{index}"
            start = time.perf_counter()
            _como3r("run", *agent_args, "--out", str(run), *common, *extra)
            rows[name] = _row(run, time.perf_counter() - start)
        by_seed.append(rows)
        _print_table(f"seed {seed}", rows)
    means = {
        name: {
            c: (
                mean(float(r[name][c]) for r in by_seed)
                if c != "stop"
                else "/".join(sorted({str(r[name][c]) for r in by_seed}))
            )
            for c in COLUMNS
        }
        for name, _ in CONFIGURATIONS
    }
    _print_table(f"mean over seeds {args.seeds}", means)


if __name__ == "__main__":
    main()
