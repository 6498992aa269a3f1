"""The pickle-free message codec: bit-exact round trips and strict rejection on decode."""

from __future__ import annotations

import math
import pickle
import re
import typing
from collections.abc import Callable
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import torch

import como3r.transport.messages as messages
from como3r.errors import Como3rError, MessageError
from como3r.frontend.agent import FrontendStats
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PoseUpdate
from como3r.frontend.pairs import DirectedMatches
from como3r.live import FrameEvent
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.prior.retrieval import Aggregated
from como3r.prior.simulated import SimulatedEncoding
from como3r.prior.simulated_record import SimulatedTruthRecord
from como3r.transport import codec, codec_compact, codec_registry, verification_messages
from como3r.transport.codec import decode, encode

H, W = 6, 8


@dataclass(frozen=True)
class Probe:
    """A test-only message carrying any value."""

    value: Any
    version: int = 1


codec_registry.register(Probe, version=1, name="tests.Probe")


@dataclass(frozen=True)
class HalfProbe:
    """A test-only message whose ``value`` travels in half precision."""

    value: Any
    exact: Any = None
    version: int = 1


codec_registry.register(HalfProbe, version=1, name="tests.HalfProbe", half=("value",))


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _matches(seed: int) -> DirectedMatches:
    g = _gen(seed)
    return DirectedMatches(
        idx=torch.randint(0, H * W, (H * W,), generator=g),
        valid=torch.rand(H * W, generator=g) > 0.5,
        q=torch.rand(H * W, generator=g),
    )


def _from_hints(cls: type, seed: int, **given: Any) -> Any:
    """An instance of a dataclass of tensors and scalars, built from its annotations (so the
    sample follows the class as it evolves); tensors cycle through several dtypes."""
    g = _gen(seed)
    makers = [
        lambda: torch.randn(H, W, 3, generator=g),
        lambda: torch.rand(H, W, generator=g) > 0.5,
        lambda: torch.randint(-1, 9, (H, W), generator=g),
        lambda: torch.randn(H, W, 2, 3, dtype=torch.float64, generator=g),
    ]
    scalars = {int: 3, float: 0.0123, bool: True, str: "s"}
    hints = typing.get_type_hints(cls)
    values = {}
    for i, f in enumerate(fields(cls)):
        hint = hints[f.name]
        if f.name in given:
            values[f.name] = given[f.name]
        elif hint is torch.Tensor or typing.get_args(hint) == (torch.Tensor, type(None)):
            values[f.name] = makers[i % len(makers)]()
        elif hint in scalars:
            values[f.name] = scalars[hint]
        elif typing.get_origin(hint) is tuple:
            values[f.name] = (H, W)
        else:
            raise AssertionError(f"no sample value for {cls.__name__}.{f.name}: {hint}")
    return cls(**values)


def _simulated_encoding() -> SimulatedEncoding:
    return _from_hints(SimulatedEncoding, 1, agent=1, index=7, record=None)


def _mast3r_encoding() -> MASt3REncoding:
    return MASt3REncoding(
        agent=0,
        index=3,
        shape=(32, 48),
        tokens=torch.randn(6, 16, generator=_gen(2)),
        pos=torch.arange(12, dtype=torch.int64).reshape(6, 2),
        grid=(2, 3),
    )


def _refresh() -> PointmapRefresh:
    return PointmapRefresh(
        kf_id=2,
        X_hat=torch.randn(H, W, 3, generator=_gen(3)),
        C_hat=1 + torch.rand(H, W, generator=_gen(4)),
        fused_frames=4,
    )


def _packet(encoding: Any = None) -> KeyframePacket:
    g = _gen(5)
    return KeyframePacket(
        agent=1,
        kf_id=3,
        frame_index=12,
        timestamp=0.4,
        T_WC=torch.randn(8, dtype=torch.float64),
        X_hat=torch.randn(H, W, 3, generator=g),
        C_hat=1 + torch.rand(H, W, generator=g),
        colors=np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8),
        encoding=encoding if encoding is not None else _simulated_encoding(),
        retrieval=(torch.randn(5, 16, generator=g), torch.rand(5, generator=g)),
        sequential_ij=_matches(6),
        sequential_ji=_matches(7),
        previous=_refresh(),
        K=torch.tensor([[50.0, 0.0, 4.0], [0.0, 50.0, 3.0], [0.0, 0.0, 1.0]]),
    )


def _pose_update() -> PoseUpdate:
    return PoseUpdate(
        agent=1,
        kf_ids=torch.arange(4),
        T_WC=torch.randn(4, 8, dtype=torch.float64),
        reason="global_ba",
    )


def _finished() -> messages.AgentFinished:
    return messages.AgentFinished(
        agent=1,
        final=_refresh(),
        stats=FrontendStats(frames=5, lost=1, lost_frames=[4]),
        seconds=1.5,
        applied_seq=2,
        frame_indices=np.arange(5, dtype=np.int64),
        timestamps=np.linspace(0, 1, 5),
        anchors=np.array([0, 0, 1, 1, 1], dtype=np.int64),
        T_rel=torch.randn(5, 8, dtype=torch.float64),
        keyframe_frames=np.array([0, 2], dtype=np.int64),
        keyframe_timestamps=np.array([0, 0.5]),
        keyframe_T_WC=torch.randn(2, 8, dtype=torch.float64),
        edges=[messages.EdgeSummary(0, 1, "sequential", 0.75)],
    )


def _aggregated() -> Aggregated:
    """Per-word sign bits of 7 query and 3 build words of a 64-bit descriptor."""
    rng = np.random.default_rng(4)
    return Aggregated(
        "0123456789abcdef" * 2,
        np.array([0, 2, 3, 9, 40, 41, 70000], np.int64),
        rng.integers(0, 2**32, (7, 2), dtype=np.uint32),
        np.array([2, 9, 41], np.int64),
        rng.integers(0, 2**32, (3, 2), dtype=np.uint32),
    )


def _image(encoding: Any, key: tuple[int, int] = (1, 3)) -> verification_messages.KeyframeImage:
    return verification_messages.KeyframeImage(
        agent=key[0],
        kf_id=key[1],
        frame_index=12,
        colors=np.random.default_rng(key[1]).integers(0, 256, (H, W, 3), dtype=np.uint8),
        encoding=encoding,
    )


def _verified_pair() -> verification_messages.VerifiedPair:
    return verification_messages.VerifiedPair(_matches(9), 0.8, _matches(10), 0.75, True)


SAMPLES: dict[str, Callable[[], Any]] = {
    "KeyframePacket": _packet,
    "Aggregated": _aggregated,
    "PointmapRefresh": _refresh,
    "PoseUpdate": _pose_update,
    "DirectedMatches": lambda: _matches(8),
    "FrontendStats": lambda: FrontendStats(
        frames=3, tracked=2, lost=1, local_solve_seconds=0.25, lost_frames=[7]
    ),
    "SimulatedEncoding": _simulated_encoding,
    "SimulatedTruthRecord": lambda: _from_hints(SimulatedTruthRecord, 5, agent=1, index=7),
    "MASt3REncoding": _mast3r_encoding,
    "AgentTask": lambda: messages.AgentTask(
        agent=0,
        input_path="/data/agent_0",
        config={"input": {"long_side": 64}, "seed": 3},
        prior={"name": "simulated", "weights": None, "device": "cpu"},
    ),
    "AgentStarted": lambda: messages.AgentStarted(agent=0, pid=1234, frames=10),
    "KeyframeMessage": lambda: messages.KeyframeMessage(
        packet=_packet(_mast3r_encoding()),
        applied_seq=2,
        T_WC_previous=torch.randn(8, dtype=torch.float64),
    ),
    "FrameDone": lambda: messages.FrameDone(
        agent=1,
        frame_index=4,
        timestamp=0.1333,
        outcome="tracked",
        seconds=0.5,
        keyframes_waiting=1,
    ),
    "FrameEvent": lambda: FrameEvent(
        agent=1,
        frame_index=4,
        timestamp=0.1333,
        state="tracking",
        T_WC=np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 1.1]),
        K=np.eye(3),
        image=np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3),
        wall_time=1.7e9,
    ),
    "AgentFinished": _finished,
    "AgentFailed": lambda: messages.AgentFailed(
        agent=2, error="InputError: bad frame", details="Traceback ...", frame_index=6
    ),
    "PoseUpdateMessage": lambda: messages.PoseUpdateMessage(update=_pose_update(), seq=3),
    "Step": lambda: messages.Step(frame_index=8),
    "Shutdown": lambda: messages.Shutdown(reason="test"),
    "EdgeSummary": lambda: messages.EdgeSummary(i=1, j=2, kind="loop", match_fraction=0.4),
    "KeyframeImage": lambda: _image(_from_hints(SimulatedTruthRecord, 5, agent=1, index=7)),
    "VerificationRequest": lambda: verification_messages.VerificationRequest(
        request=4,
        query=(1, 3),
        candidates=[(0, 2), (1, 0)],
        similarities=[0.03, math.nan],
        images=[_image(None), _image(None, (0, 2)), _image(_mast3r_encoding(), (1, 0))],
    ),
    "VerificationDone": verification_messages.VerificationDone,
    "VerifiedPair": _verified_pair,
    "VerificationReply": lambda: verification_messages.VerificationReply(
        agent=1,
        request=4,
        query=(1, 3),
        pairs=[
            _verified_pair(),
            verification_messages.VerifiedPair(_matches(11), 0.2, None, None, False),
        ],
        decodes=3,
        seconds={"reencode": 0.5, "prior_decode": 0.25, "verification": 0.125},
        after_stream=True,
    ),
    "tests.Probe": lambda: Probe(value=(None, [1, 2.5], {"a": True})),
    "tests.HalfProbe": lambda: HalfProbe(value=[1.5], exact=torch.ones(2)),
}


def assert_identical(a: Any, b: Any, path: str = "") -> None:
    """Same types, same structure, bit-identical arrays and floats."""
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if isinstance(a, torch.Tensor):
        assert (a.dtype, a.shape, a.device) == (b.dtype, b.shape, torch.device("cpu")), path
        raw = (lambda t: t.view(torch.int16)) if a.dtype == torch.bfloat16 else (lambda t: t)
        assert raw(a.contiguous()).numpy().tobytes() == raw(b).numpy().tobytes(), path
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), path
        assert a.tobytes() == b.tobytes(), path
    elif is_dataclass(a):
        for f in fields(a):
            assert_identical(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_identical(x, y, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            assert_identical(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, float):
        assert a == b or (math.isnan(a) and math.isnan(b)), path
    else:
        assert a == b, path


def tamper(data: bytes, edit: Callable[[dict], None]) -> bytes:
    """Re-pack an encoded message after editing its wire tree in place."""
    tree = msgpack.unpackb(data, raw=False)
    edit(tree)
    return msgpack.packb(tree, use_bin_type=True)


# ---------------------------------------------------------------------- round trips


def test_every_registered_type_has_a_sample() -> None:
    # decentralized/ registers its own messages and round-trips them in its own tests, as
    # store/ its coded arrays (tests/runtime/test_store_coded.py)
    ours = {
        name
        for name, cls in codec_registry.registered_types().items()
        if not cls.__module__.startswith(("como3r.decentralized", "como3r.store"))
    }
    assert ours == set(SAMPLES)


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_round_trip_is_bit_exact(name: str) -> None:
    message = SAMPLES[name]()
    assert_identical(message, decode(encode(message)))


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_lossy_round_trip_is_bit_exact_but_for_half_precision_fields(name: str) -> None:
    message = SAMPLES[name]()
    assert_identical(codec.as_received(message), decode(encode(message, lossy=True)))


def test_pointmaps_matches_and_retrieval_features_travel_compactly_across_machines() -> None:
    packet = SAMPLES["KeyframePacket"]()
    back = decode(encode(packet, lossy=True))
    for name in ("X_hat", "C_hat"):
        original, received = getattr(packet, name), getattr(back, name)
        assert received.dtype == torch.float32 and not torch.equal(original, received)
    error = (back.X_hat - packet.X_hat).norm(dim=-1) / packet.X_hat.norm(dim=-1)
    assert float(error.max()) <= codec_compact.POINTMAP_RELATIVE_ERROR
    relative = (back.C_hat / packet.C_hat - 1).abs().max()
    assert float(relative) <= codec_compact.CONFIDENCE_RELATIVE_ERROR
    assert_identical(packet.T_WC, back.T_WC)  # poses stay exact
    assert_identical(packet.encoding, back.encoding)  # the simulated prior's encodings too
    assert np.array_equal(packet.colors, back.colors)  # colours are lossless
    for original, received in zip(packet.retrieval, back.retrieval):  # retrieval features
        assert received.dtype == torch.float32 and not torch.equal(original, received)
    valid = packet.sequential_ij.valid
    assert torch.equal(back.sequential_ij.idx[valid], packet.sequential_ij.idx[valid])
    assert not torch.equal(packet.sequential_ij.q, back.sequential_ij.q)


@pytest.mark.parametrize("lossy", [False, True])
def test_part_sizes_add_up_to_the_encoding_and_break_down_nested_messages(lossy: bool) -> None:
    packet = SAMPLES["KeyframePacket"]()
    message = messages.KeyframeMessage(packet, 3, None)
    sizes = codec.part_sizes(message, lossy=lossy)
    total = len(encode(message, lossy=lossy))
    assert "packet.X_hat" in sizes and "packet.previous.C_hat" in sizes
    assert any(key.startswith("packet.encoding.") for key in sizes)
    assert "packet.previous" not in sizes  # a nested message is its fields
    # only field names and the dataclasses' tags, type names and versions lie outside
    assert 0 < total - sum(sizes.values()) < 40 * len(sizes)
    alone = len(
        msgpack.packb(
            msgpack.unpackb(encode(message, lossy=lossy), raw=False)["fields"]["packet"]["fields"][
                "X_hat"
            ],
            use_bin_type=True,
        )
    )
    assert sizes["packet.X_hat"] == alone


def test_part_sizes_are_smaller_on_the_lossy_wire() -> None:
    packet = SAMPLES["KeyframePacket"]()
    sent = codec.part_sizes(packet, lossy=True)
    assert sent["X_hat"] < codec.part_sizes(packet)["X_hat"]  # a coded pointmap
    assert sent["sequential_ij"] < sum(
        size for key, size in codec.part_sizes(packet).items() if key.startswith("sequential_ij")
    )


@pytest.mark.parametrize(
    "dtype",
    [
        torch.float32,
        torch.float64,
        torch.int64,
        torch.bool,
        torch.uint8,
        torch.int32,
        torch.float16,
        torch.bfloat16,
    ],
)
def test_tensor_dtypes_round_trip(dtype: torch.dtype) -> None:
    values = torch.tensor([[0.0, -1.5, 2.25], [math.inf, -0.0, 7.0]])
    tensor = values.to(dtype)
    if dtype.is_floating_point:
        tensor = torch.cat([tensor, torch.tensor([[math.nan, 1e-3, -1e3]], dtype=dtype)])
    message = Probe(value=[tensor, tensor[:, 1:], tensor.T, tensor[0, 0], tensor[:0]])
    assert_identical(message, decode(encode(message)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64, np.bool_, np.uint8, np.int8])
def test_numpy_arrays_round_trip(dtype: type) -> None:
    array = (np.arange(24).reshape(2, 3, 4) % 3).astype(dtype)
    message = Probe(
        value={
            "c": array,
            "strided": array[:, ::2],
            "empty": array[:0],
            "scalar": np.asarray(array[1, 1, 1]),
        }
    )
    back = decode(encode(message)).value
    assert_identical({k: v.copy(order="C") for k, v in message.value.items()}, back)


@pytest.mark.parametrize(
    "dtype",
    [
        torch.float32,
        torch.float64,
        torch.int64,
        torch.bool,
        torch.uint8,
        torch.float16,
        torch.bfloat16,
    ],
)
def test_large_arrays_travel_compressed_and_come_back_bit_exact(dtype: torch.dtype) -> None:
    smooth = torch.linspace(-3, 3, 192 * 96).reshape(192, 96)
    tensor = (smooth > 0) if dtype == torch.bool else (smooth * 40).to(dtype)
    array = torch.randn(64, 96, generator=_gen(3)).to(torch.float32).numpy()  # noisy floats
    message = Probe(value=[tensor, tensor[:, ::3], array])
    data = encode(message)
    wire = msgpack.unpackb(data, raw=False)["fields"]["value"]
    assert all("zstd" in item and "data" not in item for item in wire)
    assert (
        len(data)
        < sum(t.numel() * t.element_size() for t in (tensor, tensor[:, ::3])) + array.nbytes
    )
    assert_identical(message, decode(data))


def _zeros_message(nbytes: int) -> bytes:
    return encode(Probe(np.zeros(nbytes, np.uint8)))


def test_compressed_arrays_may_not_decompress_past_the_budget() -> None:
    data = _zeros_message(10 * 2**20)  # 10 MiB of zeros: a few hundred bytes on the wire
    with pytest.raises(MessageError, match="more than 8 times the message size cap"):
        decode(data, max_bytes=len(data))
    assert decode(data, max_bytes=2 * 2**20).value.nbytes == 10 * 2**20


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda a: a.update(zstd=b"not zstd at all"), "compressed array data is not valid"),
        (lambda a: a.update(shape=[a["shape"][0] + 1]), "does not decompress to the"),
        (lambda a: a.update(shape=[a["shape"][0] - 1]), "does not decompress to the"),
        (lambda a: a.update(data=b""), "has keys"),
        (lambda a: a.update(zstd=a["zstd"] + a["zstd"]), "does not decompress to the"),
    ],
)
def test_tampered_compressed_arrays_are_rejected(edit: Callable[[dict], None], match: str) -> None:
    data = tamper(_zeros_message(8192), lambda tree: edit(tree["fields"]["value"]))
    with pytest.raises(MessageError, match=match):
        decode(data)


def test_mutated_compressed_arrays_never_escape_as_other_errors() -> None:
    rng = np.random.default_rng(1)
    original = encode(Probe(torch.linspace(0, 1, 4096)))
    for _ in range(200):
        data = bytearray(original)
        for pos in rng.integers(0, len(data), size=rng.integers(1, 4)):
            data[pos] = int(rng.integers(256))
        try:
            decode(bytes(data))
        except MessageError:
            pass


def test_half_fields_travel_as_float16_and_come_back_as_float32() -> None:
    tensor = torch.randn(64, 96, generator=_gen(5)) * 30
    array = tensor.numpy() + np.float32(1e4)
    for value in (tensor, array):
        data = encode(HalfProbe(value, exact=value), lossy=True)
        assert_identical(decode(encode(HalfProbe(value))).value, value)  # not lossy: exact
        wire = msgpack.unpackb(data, raw=False)["fields"]
        assert wire["value"]["dtype"] == "float16" and wire["value"]["as"] == "float32"
        assert wire["exact"]["dtype"] == "float32"  # not a half field
        back = decode(data)
        assert type(back.value) is type(value) and back.value.dtype == value.dtype
        assert np.array_equal(
            np.asarray(back.value), np.asarray(value).astype(np.float16).astype(np.float32)
        )
        assert_identical(back.exact, value)


def test_a_half_field_that_is_a_tuple_narrows_its_float32_arrays() -> None:
    value = (
        torch.randn(8, 4, generator=_gen(6)),
        torch.arange(3),
        torch.rand(8, generator=_gen(7)),
    )
    data = encode(HalfProbe(value), lossy=True)
    items = msgpack.unpackb(data, raw=False)["fields"]["value"]["items"]
    assert [item["dtype"] for item in items] == ["float16", "int64", "float16"]
    back = decode(data).value
    assert isinstance(back, tuple) and [v.dtype for v in back] == [v.dtype for v in value]
    assert_identical(back, codec.as_received(HalfProbe(value)).value)
    assert torch.equal(back[1], value[1]) and not torch.equal(back[0], value[0])
    assert_identical(decode(encode(HalfProbe(value))).value, value)  # not lossy: exact


def test_half_fields_that_float16_cannot_hold_travel_in_float32() -> None:
    value = torch.tensor([1.0, 7e4, math.inf, math.nan])  # 7e4 would become inf
    wire = msgpack.unpackb(encode(HalfProbe(value), lossy=True), raw=False)["fields"]["value"]
    assert wire["dtype"] == "float32" and "as" not in wire
    for other in (torch.arange(4), torch.zeros(3, dtype=torch.float64), [1.5]):
        assert_identical(decode(encode(HalfProbe(other), lossy=True)).value, other)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda a: a.update({"as": "float64"}), "cannot travel as 'float64'"),
        (lambda a: a.update(dtype="int16"), "a int16 array cannot travel as 'float32'"),
    ],
)
def test_tampered_widening_is_rejected(edit: Callable[[dict], None], match: str) -> None:
    data = tamper(
        encode(HalfProbe(torch.ones(4)), lossy=True), lambda t: edit(t["fields"]["value"])
    )
    with pytest.raises(MessageError, match=match):
        decode(data)


def test_big_endian_arrays_keep_their_values() -> None:
    array = np.arange(6, dtype=">f8").reshape(2, 3) / 7
    back = decode(encode(Probe(array))).value
    assert back.dtype == np.float64 and np.array_equal(back, array)


def test_nested_containers_none_and_scalars_round_trip() -> None:
    value = (
        None,
        (1, (2.5, "x")),
        [True, False, None],
        {"k": (1,), 3: [b"raw"]},
        -(2**63),
        2**64 - 1,
        1e-300,
        math.inf,
        "ü",
    )
    assert_identical(Probe(value), decode(encode(Probe(value))))


def test_numpy_scalars_encode_as_python_numbers() -> None:
    back = decode(encode(Probe([np.float32(1.5), np.int64(3)]))).value
    assert back == [1.5, 3] and type(back[1]) is int


def test_tensors_come_back_on_cpu_and_detached() -> None:
    tensor = torch.randn(3, requires_grad=True)
    back = decode(encode(Probe(tensor * 2))).value
    assert not back.requires_grad and torch.equal(back, (tensor * 2).detach())


# ---------------------------------------------------------------------- encode errors


@pytest.mark.parametrize(
    "value",
    [
        object(),
        {1.5: "float key"},
        {(1,): "tuple key"},
        torch.zeros(2, dtype=torch.complex64),
        np.array(["a"], dtype=object),
        Path("/tmp"),
        2**70,
        "\udc80",
    ],
)
def test_encoding_unsupported_values_fails(value: Any) -> None:
    with pytest.raises(MessageError):
        encode(Probe(value))


def test_encoding_an_unregistered_dataclass_fails() -> None:
    @dataclass
    class Unregistered:
        x: int = 0

    with pytest.raises(MessageError, match="not a registered message type"):
        encode(Unregistered())
    with pytest.raises(MessageError, match="not a registered message type"):
        encode(Probe(Unregistered()))
    with pytest.raises(MessageError, match="only registered dataclasses"):
        encode({"x": 1})


def test_encoding_over_the_cap_fails() -> None:
    with pytest.raises(MessageError, match="over the cap"):
        encode(Probe(torch.zeros(1000)), max_bytes=1000)


# ---------------------------------------------------------------------- malicious input


def _valid() -> bytes:
    return encode(SAMPLES["PoseUpdateMessage"]())


def test_pickle_bytes_are_rejected() -> None:
    for payload in (
        pickle.dumps(SAMPLES["PoseUpdateMessage"]()),
        pickle.dumps({"x": 1}),
        pickle.dumps(torch.zeros(3)),
    ):
        with pytest.raises(MessageError):
            decode(payload)


def test_garbage_and_truncated_bytes_are_rejected() -> None:
    data = _valid()
    for cut in (0, 1, 7, len(data) // 2, len(data) - 1):
        with pytest.raises(MessageError):
            decode(data[:cut])
    for junk in (
        b"\xc1",
        b"\xff" * 16,
        msgpack.packb([1, 2, 3]),
        msgpack.packb({"#": "tuple"}),
        msgpack.packb("text"),
        data + b"\x00",
    ):
        with pytest.raises(MessageError):
            decode(junk)
    with pytest.raises(MessageError, match="bytes"):
        decode("not bytes")  # type: ignore[arg-type]


def test_random_mutations_never_escape_as_other_errors() -> None:
    """Flip bytes of valid messages: each mutant decodes or raises MessageError, nothing else."""
    rng = np.random.default_rng(0)
    originals = [
        encode(SAMPLES[n]()) for n in ("PoseUpdateMessage", "KeyframeMessage", "AgentFinished")
    ]
    for _ in range(300):
        data = bytearray(originals[rng.integers(len(originals))])
        header = min(len(data), 400)  # mostly structure, not raw array bytes
        for pos in rng.integers(0, header, size=rng.integers(1, 4)):
            data[pos] = int(rng.integers(256))
        try:
            decode(bytes(data))
        except MessageError:
            pass


WIRE_VALUES = [
    None,
    True,
    0,
    -1,
    2**64 - 1,
    1.5,
    math.nan,
    "",
    "object",
    "#",
    b"",
    b"\x00" * 8,
    [],
    [[0]] * 3,
    {},
    {"#": "tuple"},
    {"#": "dict", "items": [["a", 1]]},
    {"#": "tensor", "dtype": "float32", "shape": [2], "data": b"\x00" * 8},
    {"#": "object", "type": "Step", "version": 1, "fields": {"frame_index": 1, "version": 1}},
]


def _wire_slots(tree: Any, out: list) -> list:
    """Every (container, key) of a wire tree."""
    items = tree.items() if isinstance(tree, dict) else enumerate(tree)
    for key, value in list(items):
        out.append((tree, key))
        if isinstance(value, (dict, list)):
            _wire_slots(value, out)
    return out


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_structural_mutations_never_escape_as_other_errors(name: str) -> None:
    """Replace random nodes of a valid wire tree by random wire values: every mutant decodes
    or raises MessageError."""
    rng = np.random.default_rng(1)
    data = encode(SAMPLES[name]())
    for _ in range(40):
        tree = msgpack.unpackb(data, raw=False)
        slots = _wire_slots(tree, [])
        for slot in rng.integers(len(slots), size=rng.integers(1, 4)):
            container, key = slots[slot]
            container[key] = WIRE_VALUES[rng.integers(len(WIRE_VALUES))]
        try:
            decode(msgpack.packb(tree, use_bin_type=True))
        except MessageError:
            pass


def test_oversize_is_rejected_before_parsing() -> None:
    data = _valid()
    with pytest.raises(MessageError, match="exceeds the cap"):
        decode(data, max_bytes=len(data) - 1)
    assert decode(data, max_bytes=len(data)).seq == 3


def _first_array(tree: dict) -> dict:
    return tree["fields"]["update"]["fields"]["T_WC"]


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda t: t.update(type="os.system"), "unknown message type"),
        (lambda t: t.update(type="Probe"), "unknown message type"),
        (lambda t: t.update(version=2), "version 2 is not the supported"),
        (lambda t: t.update(version=True), "version True"),
        (lambda t: t["fields"].update(version=2), r"\.version: 2 is not 1"),
        (lambda t: t["fields"].update(extra=1), "unexpected \\['extra'\\]"),
        (lambda t: t["fields"].pop("seq"), "missing \\['seq'\\]"),
        (lambda t: t["fields"].update(seq="three"), "seq: a str does not match"),
        (lambda t: t["fields"].update(seq=2.0), "seq: a float does not match"),
        (lambda t: t["fields"].update(seq=0), "seq must be >= 1"),
        (lambda t: t["fields"]["update"]["fields"].update(reason=None), "reason: a NoneType"),
        (lambda t: t["fields"]["update"].update(type="Step", version=1), "wrong fields for Step"),
        (lambda t: _first_array(t).update(dtype="object"), "dtype 'object' is not allowed"),
        (lambda t: _first_array(t).update(dtype="<f8"), "is not allowed"),
        (lambda t: _first_array(t).update(shape=[4, 9]), "do not hold a float64 array"),
        (lambda t: _first_array(t).update(shape=[4, -8]), "non-negative"),
        (lambda t: _first_array(t).update(shape=[1] * 9), "at most 8"),
        (lambda t: _first_array(t).update(shape=[0, 2**64 - 1], data=b""), "at most 8"),
        (lambda t: _first_array(t).update(shape=[2**62, 0, 2**62], data=b""), "at most 8"),
        (lambda t: _first_array(t).update(data=b"\x00" * 8), "do not hold"),
        (lambda t: _first_array(t).update(data="text"), "not bytes"),
        (lambda t: _first_array(t).update(extra=1), "has keys"),
        (lambda t: _first_array(t).update({"#": "pickle"}), "unknown wire tag 'pickle'"),
        (
            lambda t: t["fields"]["update"]["fields"].update(T_WC={"plain": "map"}),
            "unknown wire tag",
        ),
        (lambda t: t["fields"]["update"]["fields"].update(T_WC=[1.0] * 8), "a list does not match"),
        (
            lambda t: t["fields"]["update"]["fields"]["T_WC"].update(
                shape=[4, 7], data=b"\x00" * 224
            ),
            r"T_WC has shape \(4, 7\)",
        ),
        (lambda t: t.update(fields=[1, 2]), "are not a map"),
    ],
)
def test_tampered_messages_are_rejected(edit: Callable[[dict], None], match: str) -> None:
    with pytest.raises(MessageError, match=match):
        decode(tamper(_valid(), edit))


def test_bool_arrays_hold_only_zero_and_one() -> None:
    def edit(tree: dict) -> None:
        tree["fields"]["value"]["data"] = b"\x00\x02"

    with pytest.raises(MessageError, match="bool array"):
        decode(tamper(encode(Probe(torch.tensor([True, False]))), edit))


def test_bfloat16_is_allowed_for_tensors_only() -> None:
    def edit(tree: dict) -> None:
        tree["fields"]["value"]["#"] = "ndarray"

    with pytest.raises(MessageError, match="only allowed for tensors"):
        decode(tamper(encode(Probe(torch.zeros(2, dtype=torch.bfloat16))), edit))


def test_dict_wire_form_is_validated() -> None:
    data = encode(Probe({"a": 1}))
    for items in ([["a", 1], ["a", 2]], [["a"]], [[1.5, 1]], "x"):

        def edit(tree: dict, items: Any = items) -> None:
            tree["fields"]["value"]["items"] = items

        with pytest.raises(MessageError):
            decode(tamper(data, edit))


def test_deep_nesting_is_rejected() -> None:
    value: Any = 0
    for _ in range(codec.MAX_DEPTH + 2):
        value = [value]
    tree = {
        "#": "object",
        "type": "tests.Probe",
        "version": 1,
        "fields": {"value": value, "version": 1},
    }
    with pytest.raises(MessageError, match="nested deeper"):
        decode(msgpack.packb(tree))
    with pytest.raises(MessageError, match="nested deeper"):
        encode(Probe(value))


def test_expected_type_is_enforced() -> None:
    with pytest.raises(MessageError, match="expected a Step or Shutdown message"):
        decode(_valid(), expected=(messages.Step, messages.Shutdown))
    assert isinstance(
        decode(_valid(), expected=messages.PoseUpdateMessage), messages.PoseUpdateMessage
    )


def test_message_error_is_a_como3r_error() -> None:
    assert issubclass(MessageError, Como3rError)


def test_registry_rejects_conflicting_names_and_versions() -> None:
    @dataclass(frozen=True)
    class Other:
        version: int = 2

    with pytest.raises(ValueError, match="already registered"):
        codec_registry.register(Other, version=2, name="Step")
    with pytest.raises(TypeError, match="defaults to 2"):
        codec_registry.register(Other, version=1, name="tests.Other")
    with pytest.raises(ValueError, match="no registered message type"):
        codec_registry.add_check("tests.Unknown", lambda obj: None)


# ---------------------------------------------------------------------- no pickle anywhere


SRC = Path(codec.__file__).parents[1]
#: every module of the packages whose data crosses a process or network boundary
CROSSING = sorted(
    str(path.relative_to(SRC))
    for package in ("transport", "store", "runtime")
    for path in (SRC / package).glob("*.py")
)


@pytest.mark.parametrize("module", CROSSING)
def test_runtime_modules_do_not_use_pickle(module: str) -> None:
    source = (SRC / module).read_text()
    assert not re.search(r"^\s*(import|from)\s+(c?pickle|dill|cloudpickle|_pickle)\b", source, re.M)
    assert not re.search(r"\b(pickle|dill)\.(loads?|dumps?)\b|torch\.load\(", source)
    # Connection.send/recv and multiprocessing queues pickle: only raw bytes may cross
    assert not re.search(
        r"\.recv\(|\bQueue\(\)|SimpleQueue|JoinableQueue", source.replace("queue.Queue()", "")
    )


@pytest.mark.parametrize("lossy", [False, True])
def test_a_sender_records_the_part_sizes_of_the_encoding_it_sends(lossy: bool) -> None:
    message = messages.KeyframeMessage(SAMPLES["KeyframePacket"](), 3, None)
    seen: list[dict[str, int]] = []
    codec.record_parts(message, seen.append)
    data = encode(message, lossy=lossy)
    assert seen == [codec.part_sizes(message, lossy=lossy)]
    assert 0 < len(data) - sum(seen[0].values()) < 40 * len(seen[0])
    encode(message, lossy=lossy)  # once: a later encode of the same message is not counted
    encode(messages.KeyframeMessage(SAMPLES["KeyframePacket"](), 3, None))  # nor another's
    assert len(seen) == 1
    too_big = messages.KeyframeMessage(SAMPLES["KeyframePacket"](), 3, None)
    codec.record_parts(too_big, seen.append)
    with pytest.raises(MessageError, match="over the cap"):
        encode(too_big, max_bytes=100)
    assert len(seen) == 1  # a message that never left is not counted
