"""The coordinator's SLAM work per keyframe vs the prior's decode, in one process (not a test).

Runs ``como3r run --single-process`` (the pipeline of :mod:`como3r.runtime.pipeline`, default
configuration, simulated prior) on a synthetic multi-agent scene (``como3r synth``) and
prints the coordinator's ``stage_seconds`` from ``metrics.json`` (retrieval, verification,
gauge, focal, global BA, the terminal cleanup and refinement, the session store's writes;
the prior's decodes apart) per keyframe, over one full-size MASt3R decode at the run's
resolution (``slam_vs_prior.mast3r_decode_seconds``), and over the decodes the keyframes
caused (``prior_decodes``: the ordered pairs verification had decoded).
Agents and coordinator take turns in one process, so with one thread on an idle machine the
coordinator's wall seconds are its CPU seconds; the dashboard (``report.py``) measures the
same stages in multi-process runs, where they share the cores with the agents.

Two checkouts compare like for like by running this file of either on the same scene
(``PYTHONPATH=<checkout>/src``).

    como3r synth --out /tmp/s4 --agents 4 --frames 16 --loop-frames 100 --width 640 \\
        --height 480 --overlap 0.5   # the dashboard's 4-agent scene (report.py makes it too)
    OMP_NUM_THREADS=1 python benchmarks/coordinator_stages.py --scene /tmp/s4 \\
        --out /tmp/coordinator_run
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))

import slam_vs_prior  # noqa: E402

from como3r.config import Config  # noqa: E402
from como3r.data.preprocess import compute_transform  # noqa: E402
from como3r.prior.mast3r.precision import PRECISIONS  # noqa: E402
from como3r.runtime.pipeline import PriorSpec, run  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True, help="folder of agent_* inputs")
    parser.add_argument("--out", type=Path, required=True, help="output folder (replaced)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--decode-ms",
        type=float,
        default=None,
        help="skip the MASt3R timing and use this decode time",
    )
    parser.add_argument("--precision", default="auto", choices=PRECISIONS)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    agents = sorted(args.scene.glob("agent_*"), key=lambda p: int(p.name.split("_")[1]))
    if not agents:
        parser.error(f"no agent_* folders in {args.scene}")
    start = time.process_time()
    summary = run(agents, args.out, Config(), PriorSpec("simulated"), overwrite=True)
    process_seconds = time.process_time() - start
    metrics = json.loads((Path(summary.out) / "metrics.json").read_text())
    coordinator = metrics["coordinator"]
    keyframes = max(1, coordinator["keyframes"])
    stages = {
        stage: seconds
        for stage, seconds in coordinator["stage_seconds"].items()
        if not stage.startswith("prior_")
    }
    if args.decode_ms is None:
        with Image.open(next((agents[0] / "rgb").iterdir())) as image:
            width, height = compute_transform(*image.size, Config().input.long_side).output
        decode_ms = 1000.0 * slam_vs_prior.mast3r_decode_seconds(width, height, args.precision)
    else:
        decode_ms = args.decode_ms
    decodes = coordinator["prior_decodes"] / keyframes
    print(
        f"{len(agents)} agents, {keyframes} keyframes, run {process_seconds:.1f} s CPU; "
        f"one decode {decode_ms:.0f} ms; {decodes:.2f} decodes per keyframe "
        "(verification's ordered pairs)\n"
    )
    print("| stage | s | ms per keyframe | / one decode | / its decodes |\n|---|---|---|---|---|")
    for stage, seconds in [*sorted(stages.items()), ("total", sum(stages.values()))]:
        ms = 1000.0 * seconds / keyframes
        caused = f"{ms / (decodes * decode_ms):.3f}" if decodes else "-"
        print(f"| {stage} | {seconds:.2f} | {ms:.0f} | {ms / decode_ms:.3f} | {caused} |")


if __name__ == "__main__":
    main()
