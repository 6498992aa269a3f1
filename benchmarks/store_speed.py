"""Session store and evaluation kernels: blob compression and voxel grouping (a script, not
a test; issue 14 / 16 speed claims).

Prints three tables of CPU milliseconds (``time.process_time``, one thread, median of
``--repeats``), ratios within one run:

1. one keyframe blob as the session store writes it (a 512x384 float32 pointmap, its
   confidence and int64 match indices): its byte planes compressed and decompressed with
   Zstandard at level 1 with the content checksum (the store's, format version 3) and
   with zlib at level 1 (format version 2), with the compressed size over the raw; and
   the store's whole :func:`~como3r.store.blobs.pack_arrays` / ``unpack_arrays``;
2. the distinct voxels of a cloud and each point's voxel
   (:func:`como3r.evaluation.reconstruction.unique_rows`, one int64 key per cell) against
   ``np.unique(axis=0)``, for a 640x480 ground-truth frame at stride 4 and for 10^6 points;
3. a 512x384 keyframe (the pointmap, confidence and matches of table 1, smooth colours,
   300 x 1024 retrieval features: MASt3R's shapes, no encoding: the coordinator makes
   MASt3R's again from the colours) through the coordinator's ingest
   (:func:`como3r.runtime.ingest.received`: the lossy wire coding's encode and decode),
   and each of its parts as the session store writes it, exact (format version 4) and
   coded (version 5, :mod:`como3r.store.coded`: the coding, and the decode that checks it
   gives the array back), with their sizes.

    python benchmarks/store_speed.py [--repeats 10]

Table 3 as measured (a 2-core machine shared with other work, load 14; the colours are a
synthetic pattern that WebP takes to nothing: ``benchmarks/message_sizes.py`` measures real
ones, 400 kB exact and 194 kB coded)::

    ingest (lossy encode + decode): 85 ms
    part                          exact kB     ms  coded kB     ms  read ms
    colours                          203.1      1       0.3      3        1
    pointmap                        1753.8      3     131.1     58       26
    confidence                       232.2      3      99.1      7        1
    retrieval                       1037.0      3     283.6      2        1
    matches (both directions)        783.3     13     106.4     19        8
"""

from __future__ import annotations

import argparse
import statistics
import time
import zlib
from collections.abc import Callable

import numpy as np
import torch

from como3r.evaluation.reconstruction import unique_rows
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches
from como3r.runtime.ingest import received
from como3r.store import coded
from como3r.store.blobs import ZSTD_OPTIONS, pack_arrays, unpack_arrays
from como3r.transport.codec_arrays import byte_planes, zstd

HEIGHT, WIDTH = 384, 512


def _cpu_ms(work: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.process_time()
        work()
        times.append(1000.0 * (time.process_time() - start))
    return statistics.median(times)


def keyframe_arrays(seed: int = 0) -> list[np.ndarray]:
    """A smooth 512x384 pointmap with range noise, its confidence and match indices."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float32)
    z = 2 + 0.3 * np.sin(u / 40) + 0.2 * np.cos(v / 30) + rng.normal(0, 0.002, (HEIGHT, WIDTH))
    X = np.stack([(u - WIDTH / 2) / 400 * z, (v - HEIGHT / 2) / 400 * z, z], -1)
    C = 1 + rng.gamma(2.0, 1.0, (HEIGHT, WIDTH))
    matches = rng.integers(0, HEIGHT * WIDTH, HEIGHT * WIDTH)
    return [X.astype(np.float32), C.astype(np.float32), matches.astype(np.int64)]


def blob_table(repeats: int) -> None:
    arrays = keyframe_arrays()
    tensors = [torch.from_numpy(a) for a in arrays]
    payload = b"".join(byte_planes(a.tobytes(), a.itemsize) for a in arrays)
    blob = pack_arrays(*tensors)
    assert all(
        np.array_equal(a, b.numpy()) for a, b in zip(arrays, unpack_arrays(blob, "benchmark"))
    )
    zstd_packed = zstd.compress(payload, options=ZSTD_OPTIONS)
    zlib_packed = zlib.compress(payload, 1)
    print(f"1. one keyframe blob ({len(payload) / 2**20:.1f} MB raw), CPU ms, median of {repeats}")
    print(f"{'step':<40} {'pack':>8} {'unpack':>8} {'size / raw':>11}")
    rows = [
        (
            "byte planes, Zstandard 1 + checksum",
            lambda: zstd.compress(payload, options=ZSTD_OPTIONS),
            lambda: zstd.decompress(zstd_packed),
            len(zstd_packed),
        ),
        (
            "byte planes, zlib 1 (format 2)",
            lambda: zlib.compress(payload, 1),
            lambda: zlib.decompress(zlib_packed),
            len(zlib_packed),
        ),
        (
            "the store's whole blob (Zstandard)",
            lambda: pack_arrays(*tensors),
            lambda: unpack_arrays(blob, "benchmark"),
            len(blob),
        ),
    ]
    for name, pack, unpack, size in rows:
        print(
            f"{name:<40} {_cpu_ms(pack, repeats):>8.1f} {_cpu_ms(unpack, repeats):>8.1f} "
            f"{size / len(payload):>11.3f}"
        )


def voxel_table(repeats: int) -> None:
    rng = np.random.default_rng(1)
    print(f"\n2. distinct voxels of a cloud, CPU ms, median of {repeats}")
    print(f"{'points':>9} {'unique_rows':>12} {'np.unique axis 0':>17} {'ratio':>6}")
    for points in (19_200, 1_000_000):
        cells = np.floor(rng.normal(size=(points, 3)) * [3, 1, 5] / 0.05).astype(np.int64)
        ours = _cpu_ms(lambda: unique_rows(cells), repeats)
        numpy = _cpu_ms(lambda: np.unique(cells, axis=0, return_inverse=True), repeats)
        print(f"{points:>9} {ours:>12.1f} {numpy:>17.1f} {numpy / ours:>6.1f}")


def keyframe_packet() -> KeyframePacket:
    """Table 1's arrays as a keyframe packet with MASt3R's shapes (module docstring)."""
    X, C, idx = (torch.from_numpy(a) for a in keyframe_arrays())
    rng = np.random.default_rng(2)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    colours = np.stack([u % 256, v % 256, (u + v) % 256], -1).astype(np.uint8)
    # matches of a smooth flow: each pixel's neighbour a few pixels on, most of them valid
    flow = torch.arange(HEIGHT * WIDTH) + 3 * WIDTH + 2
    valid = (torch.from_numpy(rng.random(HEIGHT * WIDTH)) > 0.2) & (flow < HEIGHT * WIDTH)
    q = torch.from_numpy(1 + rng.gamma(2.0, 1.0, HEIGHT * WIDTH).astype(np.float32))
    matches = DirectedMatches(torch.where(valid, flow, idx % (HEIGHT * WIDTH)), valid, q * valid)
    descriptors = torch.from_numpy(rng.normal(size=(300, 1024)).astype(np.float32))
    return KeyframePacket(
        agent=0,
        kf_id=1,
        frame_index=4,
        timestamp=0.4,
        T_WC=torch.tensor([0, 0, 0, 0, 0, 0, 1, 1], dtype=torch.float32),
        X_hat=X,
        C_hat=C,
        colors=colours,
        encoding=None,
        retrieval=(descriptors, torch.from_numpy(rng.random(300).astype(np.float32))),
        sequential_ij=matches,
        sequential_ji=matches,
        previous=None,
    )


def keyframe_table(repeats: int) -> None:
    packet = keyframe_packet()
    ingest = _cpu_ms(lambda: received(packet), repeats)
    print(f"\n3. a 512x384 keyframe, MASt3R shapes, CPU ms, median of {repeats}")
    print(f"ingest (lossy encode + decode): {ingest:.0f} ms")
    got = received(packet)
    m = got.sequential_ij, got.sequential_ji
    parts: dict[str, tuple[Callable[[], bytes], Callable[[], bytes]]] = {
        "colours": (lambda: pack_arrays(got.colors), lambda: coded.pack_colours(got.colors)),
        "pointmap": (lambda: pack_arrays(got.X_hat), lambda: coded.pack_pointmap(got.X_hat)[0]),
        "confidence": (lambda: pack_arrays(got.C_hat), lambda: coded.pack_pointmap(got.C_hat)[0]),
        "retrieval": (
            lambda: pack_arrays(*got.retrieval),
            lambda: coded.pack_retrieval(got.retrieval),
        ),
        "matches (both directions)": (
            lambda: pack_arrays(*(getattr(d, f) for d in m for f in ("idx", "valid", "q"))),
            lambda: coded.pack_matches(*m, WIDTH),  # type: ignore[misc]
        ),
    }
    print(f"{'part':<28} {'exact kB':>9} {'ms':>6} {'coded kB':>9} {'ms':>6} {'read ms':>8}")
    totals = [0, 0]
    for name, (exact, coding) in parts.items():
        a, b = exact(), coding()
        totals[0] += len(a)
        totals[1] += len(b)
        print(
            f"{name:<28} {len(a) / 1e3:>9.1f} {_cpu_ms(exact, repeats):>6.0f} "
            f"{len(b) / 1e3:>9.1f} {_cpu_ms(coding, repeats):>6.0f} "
            f"{_cpu_ms(lambda: coded.unpack(b, name), repeats):>8.0f}"
        )
    print(f"{'total':<28} {totals[0] / 1e3:>9.1f} {'':>6} {totals[1] / 1e3:>9.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    blob_table(args.repeats)
    voxel_table(args.repeats)
    keyframe_table(args.repeats)


if __name__ == "__main__":
    main()
