"""The speed dashboard on a CUDA device, beside this machine's CPU (not a test).

``report.py`` measures the system on a CPU; this measures what moves to a GPU, each part on
the device and on the CPU of the same machine (ratios are the claims), as Markdown tables:

1. **MASt3R** (the full released configuration, seeded random weights: the released
   network's cost) at ``--size``: ms per ``encode`` of one image, per ``decode`` of one
   ordered pair, and per pair of a ``decode_symmetric`` batch of ``--batch`` pairs (wall
   time; the CPU's with ``--threads`` threads), for each
   precision on the device (fp32, bf16 where the device computes it natively, fp16) and fp32
   on the CPU (encode and decode only, two repeats); the relative error of each reduced precision's output maps against the
   device's fp32.
2. **SLAM per frame** (:func:`slam_vs_prior.frontend_run`): one agent's front-end on a
   640x480 synthetic scene (long side 512) with the simulated prior, its predictions handed
   over on the device as MASt3R's would be (:class:`slam_vs_prior.OnDevice`), so matching,
   tracking, fusion, keyframe linking and local solves run there: ms per frame and stage on
   the CPU (CPU seconds, one thread, as ``report.py``) and on the device (synchronised wall
   seconds), and the SLAM's share of the decodes the frame caused at the device's auto
   precision.
3. **Keyframe-graph Gauss-Newton** (:func:`ba_scaling.build_problem`'s synthetic graphs):
   seconds of one iteration's linearisation and of the default backend's solve
   (``optim.linear.solve``, ``backend="auto"``) for ``--ba-sizes`` keyframes, on the CPU
   and on the device.

Every timed call follows an untimed one (CUDA's kernels and numba's compiled loops are set
up at their first call); tables 1 and 3 give medians of ``--repeats`` wall times (on the
device after a synchronisation).
Writes ``cuda_speed.md`` into ``--out`` and prints it.

    python benchmarks/cuda_speed.py --out /tmp/cuda_speed [--device cuda] [--frames 8]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import ba_scaling  # noqa: E402
import report as dashboard  # noqa: E402
import slam_vs_prior  # noqa: E402

from como3r.optim.linear import auto_backend, solve  # noqa: E402
from como3r.optim.system import assemble  # noqa: E402
from como3r.prior.base import PairPrediction  # noqa: E402
from como3r.prior.mast3r import MASt3RNetwork, MASt3RPrior, parse_model_string  # noqa: E402
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING  # noqa: E402
from como3r.prior.mast3r.precision import choose_dtype, cuda_supports_bf16  # noqa: E402

DTYPE_NAMES = {torch.float32: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}


def median_ms(run: Callable[[], object], device: torch.device, repeats: int) -> float:
    """Median wall milliseconds of ``repeats`` calls of ``run`` after an untimed one (on
    CUDA after a synchronisation: its work is queued)."""
    cuda = device.type == "cuda"

    def now() -> float:
        if cuda:
            torch.cuda.synchronize(device)
        return time.perf_counter()

    run()
    samples = []
    for _ in range(repeats):
        start = now()
        run()
        samples.append(1000.0 * (now() - start))
    return statistics.median(samples)


def relative_error(value: torch.Tensor, reference: torch.Tensor) -> float:
    """``||value - reference|| / ||reference||`` in float64."""
    reference = reference.double()
    return float((value.double() - reference).norm() / reference.norm())


def mast3r_rows(
    device: torch.device, size: tuple[int, int], batch: int, repeats: int
) -> list[dict[str, str]]:
    """Table 1: encode / decode / batched symmetric decode ms per precision and device."""
    width, height = size
    torch.manual_seed(0)
    network = MASt3RNetwork(parse_model_string(RELEASED_MODEL_STRING))
    images = torch.rand(2, 3, height, width) * 2 - 1
    dtypes = [torch.float32] + ([torch.bfloat16] if cuda_supports_bf16(device) else [])
    runs = [(device, dtype) for dtype in (*dtypes, torch.float16)]
    runs.append((torch.device("cpu"), torch.float32))
    reference = None
    rows = []
    for where, dtype in runs:
        row, prediction = mast3r_row(
            MASt3RPrior(network.to(where), dtype=dtype), images, batch, repeats, reference
        )
        rows.append(row)
        if reference is None:
            reference = prediction
    network.to("cpu")
    return rows


def mast3r_row(
    prior: MASt3RPrior,
    images: torch.Tensor,
    batch: int,
    repeats: int,
    reference: PairPrediction | None,
) -> tuple[dict[str, str], PairPrediction]:
    """One row of table 1 (``images``: ``(2, 3, H, W)``, the pair), and the pair's
    prediction; the error column against ``reference`` (None: this is the reference)."""
    where = prior.device
    on = images.to(where)
    enc_i, enc_j = prior.encode(on)
    pairs = [(enc_i, enc_j)] * batch
    prediction = prior.decode(enc_i, enc_j)
    error = "-"
    if reference is not None and where == reference.X_ii.device:
        error = "{:.1e}".format(
            max(
                relative_error(getattr(prediction, f.name), getattr(reference, f.name))
                for f in fields(reference)
            )
        )
    # the CPU's row: two repeats and no batch (a batch of 8 symmetric decodes of the full
    # network takes tens of seconds there; the GPU's rows are what the batch is about)
    cpu = where.type == "cpu"
    repeats = min(repeats, 2) if cpu else repeats
    symmetric = "-"
    if not cpu:
        ms = median_ms(lambda: prior.decode_symmetric(pairs), where, repeats)
        symmetric = f"{ms / batch:.1f}"
    row = {
        "device": str(where),
        "precision": DTYPE_NAMES[prior.dtype],
        "encode ms": f"{median_ms(lambda: prior.encode(on[:1]), where, repeats):.1f}",
        "decode ms": f"{median_ms(lambda: prior.decode(enc_i, enc_j), where, repeats):.1f}",
        f"symmetric ms/pair (batch {batch})": symmetric,
        "max rel. error vs fp32": error,
    }
    return row, prediction


def slam_rows(
    agent: Path, frames: int, device: torch.device, decode_ms: float
) -> tuple[list[dict[str, str]], list[str]]:
    """Table 2: ms per frame and stage of one agent's SLAM on the CPU and on the device."""
    measured = {}
    counters = {}
    threads = torch.get_num_threads()
    for where in ("cpu", str(device)):
        # one thread on the CPU, as report.py's table 1: its clock reads CPU seconds
        torch.set_num_threads(1 if where == "cpu" else threads)
        clock, counters[where] = slam_vs_prior.frontend_run(agent, frames, [], where)
        n = counters[where]["frames"]
        measured[where] = {
            stage: 1000.0 * clock.seconds.get(stage, 0.0) / n for stage in slam_vs_prior.SLAM_STAGES
        }
    rows = []
    for stage in (*slam_vs_prior.SLAM_STAGES, "SLAM total"):
        cpu, gpu = (
            (sum(measured[w].values()) if stage == "SLAM total" else measured[w][stage])
            for w in ("cpu", str(device))
        )
        rows.append(
            {
                "stage": stage,
                "CPU ms/frame": f"{cpu:.1f}",
                f"{device} ms/frame": f"{gpu:.1f}",
                "CPU / device": f"{cpu / gpu:.2f}" if gpu > 0 else "-",
            }
        )
    on_device = counters[str(device)]
    decodes_per_frame = on_device["decodes"] / on_device["frames"]
    slam_total = sum(measured[str(device)].values())
    notes = [
        f"counters: CPU {counters['cpu']}; device {on_device}",
        f"SLAM on {device} / one MASt3R decode there ({decode_ms:.1f} ms): "
        f"{slam_total / decode_ms:.3f}",
        f"SLAM on {device} / the {decodes_per_frame:.2f} decodes a frame caused there: "
        f"{slam_total / (decodes_per_frame * decode_ms):.3f}",
    ]
    return rows, notes


def ba_rows(sizes: list[int], device: torch.device, repeats: int) -> list[dict[str, str]]:
    """Table 3: one GN iteration's linearisation and default solve on the CPU and device."""
    rows = []
    for n in sizes:
        row: dict[str, str] = {"keyframes": str(n)}
        for where in (torch.device("cpu"), device):
            factors, values = ba_scaling.build_problem(n, device=str(where))
            system = assemble(n, [factors.linearize(values.poses)])
            backend = auto_backend(n - 1)
            linearize = median_ms(
                lambda f=factors, v=values: assemble(n, [f.linearize(v.poses)]), where, repeats
            )
            step = median_ms(lambda s=system, v=values: solve(s, v.free), where, repeats)
            name = "CPU" if where.type == "cpu" else str(device)
            row[f"{name} linearize ms"] = f"{linearize:.1f}"
            row[f"{name} solve ms ({backend})"] = f"{step:.1f}"
        rows.append(row)
    return rows


def table(rows: list[dict[str, str]]) -> list[str]:
    """Markdown lines of ``rows`` (one dict per row, the first row's keys as columns)."""
    columns = list(rows[0])
    return [
        "| " + " | ".join(columns) + " |",
        "|" + "---|" * len(columns),
        *("| " + " | ".join(row[c] for c in columns) + " |" for row in rows),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for scene and report")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--frames", type=int, default=8, help="processed frames (table 2)")
    parser.add_argument("--size", default="512x384", help="W x H of table 1's images")
    parser.add_argument("--batch", type=int, default=8, help="pairs per symmetric decode")
    parser.add_argument("--ba-sizes", type=int, nargs="+", default=[100, 500, 2000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type != "cuda" or not torch.cuda.is_available():
        parser.error(f"--device {args.device}: this benchmark needs a CUDA device torch can use")
    if device.index is None:  # named as the tensors name it ("cuda:0"), rows compare by name
        device = torch.device("cuda", torch.cuda.current_device())
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    width, height = (int(v) for v in args.size.split("x"))
    lines = [
        "# como3r speed on CUDA\n",
        f"{torch.cuda.get_device_name(device)}; CPU {platform.processor() or platform.machine()}"
        f", {os.cpu_count()} CPUs, {args.threads} torch thread(s); torch {torch.__version__}\n",
        f"## MASt3R at {width}x{height} (random weights)\n",
    ]
    mast3r = mast3r_rows(device, (width, height), args.batch, args.repeats)
    lines += [*table(mast3r), ""]
    print("\n".join(lines), flush=True)
    auto = DTYPE_NAMES[choose_dtype(device, "auto")]
    decode_ms = next(
        float(r["decode ms"])
        for r in mast3r
        if r["device"] == str(device) and r["precision"] == auto
    )
    agent = dashboard.scene(args.out, 1, args.frames) / "agent_0"
    slam, notes = slam_rows(agent, args.frames, device, decode_ms)
    part = [f"## SLAM per frame ({args.frames} frames, 512x384, {auto} decodes)\n", *table(slam)]
    part += ["", *(f"- {note}" for note in notes), "", "## Keyframe-graph GN iteration\n"]
    part += [*table(ba_rows(args.ba_sizes, device, args.repeats)), ""]
    print("\n".join(part), flush=True)
    (args.out / "cuda_speed.md").write_text("\n".join(lines + part) + "\n")


if __name__ == "__main__":
    main()
