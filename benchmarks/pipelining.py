"""Seconds per frame of one agent with the prior's encode in line and run ahead on a thread
(``input.prefetch_frames`` 0 against the default), on this machine (a script, not a test).

The SLAM work is real (the simulated prior's pointmaps, default configuration, 512 px);
the prior's cost is MASt3R's: every encode and decode also runs the full-size network
(random weights, ``--precision``) on the frame's image and discards the result, so the
timeline is that of a MASt3R run while tracking stays meaningful. Both settings run the
same frames alternately in one process and print wall seconds per frame and the ratio.

    como3r synth --out /tmp/s640 --agents 1 --frames 40 --width 640 --height 480 \\
        --loop-frames 100
    python benchmarks/pipelining.py --agent /tmp/s640/agent_0 --frames 8 --threads 1
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import time
from pathlib import Path

import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.frontend.agent import AgentFrontend
from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, MASt3RPrior
from como3r.prior.mast3r.precision import choose_dtype
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.pipeline import load_frame
from como3r.runtime.prefetch import prepared_frames


class CostlyPrior:
    """The simulated prior that also pays MASt3R's compute for every encode and decode."""

    def __init__(self, simulated: SimulatedPrior, mast3r: MASt3RPrior) -> None:
        self.simulated, self.mast3r = simulated, mast3r
        self._images: dict[tuple[int, int], object] = {}

    def __getattr__(self, name: str):
        return getattr(self.simulated, name)

    def encode(self, view):
        self._images[(view.agent, view.index)] = self.mast3r.encode(view.image)
        return self.simulated.encode(view)

    def decode(self, enc_i, enc_j):
        self.mast3r.decode(
            self._images[(enc_i.agent, enc_i.index)], self._images[(enc_j.agent, enc_j.index)]
        )
        return self.simulated.decode(enc_i, enc_j)

    def decode_symmetric(self, pairs):
        for enc_i, enc_j in pairs:
            self.mast3r.decode_symmetric(
                [
                    (
                        self._images[(enc_i.agent, enc_i.index)],
                        self._images[(enc_j.agent, enc_j.index)],
                    )
                ]
            )
        return self.simulated.decode_symmetric(pairs)


def seconds_per_frame(prior: CostlyPrior, agent_path: Path, frames: int, prefetch: int) -> float:
    """Wall seconds per processed frame of one agent's front-end."""
    config = apply_overrides(Config(), [f"input.prefetch_frames={prefetch}"])
    source = open_agent(agent_path)
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    indices = list(range(0, source.num_frames, config.input.subsample))[:frames]
    start = time.perf_counter()
    stream = prepared_frames(
        ((0, i) for i in indices),
        lambda a, i: load_frame(source, a, i, config.input.long_side, False),
        prior,
        prefetch,
    )
    with contextlib.closing(stream):
        for frame in stream:
            frontend.process(frame.view, frame.timestamp, frame.colors, frame.encoding)
    return (time.perf_counter() - start) / len(indices)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per thread")
    parser.add_argument("--precision", default="auto")
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    dtype = choose_dtype(torch.device("cpu"), args.precision)
    mast3r = MASt3RPrior(MASt3RNetwork(MASt3RConfig()), dtype=dtype)
    truth = AgentFolderTruth({0: open_agent(args.agent)}, Config().input.long_side)
    prior = CostlyPrior(SimulatedPrior(Config().simulated_prior, truth), mast3r)
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, "
        f"{args.threads} torch thread(s), MASt3R {dtype} (random weights), load average "
        f"{os.getloadavg()[0]:.1f}; {args.frames} frames at long side 512"
    )
    results: dict[int, list[float]] = {0: [], 2: []}
    for _ in range(args.rounds):
        for prefetch in results:
            results[prefetch].append(seconds_per_frame(prior, args.agent, args.frames, prefetch))
    in_line, ahead = min(results[0]), min(results[2])
    print(f"{'encode':>10} | s per frame (best of {args.rounds})")
    print(f"{'in line':>10} | {in_line:.2f}")
    print(f"{'ahead':>10} | {ahead:.2f}")
    print(f"speed-up (in line / ahead): {in_line / ahead:.2f}")


if __name__ == "__main__":
    main()
