"""Resident memory against sequence length, with the coordinator's keyframes paged out to the
session store and without (issue 14, bounded memory; a script, not a test).

One agent on a long synthetic loop runs in the default multi-process runtime (``como3r
run``): the coordinator in the measuring process, the agent in its own. Every ``--every``
processed frames both processes' resident set size (``VmRSS``) and peak
(``VmHWM``) are read from ``/proc`` (Linux only), with the keyframes the coordinator holds;
the last row is the end of the run (terminal refinement and outputs included); with
``--phases`` also as each step of the end starts (a cleanup pass, an alternation round, the
outputs, the evaluation, the report: which step makes the peak). Each
``--resident`` value (``session.resident_keyframes``: the keyframes per agent kept whole in
memory; the default configuration's first) runs in a process of its own, so peaks do not
carry over.

    como3r synth --out /tmp/long --agents 1 --frames 5000 --width 64 --height 48
    python benchmarks/memory.py --agent /tmp/long/agent_0 --every 250 --long-side 64
    python benchmarks/memory.py --agent /tmp/long/agent_0 --every 250 --long-side 64 \
        --frames 1000 --resident 1000000000     # the first 1,000 frames, never paged

``--long-side`` defaults to the configuration's (512); the figures in the closing note of
issue 14 were taken with ``--long-side 64`` (the scene's own size) to fit 5,000 frames into
an hour on a 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from como3r.config import Config, apply_overrides
from como3r.progress import AgentProgress, PhaseEvent
from como3r.runtime.multiprocess import run_multiprocess
from como3r.runtime.pipeline import PriorSpec


def _status(pid: int | str) -> dict[str, float]:
    """``VmRSS`` and ``VmHWM`` of a process [MB] (zeros if it is gone)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return {"VmRSS": 0.0, "VmHWM": 0.0}
    fields = dict(line.split(":", 1) for line in lines if ":" in line)
    return {key: int(fields[key].split()[0]) / 1024 for key in ("VmRSS", "VmHWM")}


def _agent_pids() -> list[int]:
    """This process's agent processes (multiprocessing spawn children, not its resource
    tracker)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == os.getpid() and b"spawn_main" in command and b"resource_tracker" not in command:
            pids.append(int(entry.name))
    return pids


def first_frames(agent: Path, frames: int, folder: Path) -> Path:
    """An agent folder of the first ``frames`` frames of ``agent`` (links to its files)."""
    folder.mkdir(parents=True, exist_ok=True)
    for entry in agent.iterdir():
        target = folder / entry.name
        if entry.is_dir():
            target.mkdir(exist_ok=True)
            for file in sorted(entry.iterdir())[:frames]:
                if not (target / file.name).exists():
                    (target / file.name).symlink_to(file)
        elif entry.name in ("timestamps.txt", "groundtruth.txt", "odometry.txt"):
            lines = entry.read_text().splitlines(keepends=True)
            header = [line for line in lines if line.startswith("#")]
            target.write_text(
                "".join(header + [line for line in lines if not line.startswith("#")][:frames])
            )
        elif not target.exists():
            target.symlink_to(entry)
    return folder


def measure(
    agent: Path, out: Path, resident: int, every: int, long_side: int | None, phases: bool = False
) -> None:
    """One run; prints one JSON line per sample (with ``phases`` also one as each step of
    the end starts: the first six letters of its phase in ``frames``, its number in
    ``keyframes``)."""
    overrides = [f"session.resident_keyframes={resident}"]
    if long_side is not None:
        overrides.append(f"input.long_side={long_side}")
    config = apply_overrides(Config(), overrides)
    start = time.perf_counter()

    def sample(frames: int | str, keyframes: int | str) -> None:
        own = _status("self")
        agents = [_status(pid) for pid in _agent_pids()]
        print(
            json.dumps(
                {
                    "frames": frames,
                    "keyframes": keyframes,
                    "coordinator_rss": own["VmRSS"],
                    "coordinator_peak": own["VmHWM"],
                    "agent_rss": sum(a["VmRSS"] for a in agents),
                    "agent_peak": sum(a["VmHWM"] for a in agents),
                    "seconds": time.perf_counter() - start,
                }
            ),
            flush=True,
        )

    def progress(event: object) -> None:
        if (
            isinstance(event, AgentProgress)
            and event.frames_done % every == 0
            and event.frames_done
        ):
            sample(event.frames_done, event.keyframes)
        elif isinstance(event, PhaseEvent) and phases:  # as the step starts
            sample(event.name[:6], event.done)

    summary = run_multiprocess(
        [agent], out, config, PriorSpec("simulated"), overwrite=True, progress=progress
    )
    sample(summary.agents[0]["frames"], summary.agents[0]["keyframes"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", type=Path, required=True, help="a long agent input")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("/tmp/como3r_memory"),
        help="scratch folder for the runs' outputs",
    )
    parser.add_argument("--every", type=int, default=250, help="sample every N frames")
    parser.add_argument(
        "--resident",
        type=int,
        nargs="+",
        default=[Config().session.resident_keyframes, 10**9],
        help="session.resident_keyframes values to compare (10**9: never paged)",
    )
    parser.add_argument(
        "--long-side", type=int, default=None, help="input.long_side (default: the configuration's)"
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="only the first N frames of the input (default: all)",
    )
    parser.add_argument(
        "--phases",
        action="store_true",
        help="also sample as each step of the end starts (cleanup passes, "
        "alternation rounds, outputs, evaluation, report)",
    )
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.frames is not None and args.one is None:
        args.agent = first_frames(args.agent, args.frames, args.out / f"first_{args.frames}")
    if args.one is not None:
        measure(
            args.agent,
            args.out / f"resident_{args.one}",
            args.one,
            args.every,
            args.long_side,
            args.phases,
        )
        return
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"{args.agent}; RSS in MB"
    )
    print(
        f"{'resident':>9} {'frames':>6} {'keyframes':>9} {'coord RSS':>9} {'coord peak':>10} "
        f"{'agent RSS':>9} {'agent peak':>10} {'seconds':>8}"
    )
    for resident in args.resident:
        command = [
            sys.executable,
            __file__,
            "--agent",
            str(args.agent),
            "--out",
            str(args.out),
            "--every",
            str(args.every),
            "--one",
            str(resident),
        ]
        if args.long_side is not None:
            command += ["--long-side", str(args.long_side)]
        if args.phases:
            command.append("--phases")
        with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as run:
            for line in run.stdout:  # as they come: a long run shows its curve as it goes
                row = json.loads(line)
                print(
                    f"{resident:>9} {row['frames']:>6} {row['keyframes']:>9} "
                    f"{row['coordinator_rss']:>9.0f} {row['coordinator_peak']:>10.0f} "
                    f"{row['agent_rss']:>9.0f} {row['agent_peak']:>10.0f} "
                    f"{row['seconds']:>8.0f}",
                    flush=True,
                )
        if run.returncode:
            raise SystemExit(f"the run with --resident {resident} failed")


if __name__ == "__main__":
    main()
