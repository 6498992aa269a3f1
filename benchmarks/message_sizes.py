"""What the messages weigh and what the codec costs, on this machine (a script, not a test).

Part 0, bytes per keyframe on the wire per message part, for each ``--agent`` (its
resolution at ``input.long_side``): an agent front-end with the simulated prior runs over the
agent's first ``--frames`` frames; every keyframe message after the first (which has no
sequential edge and no refresh) is measured with :func:`como3r.transport.codec.part_sizes`,
exact (pipes on one machine) and lossy (zenoh, across machines), and averaged. Then the same
messages with MASt3R's shapes: the encoding replaced by the full-size network's (ViT-L, the
released checkpoint's configuration, seeded random weights: sizes, not values, are what
they say; trained tokens may compress differently), the retrieval features by a released-
size retrieval head's (300 descriptors of 1024 dimensions, seeded random weights) as an
agent with a codebook sends them since packet version 5: their ASMK aggregate
(:class:`~como3r.prior.retrieval.Aggregated`) in a codebook of the released size (65,536
seeded random unit centroids), of 300 seeded random unit descriptors in place of the
head's (which with random weights fall on a few words): independent descriptors share few
of their 5 nearest words, an upper bound; trained descriptors share more. Before, the descriptors in 8 bits and
300 x ``multiple_assignment_query`` random word ids. ``--prior-model`` and ``--set
KEY=VALUE`` configure the simulated front-end (the prior's error model; e.g.
``tracking.self_calibration=false``, the paper's uncalibrated mode, whose pointmaps keep
the prior's own rays). Pointmaps, confidences, colours and
matches are the simulated front-end's (MASt3R's have the same shapes and dtypes). The
agent's final message (``AgentFinished``) is measured once per run. No message carries
thumbnails. Then the blobs the session store writes as each keyframe arrives.

Measured (12-frame synthetic sequences, 11 keyframe messages each; kB per keyframe; exact:
pipes, lossy: across machines, with float16 encoder tokens and retrieval features)::

    part                   MASt3R 512x384     simulated 512x384   MASt3R 512x288
                           exact    lossy     exact    lossy      exact    lossy
    tokens                 2495.1   1253.9        -        -      1885.7    957.7
    encoding_rest             1.1      1.1   13626.4  13626.4        0.8      0.8
    pointmap               1758.8    644.1    1758.8    644.1     1323.2    485.2
    confidences             631.1    307.4     631.1    307.4      474.3    228.2
    colours                 399.9    399.9     399.9    399.9      305.2    305.2
    retrieval_descriptors   979.2    508.1     137.5     71.0      979.6    507.6
    retrieval_words           3.1      3.1       1.4      1.4        3.1      3.1
    sequential_matches     1534.9    927.9    1534.9    927.9     1141.7    679.0
    previous_refresh       2380.7    948.2    2380.7    948.2     1792.2    712.2
    other + framing           0.9      0.9       1.0      1.0        0.9      0.9
    total                 10184.7   4994.5   20471.7  16927.3     7906.6   3879.8

(with float32 tokens and retrieval features across machines: total 6706.9 at 512x384,
5279.9 at 512x288.) Without the tokens, as agents send keyframes to a coordinator that
encodes their colours again (``AgentTask.send_encoding``; MASt3R): 7688.5 exact, 3739.5
lossy at 512x384, tokens 0; the store then writes no encoding (5297.7 kB per keyframe at
512x384). The coordinator's price, one encoder run per keyframe a verification decodes
(bounded cache ``session.encoding_cache``), is printed as ``coordinator's re-encode`` with
whether its tokens are bit-identical to the agent's.
The agent's final message: 2396.8 kB exact, 958.4 lossy at 512x384.
Since the compact codings across machines (``transport/codec_compact.py``),
the same sequence at 512x384, lossy, kB per keyframe (exact unchanged)::

    part                   MASt3R   simulated     before (MASt3R lossy)
    tokens                 1253.9        -       1253.9
    pointmap                201.3     201.3       644.1
    confidences             145.0     145.0       307.4
    colours                 194.0     194.0       399.9
    retrieval_descriptors   284.3      38.8       508.1
    sequential_matches      299.4     299.4       927.9
    previous_refresh        344.1     344.1       948.2
    total                  2726.8   14851.3      4994.5
    total less tokens      1472.9         -       3740.6

(the agent's final message: 355.6 kB lossy, 958.4 before. Encode and decode took 0.65 and
0.3 s per MASt3R-shaped message on a machine loaded 15-20 times over its 2 cores: not a
speed measurement. Merged ATE of the demo scene, single process, every keyframe and
refresh through the lossy codec: 7.8796 mm against 7.8794 mm exact.) Before the compact
codings, the agent's final message: 2396.8 kB exact, 958.4 lossy at 512x384.
Session store, blobs written as a keyframe arrives (MASt3R 512x384 / simulated 512x384 /
MASt3R 512x288): colours 400 / 400 / 305, encoding 2493 / 13444 / 1885, pointmaps
2389 / 2389 / 1797, retrieval 979 / 136 / 979, edges 1530 / 1530 / 1139, total 7791 /
17898 / 6105.
Since the store keeps the received keyframe in those codings (format version 5,
``como3r.store.coded``; the packet as the coordinator's ingest gives it), at 512x384
(MASt3R / MASt3R no tokens / simulated): colours 194, encoding 1218 / 0 / 13444 (the
tokens float16-rounded, stored exact), pointmaps 287, retrieval 284 / 284 / 39, edges 261,
total 2244 / 1026 / 14224 (before: 7790 / 5298 / 17899).
With coarser steps where the receiver reads a weight (confidences and match ``q`` in
``2^-2`` log steps, within 9.1 %; a point's range in ``2^-9`` log steps, within 7.8e-4 of
it), the same sequence at 512x384, lossy, kB per keyframe (MASt3R no tokens; the
retrieval coding is unchanged)::

    part                   before    after
    pointmap                201.5    177.5
    confidences             145.1    109.0
    colours                 194.0    194.0
    retrieval_descriptors   284.2    284.2
    retrieval_words           3.1      3.1
    sequential_matches      299.4    260.8
    previous_refresh        344.3    285.2
    total less tokens      1472.1   ~1314 (sum of the parts with other and framing)

(measured with ``--parts-only`` before; after, the parts of the same simulated front-end's
messages through :func:`~como3r.transport.keyframe_bytes.wire_parts`, which are the
MASt3R-shaped column's parts but the retrieval features'. Merged ATE of
``tests/transport/test_lossy_run.py``'s scene, lossy against exact: +0.035 %, -0.059 %
before.)
With the directions against a fitted pinhole's rays, ranges in ``2^-8`` log steps,
confidences in whole powers of two, match ``q`` in ``2^-1`` steps, paired match steps, WebP
method 3 and Zstandard level 6 on the planes (``transport/codec_compact.py``,
``codec_planes.py``), lossy, kB per keyframe, MASt3R shapes without tokens::

    part                   512x384 before  after   512x288 before  after
    pointmap                        177.3  104.3            137.1   79.4
    confidences                     109.0   53.9             82.4   40.8
    colours                         194.0  169.0            147.6  128.9
    retrieval_descriptors           284.2  284.2            282.8  282.8
    retrieval_words                   3.1    3.1              3.1    3.1
    sequential_matches              260.8  223.8            192.7  165.2
    previous_refresh                285.2  156.3            218.2  119.6
    total                          1314.3  995.3           1064.6  820.5

(simulated, lossy: 14694.0 -> 14374.9 at 512x384, 10899.3 -> 10655.3 at 512x288; the
agent's final message 292.0 -> 167.9 kB at 512x384, 228.3 -> 130.9 at 512x288. Merged ATE
of ``tests/transport/test_lossy_run.py``'s scene lossy against exact: +0.018 %.)
With the retrieval as its ASMK aggregate (packet version 5; across machines the build half
against the query half), lossy, kB per keyframe, MASt3R shapes without tokens at 512x384,
the front-end under each ``--prior-model`` (default self-calibration / ``--set
tracking.self_calibration=false``; the parts but the retrieval from ``--simulated-only``)::

    part                   realistic     v2   realistic uncal.   v2 uncal.
    pointmap                   104.3  104.2            164.2       164.3
    confidences                 53.9   54.2             53.9        54.2
    colours                    169.0  173.3            169.0       173.3
    retrieval before           287.1  287.1            287.1       287.1
    retrieval after            192.2  192.2            192.2       192.2
    sequential_matches         223.8  258.2            211.0       213.1
    previous_refresh           156.3  158.1            217.2       218.3
    total before               994.9 1035.7           1103.0      1110.9
    total after                900.1  940.8           1008.1      1016.0

(retrieval before: 8-bit descriptors 284.0 and words 3.1; after: 1483 query and 299 build
words of 300 independent descriptors, 230.3 kB with both halves whole; the realistic total
measured whole, the others summed. The store as a keyframe arrives, MASt3R no tokens:
838.0 -> 746.3 kB, retrieval 284.0 -> 192.3.) Directions in ``2^-12`` octahedral steps
(``codec_compact.OCT_BITS``, 14 before), uncalibrated: pointmap 153.0 and 153.2, refresh
206.1 and 207.2, total after 986.0 and 993.9 (realistic and v2).
``--skip-reencode`` leaves the coordinator's re-encode cost out (half the run);
``--simulated-only`` measures the simulated front-end's messages alone (no network).

Part 1, payloads at 512x384 (the default ``input.long_side``): the arrays of a simulated
encoding and of a decoded pair (as the simulated prior makes them from a synthetic view),
and MASt3R's encoder tokens (the full-size ViT-L network of the released checkpoint's
configuration with seeded random weights: the released weights are not needed to know the
tokens' size; their compressibility with trained weights may differ). For each, its raw
bytes and the ratio and speed (MB/s compress / decompress) of zlib level 1, Zstandard
levels 1 and 3, and LZ4, on the raw bytes and on byte planes (every element's first byte,
then every second byte, ...), which is what ``transport/codec.py`` sends.

Part 2, the codec against msgspec (typed msgpack structs validated at decode), if
installed: microseconds to encode and decode a small message (a pose update of 50
keyframes, a frame-done note) and a large one (MASt3R encoder tokens in a registration
reply), our codec (validation, compression) against a msgspec Struct mirror of the same
fields (arrays as raw bytes plus dtype and shape, no compression).

    como3r synth --out /tmp/s384 --agents 1 --frames 12 --width 640 --height 480
    como3r synth --out /tmp/s288 --agents 1 --frames 12 --width 640 --height 360
    python benchmarks/message_sizes.py --agent /tmp/s384/agent_0 --agent /tmp/s288/agent_0

(``--parts-only``: part 0 alone, 5-6 minutes on one shared core, mostly the full-size
network's construction and encoder.)
"""

import argparse
import dataclasses
import platform
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lz4.frame
import numpy as np
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view, upsampling
from como3r.decentralized.messages import EncodingReply
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import PoseUpdate
from como3r.prior.base import view_from_colors
from como3r.prior.mast3r import MASt3REncoding, MASt3RPrior
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, parse_model_string
from como3r.prior.mast3r.model import MASt3RNetwork
from como3r.prior.mast3r.retrieval import DEFAULT_NFEAT, RetrievalHead
from como3r.prior.mast3r.testing import seeded_network
from como3r.prior.retrieval import Aggregated, RetrievalDatabase
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime.ingest import received
from como3r.runtime.pipeline import PriorSpec, build_prior, load_frame
from como3r.runtime.results import final_report
from como3r.store.blobs import pack_object
from como3r.store.coded import pack_colours, pack_matches, pack_pointmap, pack_retrieval
from como3r.transport import codec
from como3r.transport.codec_arrays import zstd
from como3r.transport.keyframe_bytes import PARTS, wire_parts
from como3r.transport.messages import FrameDone, KeyframeMessage, PoseUpdateMessage

COMPRESSORS: dict[str, tuple[Callable[[bytes], bytes], Callable[[bytes], bytes]]] = {
    "zlib-1": (lambda b: zlib.compress(b, 1), zlib.decompress),
    "zstd-1": (lambda b: zstd.compress(b, level=1), zstd.decompress),
    "zstd-3": (lambda b: zstd.compress(b, level=3), zstd.decompress),
    "lz4": (lz4.frame.compress, lz4.frame.decompress),
}


def _planes(raw: bytes, itemsize: int) -> bytes:
    if itemsize == 1:
        return raw
    return np.frombuffer(raw, np.uint8).reshape(-1, itemsize).T.tobytes()


def _keyframe_messages(
    agent_path: Path, frames: int, config: Config
) -> tuple[list[KeyframeMessage], list[Any], Any, tuple[int, int]]:
    """The simulated front-end's keyframe messages over the first ``frames`` frames (the
    first keyframe's left out), the views they were made from, the agent's final message
    and the network resolution ``(H, W)``."""
    agent = open_agent(agent_path)
    prior, codebook = build_prior(PriorSpec("simulated"), config, {0: agent})
    frontend = AgentFrontend(
        prior, config, 0, codebook, upsampling(agent.image_size, config.input.long_side)
    )
    messages, views, seen = [], [], {}
    for index in range(min(frames, agent.num_frames)):
        view, timestamp, colors = load_frame(agent, 0, index, config.input.long_side, False)
        seen[index] = view
        frontend.process(view, timestamp, colors)
        for packet in frontend.drain_new_keyframes():
            if packet.kf_id > 0:
                previous = frontend.keyframes[packet.kf_id - 1].T_WC
                # the simulated encoding as an agent sends it: the ground-truth record it is
                # made from again (Encoding.portable, runtime/agent_worker.py)
                sent = dataclasses.replace(packet, encoding=packet.encoding.portable())
                messages.append(KeyframeMessage(sent, 0, previous))
                # the keyframe's own view: a self-calibrating agent hands its first
                # keyframes out at a later frame
                views.append(seen[packet.frame_index])
    if not messages:
        raise SystemExit(f"{agent_path}: fewer than 2 keyframes in {frames} frames")
    shape = tuple(messages[0].packet.colors.shape[:2])
    return messages, views, final_report(frontend, 1.0, 0), shape


def _released_size_database(config: Config, dim: int) -> RetrievalDatabase:
    """An ASMK database of the released codebook's size (``retrieval.codebook_size``
    seeded random unit centroids of ``dim``): what an agent aggregates its retrieval in."""
    generator = np.random.default_rng(0)
    centroids = generator.standard_normal((config.retrieval.codebook_size, dim), np.float32)
    centroids /= np.linalg.norm(centroids, axis=1, keepdims=True)
    return RetrievalDatabase(centroids, config.retrieval)


def _mast3r_shaped(
    message: KeyframeMessage,
    view: Any,
    network: MASt3RNetwork,
    head: RetrievalHead,
    database: RetrievalDatabase,
) -> KeyframeMessage:
    """``message`` with MASt3R's encoding and its retrieval as an agent with a codebook
    sends it (module docstring)."""
    encoding = MASt3RPrior(network).encode(view)
    descriptors, _ = head.features(encoding.tokens)
    packet = dataclasses.replace(
        message.packet,
        encoding=encoding,
        retrieval=_aggregated(descriptors.shape[0], message.packet.kf_id, database),
        retrieval_words=None,
        codebook_id=None,
    )
    return dataclasses.replace(message, packet=packet)


def _aggregated(count: int, seed: int, database: RetrievalDatabase) -> Aggregated:
    """The aggregate of ``count`` seeded random unit descriptors: an upper bound of what an
    agent sends (a random head's descriptors of one image fall on a few words: 3.6 kB;
    independent ones on about ``count`` x ``multiple_assignment_query`` + ``count``)."""
    generator = np.random.default_rng(seed)
    descriptors = generator.standard_normal((count, database.dim), np.float32)
    descriptors /= np.linalg.norm(descriptors, axis=1, keepdims=True)
    return database.aggregate(descriptors)


def _mean_parts(messages: list[Any], lossy: bool) -> dict[str, float]:
    """Mean bytes per part of ``messages`` (:func:`wire_parts`), ``framing`` and ``total``,
    and the milliseconds of one encode and one decode (``encode_ms``, ``decode_ms``)."""
    rows = []
    for message in messages:
        parts: dict[str, float] = dict(wire_parts(message, lossy=lossy))
        start = time.perf_counter()
        data = codec.encode(message, lossy=lossy)
        middle = time.perf_counter()
        codec.decode(data)
        parts["encode_ms"] = (middle - start) * 1e3
        parts["decode_ms"] = (time.perf_counter() - middle) * 1e3
        total = len(data)
        parts["framing"] = total - sum(v for k, v in parts.items() if not k.endswith("_ms"))
        parts["total"] = total
        rows.append(parts)
    return {name: sum(r[name] for r in rows) / len(rows) for name in rows[0]}


def _stored_parts(messages: list[KeyframeMessage]) -> dict[str, float]:
    """Mean bytes per keyframe of the blobs the session store writes as a keyframe arrives
    (:mod:`como3r.store.writer`: colours, encoding, pointmap and confidence, retrieval
    features, the sequential edge's matches), rewrites of later refreshes left out: the
    packet as the coordinator receives it (:func:`como3r.runtime.ingest.received`), its
    arrays in the store's codings (:mod:`como3r.store.coded`)."""
    rows = []
    for message in messages:
        packet = received(message.packet)
        edge = packet.sequential_ij, packet.sequential_ji
        width = int(packet.X_hat.shape[1])
        rows.append(
            {
                "colours": len(pack_colours(packet.colors)),
                # not kept where the coordinator encodes the colours again
                "encoding": 0 if packet.encoding is None else len(pack_object(packet.encoding)),
                "pointmaps": sum(len(pack_pointmap(a)[0]) for a in (packet.X_hat, packet.C_hat)),
                "retrieval": len(pack_retrieval(packet.retrieval)) if packet.retrieval else 0,
                "edges": 0 if None in edge else len(pack_matches(*edge, width)),  # type: ignore[arg-type]
            }
        )
    mean = {name: sum(r[name] for r in rows) / len(rows) for name in rows[0]}
    mean["total"] = sum(mean.values())
    return mean


def _without_encoding(message: KeyframeMessage) -> KeyframeMessage:
    """``message`` as an agent sends it to a coordinator that encodes the colours again."""
    return dataclasses.replace(message, packet=dataclasses.replace(message.packet, encoding=None))


def _reencode_cost(messages: list[KeyframeMessage], network: MASt3RNetwork, size: str) -> None:
    """What the coordinator pays for tokens not sent: one encoder run per keyframe it
    verifies with (:mod:`como3r.coordination.encodings`), timed here on this machine's
    threads, and whether the tokens are bit-identical to the agent's."""
    prior, seconds, identical = MASt3RPrior(network), [], True
    for message in messages:
        packet = message.packet
        start = time.perf_counter()
        again = prior.encode(view_from_colors(packet.colors, packet.agent, packet.frame_index))
        seconds.append(time.perf_counter() - start)
        identical &= torch.equal(again.tokens, packet.encoding.tokens)
    print(
        f"coordinator's re-encode at {size}: {np.mean(seconds):.2f} s per keyframe "
        f"({torch.get_num_threads()} threads, {platform.processor() or platform.machine()}); "
        f"tokens bit-identical to the agent's: {identical}"
    )


def part0(
    agent_paths: list[Path],
    frames: int,
    reencode: bool = True,
    config: Config | None = None,
    mast3r: bool = True,
) -> None:
    """The parts (module docstring); without ``mast3r`` the simulated front-end's messages
    only (their pointmaps, confidences, colours and matches are the MASt3R-shaped ones')."""
    config = Config() if config is None else config
    if mast3r:
        network = seeded_network(parse_model_string(RELEASED_MODEL_STRING), 0).eval()
        torch.manual_seed(0)
        head = RetrievalHead(
            network.config.enc_embed_dim, hdims=(1024,), nfeat=DEFAULT_NFEAT
        ).eval()
        database = _released_size_database(config, head.dim)
    columns, finals, stored = {}, {}, {}
    for path in agent_paths:
        messages, views, final, (height, width) = _keyframe_messages(path, frames, config)
        size = f"{width}x{height}"
        batches = [("simulated", messages)]
        if mast3r:
            shaped = [
                _mast3r_shaped(m, v, network, head, database) for m, v in zip(messages, views)
            ]
            # as sent to a coordinator that encodes the colours again (AgentTask.send_encoding)
            untokened = [_without_encoding(m) for m in shaped]
            if reencode:
                _reencode_cost(shaped, network, size)
            batches[:0] = [("MASt3R", shaped), ("MASt3R no tokens", untokened)]
            stored[f"MASt3R {size}"] = _stored_parts(shaped)
            stored[f"MASt3R no tokens {size}"] = _stored_parts(untokened)
        for prior, batch in batches:
            for lossy in (False, True):
                label = f"{prior} {size} {'lossy' if lossy else 'exact'}"
                columns[label] = _mean_parts(batch, lossy)
        finals[size] = {lossy: len(codec.encode(final, lossy=lossy)) for lossy in (False, True)}
        stored[f"simulated {size}"] = _stored_parts(messages)
        print(f"{path}: {len(messages)} keyframe messages measured ({size})")
    print("\nbytes per keyframe message per part [kB] (exact: pipes; lossy: zenoh)")
    print(" | ".join(["part", *columns]))
    for name in [*PARTS, "other", "framing", "total"]:
        print(" | ".join([name, *(f"{c[name] / 1e3:.1f}" for c in columns.values())]))
    for name in ("encode_ms", "decode_ms"):  # milliseconds, not kB
        print(" | ".join([name, *(f"{c[name]:.0f}" for c in columns.values())]))
    print("\nsession store: bytes per keyframe written as it arrives [kB]")
    print(" | ".join(["part", *stored]))
    for name in next(iter(stored.values())):
        print(" | ".join([name, *(f"{c[name] / 1e3:.1f}" for c in stored.values())]))
    for size, nbytes in finals.items():
        print(
            f"agent's final message at {size}: {nbytes[False] / 1e3:.1f} kB exact, "
            f"{nbytes[True] / 1e3:.1f} kB lossy"
        )


def _payloads(agent_path: Path) -> dict[str, np.ndarray]:
    """Named arrays of the three payload kinds (module docstring)."""
    config = Config()
    agent = open_agent(agent_path)
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    views = [make_view(agent.load_frame(i), 0, config.input.long_side, None) for i in (0, 1)]
    encodings = [prior.encode(view) for view in views]
    pair = prior.decode(*encodings)
    arrays: dict[str, np.ndarray] = {}
    for name in ("rays", "ranges", "valid", "key_ids", "key_coords", "descriptors"):
        arrays[f"simulated encoding {name}"] = getattr(encodings[0], name).numpy()
    for name in ("X_ii", "C_ii", "D_ii", "Q_ii"):
        arrays[f"decoded pair {name}"] = getattr(pair, name).numpy()
    network = seeded_network(parse_model_string(RELEASED_MODEL_STRING), 0).eval()
    tokens = MASt3RPrior(network).encode(views[0]).tokens
    arrays["MASt3R tokens float32"] = tokens.numpy()
    arrays["MASt3R tokens float16"] = tokens.half().numpy()
    return arrays


def _ratio_row(name: str, array: np.ndarray) -> tuple[str, list[str]]:
    raw = np.ascontiguousarray(array).tobytes()
    cells = []
    for compress, decompress in COMPRESSORS.values():
        for data in (raw, _planes(raw, array.dtype.itemsize)):
            start = time.perf_counter()
            packed = compress(data)
            middle = time.perf_counter()
            decompress(packed)
            end = time.perf_counter()
            cells.append(
                f"{len(packed) / len(raw):.2f} {len(raw) / (middle - start) / 1e6:.0f}/"
                f"{len(raw) / (end - middle) / 1e6:.0f}"
            )
    return f"{name} ({array.dtype}, {len(raw) / 1e6:.2f} MB)", cells


def part1(agent_path: Path) -> dict[str, np.ndarray]:
    arrays = _payloads(agent_path)
    heads = [f"{c} {k}" for c in COMPRESSORS for k in ("raw", "planes")]
    print("ratio MB/s-compress/MB/s-decompress per compressor, raw bytes and byte planes")
    print(" | ".join(["payload", *heads]))
    for name, array in arrays.items():
        label, cells = _ratio_row(name, array)
        print(" | ".join([label, *cells]))
    return arrays


def _microseconds(call: Callable[[], Any], repeat: int) -> float:
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(repeat):
            call()
        best = min(best, (time.perf_counter() - start) / repeat)
    return best * 1e6


def part2(tokens: np.ndarray) -> None:
    try:
        import msgspec
    except ImportError:
        print("\nmsgspec is not installed: part 2 skipped (pip install msgspec)")
        return

    class Array(msgspec.Struct):
        dtype: str
        shape: list[int]
        data: bytes

    class PoseUpdateS(msgspec.Struct):
        agent: int
        kf_ids: Array
        T_WC: Array
        reason: str
        focal: float | None
        seq: int
        version: int

    class FrameDoneS(msgspec.Struct):
        agent: int
        frame_index: int
        timestamp: float
        outcome: str
        seconds: float
        version: int

    class ReplyS(msgspec.Struct):
        sender: int
        recipient: int
        round: int
        time_s: float
        keyframe: int
        tokens: Array
        pos: Array
        version: int

    def array(a: np.ndarray) -> Any:
        return Array(str(a.dtype), list(a.shape), a.tobytes())

    def from_array(a: Any) -> np.ndarray:
        return np.frombuffer(a.data, a.dtype).reshape(a.shape)

    kf_ids, poses = torch.arange(50), torch.randn(50, 8, dtype=torch.float64)
    pos = np.zeros((tokens.shape[0], 2), np.int64)
    ours = {
        "pose update (50 keyframes)": PoseUpdateMessage(PoseUpdate(0, kf_ids, poses, "gauge"), 3),
        "frame done": FrameDone(0, 7, 0.25, "tracked", 0.1),
        "registration reply (MASt3R tokens)": EncodingReply(
            0,
            1,
            2,
            1.5,
            4,
            MASt3REncoding(
                agent=1,
                index=4,
                shape=(384, 512),
                tokens=torch.from_numpy(tokens),
                pos=torch.from_numpy(pos),
                grid=(24, 32),
            ),
        ),
    }
    mirrors = {
        "pose update (50 keyframes)": (
            PoseUpdateS(0, array(kf_ids.numpy()), array(poses.numpy()), "gauge", None, 3, 1),
            PoseUpdateS,
        ),
        "frame done": (FrameDoneS(0, 7, 0.25, "tracked", 0.1, 1), FrameDoneS),
        "registration reply (MASt3R tokens)": (
            ReplyS(0, 1, 2, 1.5, 4, array(tokens), array(pos), 1),
            ReplyS,
        ),
    }
    print("\nmicroseconds to encode + decode (best of 3), and bytes on the wire")
    print("message | como3r codec us | bytes | msgspec struct us | bytes")
    for name, message in ours.items():
        repeat = 20 if "tokens" in name else 2000
        data = codec.encode(message)
        mine = _microseconds(lambda: codec.decode(codec.encode(message)), repeat)
        mirror, kind = mirrors[name]
        decoder = msgspec.msgpack.Decoder(kind)
        packed = msgspec.msgpack.encode(mirror)

        def theirs_once() -> None:
            decoded = decoder.decode(msgspec.msgpack.encode(mirror))
            for value in msgspec.structs.astuple(decoded):
                if isinstance(value, Array):
                    from_array(value)

        theirs = _microseconds(theirs_once, repeat)
        print(f"{name} | {mine:.0f} | {len(data)} | {theirs:.0f} | {len(packed)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--agent",
        type=Path,
        required=True,
        action="append",
        help="an agent folder with depth/ (como3r synth); repeat for more "
        "resolutions (part 1 and 2 use the first)",
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=12,
        help="frames of each agent the front-end runs over (part 0)",
    )
    parser.add_argument("--parts-only", action="store_true", help="part 0 only")
    parser.add_argument(
        "--skip-reencode",
        action="store_true",
        help="leave out the coordinator's re-encode cost (one encoder run per keyframe)",
    )
    parser.add_argument(
        "--simulated-only",
        action="store_true",
        help="part 0 with the simulated front-end's messages only (no MASt3R network: a "
        "minute; pointmaps, confidences, colours and matches are the MASt3R-shaped ones')",
    )
    parser.add_argument(
        "--prior-model",
        choices=("easy", "realistic", "v2"),
        default=None,
        help="simulated_prior.model of the front-end (default: the configuration's)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a configuration override of the front-end (e.g. tracking.self_calibration=false: "
        "the paper's uncalibrated mode, its pointmaps on the prior's own rays); repeatable",
    )
    args = parser.parse_args()
    overrides = list(args.set)
    if args.prior_model is not None:
        overrides.append(f"simulated_prior.model={args.prior_model}")
    config = apply_overrides(Config(), overrides)
    torch.set_num_threads(1)
    print(f"machine: {platform.processor() or platform.machine()}, torch threads 1")
    print(f"simulated_prior.model {config.simulated_prior.model}; overrides {overrides or 'none'}")
    part0(args.agent, args.frames, not args.skip_reencode, config, not args.simulated_only)
    if args.parts_only or args.simulated_only:
        return
    arrays = part1(args.agent[0])
    part2(arrays["MASt3R tokens float32"])


if __name__ == "__main__":
    main()
