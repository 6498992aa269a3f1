"""Seconds per pair of the decentralized registration's descriptor matching vs one decode.

Decodes keyframe pairs of a synthetic scene with the simulated prior at ``--long-side``
(512x384 by default, MASt3R's resolution), matches each pair's descriptors
(:func:`como3r.decentralized.matching.reciprocal_matches`) three ways and prints seconds per
pair, matches, and the ratio to one decode of the full-size MASt3R network (random weights,
fp32, :func:`slam_vs_prior.mast3r_decode_seconds`) measured in the same run:

- ``brute force, 4 px``: the former search, a ``(256, N)`` score matrix per chunk of
  queries and its argmax, queries on a 4-pixel grid, every pass searched anew;
- ``faiss, 4 px``: exact faiss inner-product search, each pixel searched once per pair
  (must give the same matches as the brute force: the ``same`` column);
- ``faiss, default``: the same on the default grid (``match_stride_ratio`` 1/64 of the long
  side: 8 px at 512, as the official code).

Measured with ``OMP_NUM_THREADS=1 nice -n 19 python benchmarks/decentralized_matching.py
--scene /tmp/dscale/bench512/scene_x20`` (1 thread, 2-core AMD EPYC shared with other
jobs; all seconds are process CPU time, which such sharing inflates less than wall time),
the default pairs: two true loops and one unrelated pair of the 20x scene of
``decentralized_scale.py`` (its runs registered them as loops, ratio 0.41 and 0.59, and
refused, ratio 0.12):

    512x384, 3 pairs; MASt3R decode 12.77 s (fp32, 1 thread, CPU time); simulated prior
    decode 0.44 s per pair

    method             | s per pair | / decode | matches per pair
    brute force, 4 px  |      17.05 |     1.33 | 4364 6049 1225
    faiss, 4 px        |       7.67 |     0.60 | 4364 6049 1225
    faiss, default     |       4.73 |     0.37 | 1565 1901 467
    faiss, 4 px gives the brute force's matches: 3 of 3 pairs

Exact search at the official query density is still a third of a decode: each pair searches
~7,400 neighbours (first round trip ~3,000 + ~3,000 unique, then ~1,400 + ~1,400 and ~350 +
~350 of the unconverged) among ~190,000 confident pixels of 24-d descriptors. In whole
``decentralized_scale.py`` runs the robots' ``match_seconds`` per decode went from 140 s
(wall, before, decode and matching together) to 46 s (wall) against 3.5 s of simulated
``decode_seconds``: three robot threads and other jobs shared two cores there.

Run it on any ``como3r synth`` scene with ``agent_0`` and ``agent_1`` (``--scene``); without
``--scene`` it renders the default 3-robot scene of ``decentralized_scale.py`` first.
"""

from __future__ import annotations

import argparse
import logging
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import faiss
import torch
from torch import Tensor

from como3r.config import Config, InputConfig
from como3r.data.agent import open_agent
from como3r.data.preprocess import make_view
from como3r.decentralized.config import RegistrationConfig
from como3r.decentralized.matching import query_grid, reciprocal_matches
from como3r.prior.base import PairPrediction
from como3r.runtime.pipeline import PriorSpec, build_prior

logger = logging.getLogger(__name__)

#: Queries per chunk of the former brute-force search.
_CHUNK = 256


def _brute_force_nearest(queries: Tensor, database: Tensor, scores: Tensor) -> Tensor:
    """The former search: ``(Q,)`` argmax of each chunk's row of ``queries @ database.T``,
    written to the reused ``scores`` buffer ``(_CHUNK, N)``."""
    database_T = database.T.contiguous()
    best = []
    for chunk in queries.split(_CHUNK):
        out = scores[: chunk.shape[0]]
        torch.mm(chunk, database_T, out=out)
        best.append(torch.argmax(out, dim=1))
    return torch.cat(best)


def brute_force_matches(pred: PairPrediction, stride: int,
                        config: RegistrationConfig) -> tuple[Tensor, Tensor]:
    """The former ``reciprocal_matches`` with queries every ``stride`` pixels: same
    algorithm as the package's, every pass's neighbours searched by brute force."""
    H, W, d = pred.D_ii.shape
    q_min = config.min_descriptor_confidence
    pixels_i = torch.nonzero(pred.Q_ii.reshape(-1) > q_min)[:, 0]
    pixels_j = torch.nonzero(pred.Q_ji.reshape(-1) > q_min)[:, 0]
    flat_i = pred.D_ii.reshape(-1, d)[pixels_i].float()
    flat_j = pred.D_ji.reshape(-1, d)[pixels_j].float()
    scores = torch.empty(_CHUNK, max(flat_i.shape[0], flat_j.shape[0]))
    row_of = torch.full((H * W,), -1, dtype=torch.long)
    row_of[pixels_i] = torch.arange(pixels_i.numel())
    query = row_of[query_grid(H, W, stride / max(H, W))]
    query = query[query >= 0]
    found_i, found_j = [], []
    for _ in range(config.match_iterations):
        if query.numel() == 0:
            break
        in_j = _brute_force_nearest(flat_i[query], flat_j, scores[:, :flat_j.shape[0]])
        back = _brute_force_nearest(flat_j[in_j], flat_i, scores[:, :flat_i.shape[0]])
        converged = back == query
        found_i.append(query[converged])
        found_j.append(in_j[converged])
        query = torch.unique(back[~converged])
    pairs = torch.unique(torch.stack([torch.cat(found_i), torch.cat(found_j)], dim=1), dim=0)
    return pixels_i[pairs[:, 0]], pixels_j[pairs[:, 1]]


def _render(folder: Path) -> Path:
    import decentralized_scale  # the benchmark next to this one

    scene = folder / "scene"
    decentralized_scale.render(scene, frames=40, width=160, height=120, seed=0)
    return scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="como3r synth scene (default: render one)")
    parser.add_argument("--long-side", type=int, default=Config().input.long_side)
    parser.add_argument("--pairs", default="0,17,1,0;0,23,1,0;0,0,1,29",
                        help="'agent,frame,agent,frame;...': the pairs decoded")
    parser.add_argument("--skip-brute-force", action="store_true",
                        help="no brute-force rows (they take minutes at 512)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    faiss.omp_set_num_threads(args.threads)
    scene = args.scene or _render(Path(tempfile.mkdtemp(prefix="como3r_matching_")))
    config = Config(input=InputConfig(long_side=args.long_side))
    pairs = [tuple(int(v) for v in item.split(",")) for item in args.pairs.split(";")]
    agents = {a: open_agent(scene / f"agent_{a}") for a in sorted({p[0] for p in pairs}
                                                                   | {p[2] for p in pairs})}
    prior = build_prior(PriorSpec("simulated"), config, agents)[0]
    registration = RegistrationConfig()
    methods = {"brute force, 4 px": lambda pred: brute_force_matches(pred, 4, registration),
               "faiss, 4 px": lambda pred: reciprocal_matches(
                   pred.D_ii, pred.D_ji, pred.Q_ii, pred.Q_ji,
                   replace(registration, match_stride_ratio=4 / args.long_side)),
               "faiss, default": lambda pred: reciprocal_matches(
                   pred.D_ii, pred.D_ji, pred.Q_ii, pred.Q_ji, registration)}
    if args.skip_brute_force:
        del methods["brute force, 4 px"]
    seconds = {name: 0.0 for name in methods}
    matches = {name: [] for name in methods}
    same = []
    simulated_decode = 0.0
    for a, fa, b, fb in pairs:
        views = [make_view(agents[agent].load_frame(frame), agent, args.long_side)
                 for agent, frame in ((a, fa), (b, fb))]
        encodings = [prior.encode(view) for view in views]
        start = time.process_time()
        pred = prior.decode_symmetric([tuple(encodings)])[0][0]
        simulated_decode += time.process_time() - start
        found = {}
        for name, method in methods.items():
            start = time.process_time()
            found[name] = method(pred)
            seconds[name] += time.process_time() - start
            matches[name].append(int(found[name][0].numel()))
        if "brute force, 4 px" in found:
            same.append(all(torch.equal(x, y) for x, y in
                             zip(found["brute force, 4 px"], found["faiss, 4 px"])))
        shape = tuple(pred.D_ii.shape[:2])
    from slam_vs_prior import mast3r_decode_seconds  # the benchmark next to this one

    decode = mast3r_decode_seconds(shape[1], shape[0], "fp32")
    n = len(pairs)
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"faiss {faiss.__version__}, {args.threads} thread(s); {shape[1]}x{shape[0]}; "
          f"{n} pairs; MASt3R decode {decode:.2f} s (fp32, CPU time); simulated prior "
          f"decode {simulated_decode / n:.2f} s per pair")
    print(f"{'method':<18} | {'s per pair':>10} | {'/ decode':>8} | matches per pair")
    for name in methods:
        print(f"{name:<18} | {seconds[name] / n:>10.2f} | {seconds[name] / n / decode:>8.2f} "
              f"| {' '.join(map(str, matches[name]))}")
    if same:
        print(f"faiss, 4 px gives the brute force's matches: {sum(same)} of {len(same)} pairs")


if __name__ == "__main__":
    main()
