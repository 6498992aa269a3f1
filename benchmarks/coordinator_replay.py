"""The coordinator's in-stream work on recorded input: capture a run's calls once, replay them
in one thread as often as needed (not a test; issue 41).

A multi-process run's coordinator takes its keyframes in batches that depend on timing, so
two runs of one scene differ in their batches, and the coordinator shares the cores with the
agents. ``capture`` runs a scene (``como3r run``'s multi-process runtime, default
configuration, simulated prior) and keeps every :meth:`Coordinator.add_keyframes` batch and
every pointmap refresh in the order the coordinator took them, each message coded bit-exact
in the wire codec (:mod:`como3r.transport.codec`; no pickle). ``replay`` hands the same
calls to a fresh coordinator in one process and prints, per replay: the calls' sizes, the
coordinator thread's CPU per keyframe (its verification pool's threads apart), the
verification's CPU, ``stage_seconds`` (wall; in one process on an idle machine close to the
CPU), decodes, merges, admitted edges and, with ``--scene``, the in-stream keyframe ATE
(keyframe positions before the terminal cleanup, one similarity against the ground truth),
and then those outputs again with every digit of the ATE.
The same calls replayed by two checkouts (``PYTHONPATH=<checkout>/src``) compare their
coordinators on identical input; ``--set`` compares configurations. ``--store DIR``
journals the coordinator to a session store there, which pages out what lies outside the
working set as a run's does (its pointmaps then settle on their coded values, so the
outputs differ from a replay without one); ``--census`` prints after each batch the
process's peak resident memory in it (and where the main thread was then), its memory
after a heap trim and the coordinator's tensors by owner
(:func:`como3r.coordination.census.census`).

    python benchmarks/coordinator_replay.py capture --scene /tmp/ts/scene_a16_s0 \\
        --out /tmp/cap_run --calls /tmp/cap16
    OMP_NUM_THREADS=1 python benchmarks/coordinator_replay.py replay --calls /tmp/cap16 \\
        --scene /tmp/ts/scene_a16_s0 [--set gauge.max_correspondences=0] \\
        [--store /tmp/replay_store --census]

Measured (session 29; the 16-agent scene of ``benchmarks/team_scale.py``, calls of 1 / 1 /
24 / 14 keyframes; 2 shared cores): in-stream thread CPU 868 ms per keyframe at 90798a6,
305 at 1de7378 (the merge decision's memo, ``sim3_act_points`` and
``gauge.max_correspondences``), in-stream keyframe ATE 67.66 -> 67.53 mm; with
``verification.workers=0`` 2191 ms, of which the verification 1980 (the simulated prior's
decodes and re-encodes 72 %, the matching 25 %).

Measured (session 36; the long 16-agent capture of ``team_scale.py --frames 48``, 190
keyframes, ``--store --census``): tensors held after the batch 1397 / 2117 / 2337 MB at 41 /
100 / 190 keyframes (3185 at 190 before every edge outside the working set was paged), of
which the encoding cache 1548 from 64 keyframes on; the batch's peak resident memory 3.2 /
5.1 / 8.1 GB, of which the in-stream global BA's dense factors 0.09 / 0.69 / 1.99 GB.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _tables import print_table  # noqa: E402

from como3r.config import Config, apply_overrides  # noqa: E402
from como3r.coordination.census import census, megabytes  # noqa: E402
from como3r.coordination.coordinator import Coordinator  # noqa: E402
from como3r.geometry.umeyama import umeyama_rmse, umeyama_sim3  # noqa: E402
from como3r.heap import give_back_freed_memory, one_heap_arena  # noqa: E402
from como3r.io.tum import read_tum  # noqa: E402
from como3r.optim.relinearization import ThresholdRelinearized  # noqa: E402
from como3r.prior.simulated import SimulatedPrior  # noqa: E402
from como3r.store.resume import open_store  # noqa: E402
from como3r.transport import codec  # noqa: E402

#: the largest message a capture holds (a keyframe at the full resolution, bit-exact)
MAX_BYTES = 1 << 30
COLUMNS = (
    "calls",
    "keyframes",
    "thread ms/kf",
    "verification ms/kf",
    "decodes",
    "merges",
    "edges",
    "ATE mm",
    "stages ms/kf",
)


@contextmanager
def recording(folder: Path) -> Iterator[None]:
    """While open, every coordinator of this process writes its ``add_keyframes`` batches and
    refreshes to ``folder`` (``log.json`` lists them in order; one ``.bin`` per message)."""
    folder.mkdir(parents=True, exist_ok=True)
    log: list[list[Any]] = []
    add, refresh = Coordinator.add_keyframes, Coordinator.refresh

    def recorded_add(coordinator: Coordinator, packets: Sequence[Any], solve: bool = True) -> Any:
        for k, packet in enumerate(packets):
            (folder / f"{len(log):05d}_{k:04d}.bin").write_bytes(
                codec.encode(packet, max_bytes=MAX_BYTES)
            )
        log.append(["batch", len(packets), coordinator.num_agents, solve])
        return add(coordinator, packets, solve)

    def recorded_refresh(coordinator: Coordinator, agent: int, message: Any) -> None:
        (folder / f"{len(log):05d}_r.bin").write_bytes(codec.encode(message, max_bytes=MAX_BYTES))
        log.append(["refresh", agent, coordinator.num_agents])
        refresh(coordinator, agent, message)

    Coordinator.add_keyframes = recorded_add  # type: ignore[method-assign]
    Coordinator.refresh = recorded_refresh  # type: ignore[method-assign]
    try:
        yield
    finally:
        Coordinator.add_keyframes, Coordinator.refresh = add, refresh  # type: ignore[method-assign]
        (folder / "log.json").write_text(json.dumps({"calls": log}))


def calls(folder: Path) -> Iterator[tuple[str, Any, int]]:
    """The recorded calls in order: ``("batch", (packets, solve), agents)`` or ``("refresh",
    (agent, refresh), agents)`` (a capture made before a batch said ``solve``: True)."""
    for n, (kind, what, agents, *solve) in enumerate(
        json.loads((folder / "log.json").read_text())["calls"]
    ):
        if kind == "batch":
            packets = [
                codec.decode((folder / f"{n:05d}_{k:04d}.bin").read_bytes(), max_bytes=MAX_BYTES)
                for k in range(what)
            ]
            yield kind, (packets, bool(solve[0]) if solve else True), agents
        else:
            data = (folder / f"{n:05d}_r.bin").read_bytes()
            yield kind, (what, codec.decode(data, max_bytes=MAX_BYTES)), agents


def replay(
    folder: Path, config: Config, store: Path | None = None, counted: bool = False
) -> tuple[Coordinator, list[tuple[int, float]]]:
    """A fresh coordinator fed the recorded calls; returns it and, per batch, its size and the
    coordinator thread's CPU seconds in it.

    Args:
        store: a folder for a session store that journals (and pages out) the coordinator
            as a run's does (its pointmaps settle on their coded values, so the outputs
            differ from a replay without one); None: no store, nothing paged out.
        counted: after each batch, print the process's resident memory and the
            coordinator's tensors by owner (:func:`como3r.coordination.census.census`).
    """
    prior = SimulatedPrior(config.simulated_prior, None)
    coordinator: Coordinator | None = None
    seconds: list[tuple[int, float]] = []
    with ExitStack() as stack:
        solves = stack.enter_context(watching_solves()) if counted else {}
        for kind, what, agents in calls(folder):
            if coordinator is None:
                coordinator = Coordinator(prior, config, prior.codebook(), agents)
                if store is not None:
                    store.mkdir(parents=True, exist_ok=True)
                    stack.enter_context(open_store(store, config, coordinator))
            while coordinator.num_agents < agents:
                coordinator.add_agent()
            if kind == "batch":
                watch = PeakWatch() if counted else None
                start = time.thread_time()
                coordinator.add_keyframes(*what)
                seconds.append((len(what[0]), time.thread_time() - start))
                if watch is not None:
                    print_census(coordinator, len(what), watch.stop())
                    print(
                        f"solves: largest dense factors held {solves['dense MB']:.0f} MB "
                        f"({solves['edges']} directed edges)",
                        flush=True,
                    )
                    solves.update({"dense MB": 0.0, "edges": 0})
            else:
                coordinator.refresh(*what)
    if coordinator is None:
        raise SystemExit(f"{folder}: no calls recorded")
    return coordinator, seconds


class PeakWatch:
    """The largest resident memory of this process while it runs (sampled every 0.1 s on a
    thread of its own) and where the main thread was then (its innermost frames)."""

    def __init__(self) -> None:
        self.peak, self.where = 0.0, ""
        self._main = threading.main_thread().ident or 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.1):
            rss = resident_mb("VmRSS")
            if rss > self.peak:
                frame = sys._current_frames().get(self._main)  # noqa: SLF001 (a sample)
                names: list[str] = []
                while frame is not None and len(names) < 4:
                    names.append(frame.f_code.co_name)
                    frame = frame.f_back
                self.peak, self.where = rss, " < ".join(names)

    def stop(self) -> tuple[float, str]:
        """The peak (MB) and where it was."""
        self._stop.set()
        self._thread.join()
        return self.peak, self.where


class _Held:
    """What :func:`census` walks: one solve's dense factor batches."""

    def __init__(self, dense: dict) -> None:
        self.dense = dense


@contextmanager
def watching_solves() -> Iterator[dict[str, float]]:
    """While open, the largest bytes of dense factors one global-BA solve holds at once
    (``ThresholdRelinearized``'s batches, built once per solve and kept to its end; MB) and
    that solve's edges, since the last reset of the dictionary yielded."""
    seen = {"dense MB": 0.0, "edges": 0}
    methods = {name: getattr(ThresholdRelinearized, name) for name in ("cost", "linearize")}

    def counted(method: Any) -> Any:
        def call(self: ThresholdRelinearized, poses: torch.Tensor) -> torch.Tensor:
            value = method(self, poses)
            mb = sum(census(_Held(self._dense)).values()) / 1e6
            if mb > seen["dense MB"]:
                seen["dense MB"], seen["edges"] = mb, self.num_edges
            return value

        return call

    for name, method in methods.items():
        setattr(ThresholdRelinearized, name, counted(method))
    try:
        yield seen
    finally:
        for name, method in methods.items():
            setattr(ThresholdRelinearized, name, method)


def print_census(coordinator: Coordinator, batch: int, peak: tuple[float, str]) -> None:
    """One line after a batch: keyframes, the process's peak resident memory in the batch
    and where, its resident memory after a heap trim, the tensors held and their owners
    (MB)."""
    held = megabytes(census(coordinator))
    give_back_freed_memory()
    owners = ", ".join(f"{owner} {mb:.1f}" for owner, mb in held.items() if mb >= 0.5)
    print(
        f"census: {len(coordinator.graph.keyframes)} kf (batch {batch}), peak RSS "
        f"{peak[0]:.0f} MB in {peak[1]}, RSS {resident_mb('VmRSS'):.0f} MB, held "
        f"{sum(held.values()):.0f} MB: {owners}",
        flush=True,
    )


def resident_mb(field: str) -> float:
    """A memory figure of this process's ``/proc/self/status`` (``VmRSS``, ``VmHWM``), MB
    (Linux; 0 elsewhere)."""
    status = Path("/proc/self/status")
    if not status.exists():
        return 0.0
    for line in status.read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1e3
    return 0.0


def keyframe_ate(coordinator: Coordinator, scene: Path) -> float:
    """RMSE [m] of the coordinator's keyframe positions after one similarity onto the ground
    truth at their timestamps (``scene/agent_<id>/groundtruth.txt``). Not
    :func:`como3r.evaluation.trajectory.merged_errors`: its association needs 3 poses per
    agent (``MIN_ASSOCIATED``), and a 16-agent team's coordinator holds 2 or 3 keyframes of
    each agent in these runs."""
    graph, truth = coordinator.graph, {}
    estimated, true = [], []
    for g, kf in enumerate(graph.keyframes):
        agent = graph.agent_of[g]
        if agent not in truth:
            track = read_tum(scene / f"agent_{agent}" / "groundtruth.txt")
            truth[agent] = (np.asarray(track.timestamps), track.T_WC)
        stamps, poses = truth[agent]
        nearest = int(np.argmin(np.abs(stamps - float(kf.timestamp))))
        estimated.append(kf.T_WC[:3].double())
        true.append(torch.as_tensor(poses[nearest][:3]).double())
    est, gt = torch.stack(estimated), torch.stack(true)
    return umeyama_rmse(umeyama_sim3(est, gt), est, gt)


def row(coordinator: Coordinator, seconds: list[tuple[int, float]], scene: Path | None) -> dict:
    stats = coordinator.stats
    keyframes = max(1, stats.keyframes)
    return {
        "calls": " / ".join(str(n) for n, _ in seconds),
        "keyframes": stats.keyframes,
        "thread ms/kf": 1e3 * sum(s for _, s in seconds) / keyframes,
        "verification ms/kf": 1e3
        * (stats.verification_cpu + sum(stats.pool_seconds.values()))
        / keyframes,
        "decodes": stats.prior_decodes,
        "merges": stats.gauge_syncs,
        "edges": stats.edges_accepted,
        "ATE mm": "-" if scene is None else 1e3 * keyframe_ate(coordinator, scene),
        "stages ms/kf": ", ".join(
            f"{stage} {1e3 * s / keyframes:.0f}"
            for stage, s in sorted(stats.stage_seconds.items(), key=lambda kv: -kv[1])
        ),
    }


def capture(scene: Path, out: Path, folder: Path, config: Config) -> None:
    from como3r.runtime.multiprocess import run_multiprocess
    from como3r.runtime.pipeline import PriorSpec

    agents = sorted(scene.glob("agent_*"), key=lambda p: int(p.name.split("_")[1]))
    if not agents:
        raise SystemExit(f"no agent_* folders in {scene}")
    with recording(folder):
        run_multiprocess(agents, out, config, PriorSpec("simulated"), overwrite=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    take = sub.add_parser("capture", help="run a scene and record its coordinator's calls")
    take.add_argument("--scene", type=Path, required=True, help="folder of agent_* inputs")
    take.add_argument("--out", type=Path, required=True, help="the run's output folder")
    take.add_argument("--calls", type=Path, required=True, help="where the calls go")
    again = sub.add_parser("replay", help="replay recorded calls in one thread")
    again.add_argument("--calls", type=Path, required=True)
    again.add_argument("--scene", type=Path, default=None, help="ground truth for the ATE")
    again.add_argument(
        "--store", type=Path, default=None, help="journal and page out to a store here"
    )
    again.add_argument(
        "--census", action="store_true", help="print memory and tensors by owner per batch"
    )
    for command in (take, again):
        command.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    one_heap_arena()  # as a coordinator's process does (como3r.runtime.multiprocess)
    config = apply_overrides(Config(), args.set)
    if args.command == "capture":
        capture(args.scene, args.out, args.calls, config)
        return
    coordinator, seconds = replay(args.calls, config, args.store, args.census)
    title = "coordinator replay" + (f" ({', '.join(args.set)})" if args.set else "")
    result = row(coordinator, seconds, args.scene)
    print_table(Console(width=200), [result], COLUMNS, title)
    # every digit: two checkouts that should agree bit for bit are compared on this line
    print(
        f"outputs: {result['merges']} merges, {result['edges']} edges, "
        f"{result['decodes']} decodes, in-stream keyframe ATE {result['ATE mm']!r} mm"
    )


if __name__ == "__main__":
    main()
