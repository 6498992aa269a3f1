"""What the messages weigh and what the codec costs, on this machine (a script, not a test).

Part 1, payloads at 512x384 (the default ``input.long_side``): the arrays of a simulated
encoding and of a decoded pair (as the simulated prior makes them from a synthetic view),
and MASt3R's encoder tokens (the full-size ViT-L network of the released checkpoint's
configuration with seeded random weights: the released weights are not needed to know the
tokens' size; their compressibility with trained weights may differ). For each, its raw
bytes and the ratio and speed (MB/s compress / decompress) of zlib level 1, Zstandard
levels 1 and 3, and LZ4, on the raw bytes and on byte planes (every element's first byte,
then every second byte, ...), which is what ``runtime/codec.py`` sends.

Part 2, the codec against msgspec (typed msgpack structs validated at decode), if
installed: microseconds to encode and decode a small message (a pose update of 50
keyframes, a frame-done note) and a large one (MASt3R encoder tokens in a registration
reply), our codec (validation, compression) against a msgspec Struct mirror of the same
fields (arrays as raw bytes plus dtype and shape, no compression).

    como3r synth --out /tmp/s640 --agents 1 --frames 4 --width 640 --height 480
    python benchmarks/message_sizes.py --agent /tmp/s640/agent_0
"""


import argparse
import platform
import time
import zlib
from pathlib import Path
from typing import Any, Callable

import lz4.frame
import numpy as np
import torch

from como3r.config import Config
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.preprocess import make_view
from como3r.decentralized.messages import EncodingReply
from como3r.frontend.packets import PoseUpdate
from como3r.prior.mast3r import MASt3REncoding, MASt3RPrior
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, parse_model_string
from como3r.prior.mast3r.testing import seeded_network
from como3r.prior.simulated import SimulatedPrior
from como3r.runtime import codec
from como3r.runtime.codec import zstd
from como3r.runtime.messages import FrameDone, PoseUpdateMessage

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


def _payloads(agent_path: Path) -> dict[str, np.ndarray]:
    """Named arrays of the three payload kinds (module docstring)."""
    config = Config()
    agent = open_agent(agent_path)
    prior = SimulatedPrior(config.simulated_prior, AgentFolderTruth({0: agent},
                                                                    config.input.long_side))
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
            cells.append(f"{len(packed) / len(raw):.2f} {len(raw) / (middle - start) / 1e6:.0f}/"
                         f"{len(raw) / (end - middle) / 1e6:.0f}")
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
        "registration reply (MASt3R tokens)": EncodingReply(0, 1, 2, 1.5, 4, MASt3REncoding(
            agent=1, index=4, shape=(384, 512), tokens=torch.from_numpy(tokens),
            pos=torch.from_numpy(pos), grid=(24, 32))),
    }
    mirrors = {
        "pose update (50 keyframes)": (PoseUpdateS(0, array(kf_ids.numpy()), array(poses.numpy()),
                                                   "gauge", None, 3, 1), PoseUpdateS),
        "frame done": (FrameDoneS(0, 7, 0.25, "tracked", 0.1, 1), FrameDoneS),
        "registration reply (MASt3R tokens)": (ReplyS(0, 1, 2, 1.5, 4, array(tokens), array(pos),
                                                      1), ReplyS),
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
    parser.add_argument("--agent", type=Path, required=True,
                        help="an agent folder with depth/ (como3r synth)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {platform.processor() or platform.machine()}, torch threads 1")
    arrays = part1(args.agent)
    part2(arrays["MASt3R tokens float32"])


if __name__ == "__main__":
    main()
