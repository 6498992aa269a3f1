"""How long a como3r process takes to exit once its work is done, with and without the
garbage collector frozen at exit (``atexit.register(gc.freeze)`` in ``como3r.cli.main`` and
the agent and robot processes' entry points).

Each run is a fresh interpreter that imports what a command or an agent process imports
(torch, ``como3r.cli``, ``como3r.runtime.agent_worker``), registers the variant's exit
hook, and, in its last exit hook, prints the monotonic clock and its own CPU time. The
parent takes the clock again when the process has ended and its CPU from ``getrusage``:
the differences are the interpreter's own finalization (its collections over every object
still alive, then the modules' teardown), which the frozen variant shortens.

    python benchmarks/exit_time.py [--runs 5]

Measured (session 34, ``--runs 5``; 2 cores, AMD EPYC, load 1.5): collected at exit 803 ms
of wall time (588-1148) and 660 ms of CPU, medians; frozen 178 ms (121-343) and 143 ms. A
process that has worked holds more objects: in a networked team run's processes the exit
took 1.0-1.4 s of CPU collected and 0.15-0.2 s frozen.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _tables import print_table  # noqa: E402

#: the child's program: ``{freeze}`` is the variant's exit hook (or nothing)
CHILD = """
import atexit, gc, json, os, sys, time
def last():
    print(json.dumps([time.monotonic(), time.process_time()]), flush=True)
atexit.register(last)  # registered first: run last of the exit hooks
import torch, como3r.cli, como3r.runtime.agent_worker
{freeze}
"""
VARIANTS = {"collected at exit": "", "frozen at exit": "atexit.register(gc.freeze)"}


def exit_seconds(freeze: str) -> tuple[float, float]:
    """One child's ``(wall, CPU)`` seconds from its last exit hook to its end."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    child = subprocess.run(
        [sys.executable, "-c", CHILD.format(freeze=freeze)],
        stdout=subprocess.PIPE,
        text=True,
        check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    ended = time.monotonic()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    last_clock, last_cpu = json.loads(child.stdout.strip().splitlines()[-1])
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return ended - last_clock, cpu - last_cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="processes per variant")
    args = parser.parse_args()
    measured: dict[str, list[tuple[float, float]]] = {name: [] for name in VARIANTS}
    for _ in range(args.runs):  # alternating, so a change of load touches both alike
        for name, freeze in VARIANTS.items():
            measured[name].append(exit_seconds(freeze))
    rows = [
        {
            "variant": name,
            "runs": len(runs),
            "exit wall ms (median)": 1e3 * statistics.median(w for w, _ in runs),
            "exit CPU ms (median)": 1e3 * statistics.median(c for _, c in runs),
            "exit wall ms (range)": f"{1e3 * min(w for w, _ in runs):.0f}-"
            f"{1e3 * max(w for w, _ in runs):.0f}",
        }
        for name, runs in measured.items()
    ]
    console = Console(width=160)
    console.print(f"# {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    print_table(console, rows, list(rows[0]), "a como3r process's exit")


if __name__ == "__main__":
    main()
