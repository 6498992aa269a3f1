"""Retrieval per keyframe at the released codebook's size, against the map's size (not a test).

MASt3R's retrieval codebook has 65,536 words of d = 1024 and its retrieval head keeps 300
features per keyframe (MAST3R_SPEC.md §8). The simulated prior's codebook is 1,024 words of
smaller features, so runs on it (the dashboard's, ``slam_vs_prior``'s) do not show what a
MASt3R run's retrieval costs. This times :class:`como3r.prior.retrieval.RetrievalDatabase`
at that size on a random codebook (the exact L2 search over every centroid costs the same
for any values), per keyframe as an agent and the coordinator use it (issue 16, item 4:
flat as the map grows):

* ``quantise``: the nearest-centroid search, once per keyframe
  (:meth:`~como3r.prior.retrieval.RetrievalDatabase.quantize`), for the query and the add,
  in the agent (the coordinator takes its words from the keyframe's packet);
* ``query``: the inverted-file search over the stored keyframes and the top-k;
* ``add``: aggregation and indexing of the keyframe;

with databases of ``--sizes`` keyframes. A stored keyframe is a view of one of ``--places``
places (300 features near that place's own centroids, a random 250 of them kept, with
noise), so a word's posting list grows with the map as revisits make it grow. Building
the database with exact searches would take 0.35 s a keyframe, so the stored views reuse
the words of their place's quantised features (their noise rarely moves a nearest word;
the inverted file's cost does not depend on it); every timed keyframe is quantised exactly.
It prints ms per keyframe, the log-log slope of the total against the map's size, and the
total over one full-size MASt3R decode at 512x384 (``--decode-ms``, or measured as
``slam_vs_prior`` does).

    OMP_NUM_THREADS=1 python benchmarks/retrieval_speed.py [--sizes 100 500 2000] \\
        [--decode-ms 4300]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import ba_scaling  # noqa: E402
import slam_vs_prior  # noqa: E402

from como3r.config import RetrievalConfig  # noqa: E402
from como3r.prior.retrieval import Quantized, RetrievalDatabase  # noqa: E402

#: the released codebook (words, d) and the retrieval head's features per keyframe
WORDS, DIM, FEATURES = 65536, 1024, 300
#: features of a place that one view of it keeps
KEPT = 250
STEPS = ("quantise", "query", "add")


def _unit(rows: np.ndarray) -> np.ndarray:
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


class Places:
    """Random places: each ``FEATURES`` unit features near its own random centroids."""

    def __init__(self, codebook: np.ndarray, count: int, rng: np.random.Generator) -> None:
        self.rng = rng
        self.features = [
            _unit(
                codebook[rng.choice(len(codebook), FEATURES, replace=False)]
                + 0.3 / np.sqrt(DIM) * rng.standard_normal((FEATURES, DIM))
            )
            for _ in range(count)
        ]
        self.words: list[np.ndarray] = []

    def view(self, place: int) -> tuple[np.ndarray, np.ndarray]:
        """``(features (KEPT, DIM), the place's kept rows)``: another view of ``place``."""
        rows = np.sort(self.rng.choice(FEATURES, KEPT, replace=False))
        noise = 0.1 / np.sqrt(DIM) * self.rng.standard_normal((KEPT, DIM))
        return _unit(self.features[place][rows] + noise), rows


def _ms(start: float) -> float:
    return 1000.0 * (time.perf_counter() - start)


def time_keyframe(
    database: RetrievalDatabase, features: np.ndarray, agent: int, kf_id: int
) -> dict[str, float]:
    """ms of each of :data:`STEPS` for one new keyframe, as the coordinator handles it."""
    start = time.perf_counter()
    quantized = database.quantize(features)
    ms = {"quantise": _ms(start)}
    start = time.perf_counter()
    database.query(quantized, exclude_agent=agent)
    ms["query"] = _ms(start)
    start = time.perf_counter()
    database.add(agent, kf_id, quantized)
    ms["add"] = _ms(start)
    return ms


def measure(sizes: list[int], places: int, timed: int, seed: int) -> dict[int, dict[str, float]]:
    """Median ms per step of ``timed`` new keyframes at every database size of ``sizes``,
    with as many faiss threads as torch has."""
    import faiss  # the codebook's search (asmk's index)

    faiss.omp_set_num_threads(torch.get_num_threads())
    rng = np.random.default_rng(seed)
    codebook = _unit(rng.standard_normal((WORDS, DIM)))
    database = RetrievalDatabase(codebook, RetrievalConfig())
    scene = Places(codebook, places, rng)
    scene.words = [database.quantize(f).words for f in scene.features]
    results: dict[int, dict[str, float]] = {}
    for size in sorted(sizes):
        while len(database) < size:
            place = len(database) % places
            features, rows = scene.view(place)
            database.add(
                len(database) % 4, len(database), Quantized(features, scene.words[place][rows])
            )
        times = [
            time_keyframe(database, scene.view(k % places)[0], 99, size + k) for k in range(timed)
        ]
        results[size] = {step: float(np.median([t[step] for t in times])) for step in STEPS}
        print(
            f"{size} keyframes: " + ", ".join(f"{s} {results[size][s]:.1f} ms" for s in STEPS),
            flush=True,
        )
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=[100, 500, 2000], help="keyframes in the database"
    )
    parser.add_argument("--places", type=int, default=50)
    parser.add_argument("--timed", type=int, default=5, help="keyframes timed per size")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--decode-ms",
        type=float,
        default=None,
        help="skip the MASt3R timing and use this decode time",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = measure(args.sizes, args.places, args.timed, args.seed)
    decode_ms = (
        args.decode_ms
        if args.decode_ms is not None
        else 1000.0 * slam_vs_prior.mast3r_decode_seconds(512, 384, "auto")
    )
    print(
        f"\ncodebook {WORDS} x {DIM}, {FEATURES} features per keyframe, {args.threads} "
        f"thread(s); one decode {decode_ms:.0f} ms\n"
    )
    print("| keyframes | " + " | ".join(f"{s} ms" for s in STEPS) + " | total ms | / one decode |")
    print("|---" * (len(STEPS) + 3) + "|")
    for size, ms in results.items():
        total = sum(ms.values())
        print(
            f"| {size} | "
            + " | ".join(f"{ms[s]:.1f}" for s in STEPS)
            + f" | {total:.1f} | {total / decode_ms:.3f} |"
        )
    sizes = list(results)
    if len(sizes) > 1:
        totals = [sum(results[n].values()) for n in sizes]
        queries = [results[n]["query"] + results[n]["add"] for n in sizes]
        print(
            f"\nlog-log slope against the map's size: total {ba_scaling.slope(sizes, totals):.2f}, "
            f"query + add {ba_scaling.slope(sizes, queries):.2f}"
        )


if __name__ == "__main__":
    main()
