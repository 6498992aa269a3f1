"""SLAM work per frame vs the prior's decode, on a real front-end run (not a test).

Runs one agent's front-end (simulated prior) over the first frames of an agent input at the
configured network resolution (default long side 512: 640x480 input -> 512x384) and
attributes the wall time of every ``process`` call to stages by wrapping the functions that
do the work (the same wrappers on any checkout, so two checkouts compare like for like):

* prior stages: ``prior_encode``, ``prior_decode`` (single and symmetric decodes),
  ``prior_retrieval``;
* SLAM stages: ``matching`` (projective matching with descriptor refinement, C-Eq. 1),
  ``tracking`` (LM-IRLS, C-Eq. 2), ``fusion`` (C-Eq. 3), ``keyframe`` (linking and loop
  verification around the decodes and matchings), ``local_solve`` (C-Eq. 5 on the agent's
  keyframe graph), ``calibration`` (once per agent: its camera settled on its first
  keyframes' pairs), ``other`` (the rest of ``process``).

Nested stages are exclusive (a decode inside linking counts as ``prior_decode`` only); an
untimed pass over the same frames goes first (numba's kernels compiled). It then times one
full-size MASt3R decode at the same resolution (random weights: the released network's
cost; an untimed decode first) and prints per-stage ms per frame and two ratios: SLAM
per frame over one decode (the tracking decode every frame needs), and over the decodes the
frame actually caused (tracking plus both directions of every keyframe link, counted on the
run; each dense matching comes with one of them). Times are CPU seconds of
this process (``time.process_time``): with one thread they equal wall time on an idle
machine and, unlike wall time, do not count the other jobs of a shared one.

The scene below turns at the demo's hand-held pace (its loop laid out for 100 frames, 7 deg
per processed frame); ``--frames 40`` alone lays the loop out for 40 frames (16 deg per
processed frame), which makes about twice as many keyframes.

    como3r synth --out /tmp/s640 --agents 1 --frames 30 --loop-frames 100 --width 640 --height 480
    OMP_NUM_THREADS=1 python benchmarks/slam_vs_prior.py --agent /tmp/s640/agent_0 \
        --frames 15 --threads 1
"""

from __future__ import annotations

import argparse
import functools
import platform
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.preprocess import make_view
from como3r.frontend import agent as agent_module
from como3r.frontend import keyframes as keyframes_module
from como3r.frontend import pairs as pairs_module
from como3r.frontend import tracker as tracker_module
from como3r.prior.base import Encoding, EncodingRecord, PairPrediction, Prior, View
from como3r.prior.mast3r.precision import PRECISIONS
from como3r.runtime.pipeline import PriorSpec, _colors, build_prior

PRIOR_STAGES = ("prior_encode", "prior_decode", "prior_retrieval")
SLAM_STAGES = ("matching", "tracking", "fusion", "keyframe", "local_solve", "calibration", "other")


class ExclusiveClock:
    """Seconds per stage; entering a nested stage pauses the enclosing one.

    Args:
        timer: the clock read at every switch: this process's CPU seconds by default; a
            CUDA run reads wall seconds after a device synchronisation (:func:`cuda_timer`),
            as its work is the device's, not the CPU's.
    """

    def __init__(self, timer: Callable[[], float] = time.process_time) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._stack: list[str] = []
        self._mark = 0.0
        self._timer = timer

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` with its calls charged to stage ``name``."""

        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            self.calls[name] = self.calls.get(name, 0) + 1
            self._switch(name)
            try:
                return fn(*args, **kwargs)
            finally:
                self._switch(None)

        return timed

    def _switch(self, entering: str | None) -> None:
        now = self._timer()
        if self._stack:
            top = self._stack[-1]
            self.seconds[top] = self.seconds.get(top, 0.0) + now - self._mark
        if entering is None:
            self._stack.pop()
        else:
            self._stack.append(entering)
        self._mark = now


#: the front-end's work functions each stage is charged with: (owner, attribute, stage)
STAGE_FUNCTIONS = (
    (agent_module.AgentFrontend, "process", "other"),
    (agent_module.AgentFrontend, "_link_new_keyframe", "keyframe"),
    (agent_module.AgentFrontend, "_local_solve", "local_solve"),
    (agent_module.AgentFrontend, "settle_camera", "calibration"),
    (tracker_module.FrameTracker, "solve", "tracking"),
    (keyframes_module.Keyframe, "fuse", "fusion"),
    (pairs_module, "match_pointmaps", "matching"),
)


@contextmanager
def instrumented(clock: ExclusiveClock) -> Iterator[None]:
    """The front-end's work functions (class and module attributes) charged to ``clock``
    while inside; the originals again after (a second run in the process is timed alone)."""
    originals = [(owner, name, getattr(owner, name)) for owner, name, _ in STAGE_FUNCTIONS]
    for (owner, name, stage), (_, _, function) in zip(STAGE_FUNCTIONS, originals):
        setattr(owner, name, clock.wrap(stage, function))
    try:
        yield
    finally:
        for owner, name, function in originals:
            setattr(owner, name, function)


def instrument_prior(clock: ExclusiveClock, prior: Any, decodes: list[int]) -> None:
    """Wrap the prior's per-image and per-pair work on the instance; ``decodes[0]`` counts
    decoded ordered pairs."""
    decode, decode_symmetric = prior.decode, prior.decode_symmetric

    def counted_decode(*args: Any) -> Any:
        decodes[0] += 1
        return decode(*args)

    def counted_symmetric(pairs: Any) -> Any:
        before = decodes[0]
        result = decode_symmetric(pairs)
        if decodes[0] == before:  # a batched decode (not through decode)
            decodes[0] += 2 * len(pairs)
        return result

    prior.encode = clock.wrap("prior_encode", prior.encode)
    prior.decode = clock.wrap("prior_decode", counted_decode)
    prior.decode_symmetric = clock.wrap("prior_decode", counted_symmetric)
    prior.retrieval_features = clock.wrap("prior_retrieval", prior.retrieval_features)


def frontend_run(
    agent_path: Path, frames: int, overrides: list[str], device: str = "cpu"
) -> tuple[ExclusiveClock, dict]:
    """Stage clock over the first ``frames`` processed frames and the run's counters, after
    an untimed run over the same frames (numba compiles its kernels at their first call and
    caches them beside the sources: a new checkout's first run compiled for seconds, more
    than its SLAM work, once per machine; CUDA sets up its kernels at their first call).

    Args:
        device: where the SLAM works: ``"cpu"``, or a CUDA device, where the simulated
            prior's predictions are handed over (:class:`OnDevice`) as MASt3R's would be
            made there, and the clock reads synchronised wall time (:func:`cuda_timer`).
    """
    _frontend_pass(agent_path, frames, overrides, None, device)
    clock = ExclusiveClock(cuda_timer if device.startswith("cuda") else time.process_time)
    return clock, _frontend_pass(agent_path, frames, overrides, clock, device)


def cuda_timer() -> float:
    """Wall seconds once the CUDA device's queued work is done."""
    torch.cuda.synchronize()
    return time.perf_counter()


class OnDevice(Prior):
    """``inner``'s predictions and retrieval features on ``device``; its encodings stay
    where ``inner`` made them (the SLAM never reads them, only hands them back)."""

    def __init__(self, inner: Prior, device: str) -> None:
        self.inner, self.device = inner, torch.device(device)
        self.descriptor_dim = inner.descriptor_dim

    def encode(self, view: View) -> Encoding:
        return self.inner.encode(view)

    def decode(self, enc_i: Encoding, enc_j: Encoding) -> PairPrediction:
        return self.inner.decode(enc_i, enc_j).to(self.device)

    def decode_pairs(self, pairs: Sequence[tuple[Encoding, Encoding]]) -> list[PairPrediction]:
        return [p.to(self.device) for p in self.inner.decode_pairs(pairs)]

    def decode_symmetric(
        self, pairs: Sequence[tuple[Encoding, Encoding]]
    ) -> list[tuple[PairPrediction, PairPrediction]]:
        return [
            (a.to(self.device), b.to(self.device)) for a, b in self.inner.decode_symmetric(pairs)
        ]

    def retrieval_features(self, enc: Encoding) -> tuple[Tensor, Tensor]:
        descriptors, attention = self.inner.retrieval_features(enc)
        return descriptors.to(self.device), attention.to(self.device)

    def can_reencode(self, agent: int) -> bool:
        return self.inner.can_reencode(agent)

    def encode_from_record(self, view: View, record: EncodingRecord) -> Encoding:
        return self.inner.encode_from_record(view, record)

    def describe(self) -> dict[str, object]:
        return {**self.inner.describe(), "device": str(self.device)}


def _frontend_pass(
    agent_path: Path,
    frames: int,
    overrides: list[str],
    clock: ExclusiveClock | None,
    device: str = "cpu",
) -> dict:
    """One front-end over the first ``frames`` processed frames, its stages on ``clock``
    (None: not timed) and the SLAM on ``device``; returns the run's counters."""
    config = apply_overrides(Config(), overrides)
    agent = open_agent(agent_path, fps=config.input.frame_rate_hz)
    prior, codebook = build_prior(PriorSpec("simulated"), config, {0: agent})
    if device != "cpu":
        prior = OnDevice(prior, device)
    decodes = [0]
    if clock is not None:
        instrument_prior(clock, prior, decodes)
    frontend = agent_module.AgentFrontend(prior, config, 0, codebook)
    indices = list(range(0, agent.num_frames, config.input.subsample))[:frames]
    shape = None
    with instrumented(clock) if clock is not None else nullcontext():
        for index in indices:
            frame = agent.load_frame(index)
            view = make_view(frame, 0, config.input.long_side)
            shape = tuple(view.image.shape[1:])
            frontend.process(view, frame.timestamp, _colors(view))
    stats = frontend.stats
    counters = {
        "frames": len(indices),
        "keyframes": stats.keyframes,
        "local_solves": stats.local_solves,
        "loop_edges": stats.loop_edges,
        "loop_candidates": stats.loop_candidates,
        "decodes": decodes[0],
        "resolution": f"{shape[1]}x{shape[0]}",
        "device": device,
    }
    return counters


def mast3r_decode_seconds(width: int, height: int, precision: str) -> float:
    """One decode of a pair by the full-size MASt3R network (random weights) at ``precision``
    as ``como3r run --precision`` chooses it on the CPU, after an untimed one (the first
    decode of a process also sets up the kernels: 7.4 s against 4.5)."""
    from como3r.prior.mast3r import MASt3RNetwork, parse_model_string
    from como3r.prior.mast3r.config import RELEASED_MODEL_STRING
    from como3r.prior.mast3r.precision import choose_dtype
    from como3r.prior.mast3r.prior import MASt3RPrior

    torch.manual_seed(0)
    network = MASt3RNetwork(parse_model_string(RELEASED_MODEL_STRING))
    prior = MASt3RPrior(network, dtype=choose_dtype(torch.device("cpu"), precision))
    enc = prior.encode(torch.rand(1, 3, height, width) * 2 - 1)
    prior.decode(enc, enc)
    start = time.process_time()
    prior.decode(enc, enc)
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--decode-ms",
        type=float,
        default=None,
        help="skip the MASt3R timing and use this decode time",
    )
    parser.add_argument(
        "--precision",
        default="auto",
        choices=PRECISIONS,
        help="MASt3R precision of the timed decode (as como3r run --precision)",
    )
    parser.add_argument("--set", action="append", default=[], help="config override")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    clock, counters = frontend_run(args.agent, args.frames, list(args.set))
    seconds = clock.seconds
    width, height = (int(v) for v in counters["resolution"].split("x"))
    decode_ms = (
        args.decode_ms
        if args.decode_ms is not None
        else 1000.0 * mast3r_decode_seconds(width, height, args.precision)
    )
    n = counters["frames"]
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} threads; {counters}; overrides {args.set}; precision {args.precision}"
    )
    print("stage | ms per frame | calls | ms per call")
    for stage in (*PRIOR_STAGES, *SLAM_STAGES):
        ms, calls = 1000.0 * seconds.get(stage, 0.0), clock.calls.get(stage, 0)
        per_call = f"{ms / calls:.0f}" if calls else "-"
        print(f"{stage} | {ms / n:.0f} | {calls} | {per_call}")
    slam_ms = 1000.0 * sum(seconds.get(s, 0.0) for s in SLAM_STAGES) / n
    per_frame_decode_ms = decode_ms * counters["decodes"] / n
    print(f"SLAM total | {slam_ms:.0f}")
    print(f"MASt3R decode (one ordered pair, {width}x{height}) | {decode_ms:.0f}")
    print(f"SLAM / one MASt3R decode | {slam_ms / decode_ms:.3f}")
    print(f"MASt3R decodes per frame ({counters['decodes']} / {n}) | {per_frame_decode_ms:.0f}")
    print(f"SLAM / MASt3R decodes of the frame | {slam_ms / per_frame_decode_ms:.3f}")


if __name__ == "__main__":
    main()
