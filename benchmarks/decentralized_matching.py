"""Seconds per pair of the decentralized registration's descriptor matching vs one decode.

Decodes keyframe pairs of a synthetic scene with the simulated prior at ``--long-side``
(512x384 by default, MASt3R's resolution), matches each pair's descriptors three ways and
prints seconds per pair, matches, and the ratio to one decode of the full-size MASt3R network
(random weights, fp32, :func:`slam_vs_prior.mast3r_decode_seconds`) measured in the same run:

- ``exact``: the former search: queries on the default grid (``match_stride_ratio`` 1/64 of
  the long side: 8 px at 512, as the official code), each neighbour searched over every
  confident pixel of the other view (faiss flat inner-product index, each pixel once);
- ``coarse to fine, 1``: :func:`como3r.decentralized.matching.reciprocal_matches` with one
  coarse candidate (``match_coarse_candidates=1``);
- ``coarse to fine``: the same with the default configuration (3 candidates).

``same j``: of a method's matches whose view-i pixel the exact search matches too, the share
it matches to the same view-j pixel (the round trips of the two searches visit different
view-i pixels, so most matches of each have no counterpart in the other).

Measured with ``OMP_NUM_THREADS=1 nice -n 10 python benchmarks/decentralized_matching.py
--scene /tmp/dscale/bench512/scene_x20`` (1 thread, 2-core x86_64 shared with other jobs at a
load of about 9; all seconds are process CPU time, which such sharing inflates less than wall
time), the default pairs: two true loops and one unrelated pair of the 20x scene of
``decentralized_scale.py``:

    512x384, 3 pairs; MASt3R decode 11.13 s (fp32, 1 thread, CPU time); simulated prior
    decode 0.40 s per pair

    method             | s per pair | / decode | same j | matches per pair
    exact              |      4.764 |    0.428 | 100.0% | 1565 1901 467
    coarse to fine, 1  |      0.078 |    0.007 |  65.0% | 765 1123 179
    coarse to fine     |      0.144 |    0.013 |  82.0% | 1143 1521 254

    --long-side 160 (160x112; MASt3R decode 1.97 s):
    exact              |      0.224 |    0.114 | 100.0% | 806 1123 175
    coarse to fine, 1  |      0.045 |    0.023 |  77.9% | 505 804 102
    coarse to fine     |      0.061 |    0.031 |  91.3% | 655 1021 117

(The decode's CPU time varies with the load: 11.1-13.5 s in runs of the same hour; the
exact search was 0.35-0.43x of it.) The exact search compares each of ~7,400 queries with
~190,000 confident pixels; coarse to fine compares it with the ~3,000 grid pixels and 3
windows of 9 x 9 pixels. Over the 55 pairs that scene's robots register (35 loop candidates,
20 odometry pairs) the matches are 78 % of the exact search's, and the correspondence ratios
(F-Eq. 1) of its 20 true loops stay above R_thr = 0.3 (lowest 0.43, exact 0.56) while the
unrelated pairs' fall (highest 0.38, exact 0.47); ``decentralized_scale.py`` has the loops and
merged ATE that result.

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
import numpy as np
import torch
from torch import Tensor

from como3r.config import Config, InputConfig
from como3r.config_decentralized import RegistrationConfig
from como3r.data.agent import open_agent
from como3r.data.preprocess import make_view
from como3r.decentralized.matching import query_grid, reciprocal_matches
from como3r.prior.base import PairPrediction
from como3r.runtime.pipeline import PriorSpec, build_prior

logger = logging.getLogger(__name__)


class _ExactNearest:
    """Exact nearest neighbours of one view's pixels among every pixel of the other, each
    searched once: the former search.

    Args:
        source: ``(N, d)`` float32 descriptors whose neighbours are asked for.
        target: ``(M, d)`` float32 descriptors searched (M >= 1).
    """

    def __init__(self, source: np.ndarray, target: np.ndarray) -> None:
        self._source = source
        self._index = faiss.IndexFlatIP(target.shape[1])
        self._index.add(target)
        self._nearest = np.full(source.shape[0], -1, dtype=np.int64)

    def __call__(self, rows: np.ndarray) -> np.ndarray:
        """``(Q,)`` int64 target rows nearest to the ``(Q,)`` source ``rows``."""
        missing = np.unique(rows[self._nearest[rows] < 0])
        if missing.size:
            _, found = self._index.search(np.ascontiguousarray(self._source[missing]), 1)
            self._nearest[missing] = found[:, 0]
        return self._nearest[rows]


def exact_matches(pred: PairPrediction, config: RegistrationConfig) -> tuple[Tensor, Tensor]:
    """The former ``reciprocal_matches``: the package's round trips from the same grid,
    every neighbour exact. Returns ``(M,)`` flat pixels of views i and j."""
    H, W, d = pred.D_ii.shape
    q_min = config.min_descriptor_confidence
    pixels_i = torch.nonzero(pred.Q_ii.reshape(-1) > q_min)[:, 0]
    pixels_j = torch.nonzero(pred.Q_ji.reshape(-1) > q_min)[:, 0]
    flat_i = pred.D_ii.reshape(-1, d)[pixels_i].float().contiguous().numpy()
    flat_j = pred.D_ji.reshape(-1, d)[pixels_j].float().contiguous().numpy()
    i_to_j, j_to_i = _ExactNearest(flat_i, flat_j), _ExactNearest(flat_j, flat_i)
    row_of = torch.full((H * W,), -1, dtype=torch.long)
    row_of[pixels_i] = torch.arange(pixels_i.numel())
    query = row_of[query_grid(H, W, config.match_stride_ratio)]
    query = query[query >= 0].numpy()
    found_i, found_j = [], []
    for _ in range(config.match_iterations):
        if query.size == 0:
            break
        in_j = i_to_j(query)
        back = j_to_i(in_j)
        converged = back == query
        found_i.append(query[converged])
        found_j.append(in_j[converged])
        query = np.unique(back[~converged])
    pairs = np.unique(np.stack([np.concatenate(found_i), np.concatenate(found_j)], axis=1), axis=0)
    return pixels_i[torch.from_numpy(pairs[:, 0])], pixels_j[torch.from_numpy(pairs[:, 1])]


def _agreement(
    found: tuple[Tensor, Tensor], exact: tuple[Tensor, Tensor], pixels: int
) -> tuple[int, int]:
    """Matches of ``found`` whose view-i pixel ``exact`` matches too, and those of them that
    ``exact`` matches to the same view-j pixel."""
    common = torch.isin(found[0], exact[0])
    same = torch.isin(found[0] * pixels + found[1], exact[0] * pixels + exact[1])
    return int(common.sum()), int(same.sum())


def _render(folder: Path) -> Path:
    import decentralized_scale  # the benchmark next to this one

    scene = folder / "scene"
    decentralized_scale.render(scene, frames=40, width=160, height=120, seed=0)
    return scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, help="como3r synth scene (default: render one)")
    parser.add_argument("--long-side", type=int, default=Config().input.long_side)
    parser.add_argument(
        "--pairs",
        default="0,17,1,0;0,23,1,0;0,0,1,29",
        help="'agent,frame,agent,frame;...': the pairs decoded",
    )
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    faiss.omp_set_num_threads(args.threads)
    scene = args.scene or _render(Path(tempfile.mkdtemp(prefix="como3r_matching_")))
    config = Config(input=InputConfig(long_side=args.long_side))
    pairs = [tuple(int(v) for v in item.split(",")) for item in args.pairs.split(";")]
    agents = {
        a: open_agent(scene / f"agent_{a}")
        for a in sorted({p[0] for p in pairs} | {p[2] for p in pairs})
    }
    prior = build_prior(PriorSpec("simulated"), config, agents)[0]
    registration = RegistrationConfig()
    methods = {
        "exact": lambda pred: exact_matches(pred, registration),
        "coarse to fine, 1": lambda pred: reciprocal_matches(
            pred.D_ii,
            pred.D_ji,
            pred.Q_ii,
            pred.Q_ji,
            replace(registration, match_coarse_candidates=1),
        ),
        "coarse to fine": lambda pred: reciprocal_matches(
            pred.D_ii, pred.D_ji, pred.Q_ii, pred.Q_ji, registration
        ),
    }
    seconds = {name: 0.0 for name in methods}
    matches: dict[str, list[int]] = {name: [] for name in methods}
    common = {name: 0 for name in methods}
    same = {name: 0 for name in methods}
    simulated_decode = 0.0
    for a, fa, b, fb in pairs:
        views = [
            make_view(agents[agent].load_frame(frame), agent, args.long_side)
            for agent, frame in ((a, fa), (b, fb))
        ]
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
            agreement = _agreement(found[name], found["exact"], pred.D_ii[..., 0].numel())
            common[name] += agreement[0]
            same[name] += agreement[1]
        shape = tuple(pred.D_ii.shape[:2])
    from slam_vs_prior import mast3r_decode_seconds  # the benchmark next to this one

    decode = mast3r_decode_seconds(shape[1], shape[0], "fp32")
    n = len(pairs)
    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"faiss {faiss.__version__}, {args.threads} thread(s); {shape[1]}x{shape[0]}; "
        f"{n} pairs; MASt3R decode {decode:.2f} s (fp32, CPU time); simulated prior "
        f"decode {simulated_decode / n:.2f} s per pair"
    )
    print(
        f"{'method':<18} | {'s per pair':>10} | {'/ decode':>8} | {'same j':>6} | matches per pair"
    )
    for name in methods:
        print(
            f"{name:<18} | {seconds[name] / n:>10.3f} | {seconds[name] / n / decode:>8.3f} "
            f"| {100 * same[name] / max(common[name], 1):>5.1f}% "
            f"| {' '.join(map(str, matches[name]))}"
        )


if __name__ == "__main__":
    main()
