"""The compact codings of a keyframe's large parts on the lossy wire: each round trip within
its stated tolerance (exact where it is an index or an image), malformed codings rejected,
and the receiver's results unchanged (retrieval hits)."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
import torch

import como3r.transport.messages  # noqa: F401  (registers the message checks)
from como3r.errors import MessageError
from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.frontend.pairs import DirectedMatches
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.transport import codec, codec_compact
from como3r.transport.codec import decode, encode
from como3r.transport.codec_arrays import Budget, zstd
from como3r.transport.codec_compact import (
    CONFIDENCE_RELATIVE_ERROR,
    MATCH_Q_BITS,
    POINTMAP_RELATIVE_ERROR,
    coded_from_wire,
    coded_to_wire,
)
from como3r.transport.codec_planes import pack_ints, pack_steps, unpack_steps

H, W = 48, 64


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _pointmap(seed: int = 0) -> torch.Tensor:
    """A pinhole pointmap of a noisy slanted surface, some points behind the camera."""
    rng = _rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - W / 2) / 40, (v - H / 2) / 40, np.ones_like(u)], -1)
    depth = (2 + 0.02 * u + rng.normal(0, 0.01, u.shape)) * np.exp(rng.normal(0, 0.3))
    X = rays * depth[..., None]
    X[:3, :3] *= -1  # behind the camera: the octahedral map covers every direction
    return torch.from_numpy(X.astype(np.float32))


def _matches(seed: int = 0) -> DirectedMatches:
    rng = _rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    target = np.clip(v + 3 + rng.integers(-1, 2, v.shape), 0, H - 1) * W + np.clip(
        u - 5 + rng.integers(-1, 2, u.shape), 0, W - 1
    )
    valid = rng.random(H * W) > 0.3
    q = (1 + rng.random(H * W) * 30).astype(np.float32)
    return DirectedMatches(
        torch.from_numpy(target.ravel().astype(np.int64)),
        torch.from_numpy(valid),
        torch.from_numpy(q),
    )


def _round_trip(coding: str, value: object, owner: object = None) -> object:
    wire = coded_to_wire(coding, value, owner)
    assert wire is not None
    data = msgpack.packb(wire, use_bin_type=True)
    return coded_from_wire(msgpack.unpackb(data, raw=False), "x", Budget(2**40))


def test_pointmap_moves_no_point_by_more_than_the_stated_fraction_of_its_range() -> None:
    X = _pointmap()
    back = _round_trip("pointmap", X)
    assert isinstance(back, torch.Tensor) and back.dtype == torch.float32
    error = (back - X).norm(dim=-1) / X.norm(dim=-1)
    assert float(error.max()) <= POINTMAP_RELATIVE_ERROR
    assert float(error.max()) > POINTMAP_RELATIVE_ERROR / 10  # a bound, not a vacuous one
    # smaller than float16 xyz on the wire, whose per-coordinate error is about the same
    half = codec._to_wire(X.half(), "x", 0, True)
    assert len(msgpack.packb(coded_to_wire("pointmap", X))) < 0.8 * len(msgpack.packb(half))


def test_pinhole_rays_cost_almost_nothing_and_other_rays_keep_the_bound() -> None:
    X = _pointmap()  # pinhole rays: the directions travel as their codes less the pinhole's
    wire = coded_to_wire("pointmap", X)
    assert wire is not None and wire["pinhole"] is not None
    assert max(len(p["zstd"]) for p in wire["planes"][1:]) < len(wire["planes"][0]["zstd"]) / 4
    # rays scattered about a pinhole's by about 2 degrees; rays behind the camera (no
    # pinhole): the same bound
    rng = _rng(5)
    bent = X * torch.from_numpy(1 + rng.normal(0, 0.03, (H, W, 3)).astype(np.float32))
    behind = X * torch.tensor([1.0, 1.0, -1.0])
    assert coded_to_wire("pointmap", behind)["pinhole"] is None  # type: ignore[index]
    for value in (X, bent, behind):
        back = _round_trip("pointmap", value)
        error = (back - value).norm(dim=-1) / value.norm(dim=-1)
        assert float(error.max()) <= POINTMAP_RELATIVE_ERROR


def test_a_pointmap_coded_before_its_step_was_written_down_reads_at_the_old_step(
    monkeypatch,
) -> None:
    """Session stores of formats 5 and 6 hold pointmaps coded in ``2^-14`` direction steps
    with no ``oct_bits``: they decode at that step, not at today's."""
    X = _pointmap()
    for value in (X, X * torch.tensor([1.0, 1.0, -1.0])):  # with a pinhole fit and without
        with monkeypatch.context() as then:
            then.setattr(codec_compact, "OCT_BITS", codec_compact.LEGACY_OCT_BITS)
            wire = coded_to_wire("pointmap", value)
        assert wire is not None
        del wire["oct_bits"]
        back = coded_from_wire(wire, "x", Budget(2**40))
        error = (back - value).norm(dim=-1) / value.norm(dim=-1)
        assert float(error.max()) <= 1.45e-3  # that coding's bound
    wire = coded_to_wire("pointmap", X)
    wire["oct_bits"] = "twelve"  # type: ignore[index]
    with pytest.raises(MessageError, match="direction step"):
        coded_from_wire(wire, "x", Budget(2**40))


def test_confidence_is_within_its_relative_bound_and_numpy_stays_numpy() -> None:
    C = (1 + np.exp(_rng(1).normal(0, 1.5, (H, W)))).astype(np.float32)
    back = _round_trip("confidence", C)
    assert isinstance(back, np.ndarray) and back.dtype == np.float32
    assert np.abs(back / C - 1).max() <= CONFIDENCE_RELATIVE_ERROR


def test_matches_keep_every_valid_index_exactly() -> None:
    matches = _matches()
    owner = dataclasses.make_dataclass("Owner", ["X_hat"])(torch.zeros(H, W, 3))
    back = _round_trip("matches", matches, owner)
    assert isinstance(back, DirectedMatches)
    valid = matches.valid
    assert torch.equal(back.valid, valid)
    assert torch.equal(back.idx[valid], matches.idx[valid])
    # the receiver never reads an invalid match: it comes back matched to itself with q 0
    assert torch.equal(back.idx[~valid], torch.arange(H * W)[~valid])
    assert not back.q[~valid].any()
    bound = 2 ** (2.0 ** -(MATCH_Q_BITS + 1)) - 1
    assert float((back.q[valid] / matches.q[valid] - 1).abs().max()) <= bound
    # without the row length (no pointmap beside them) the indices are still exact
    alone = _round_trip("matches", matches)
    assert torch.equal(alone.idx[valid], matches.idx[valid])


def test_step_pairs_round_trip_exactly_with_escapes() -> None:
    rng = _rng(6)
    first, second = rng.integers(-3, 4, 500), rng.integers(-3, 4, 500)
    first[::7] = rng.integers(-(2**20), 2**20, len(first[::7]))  # escaped: beyond one byte
    second[3] = -8  # zigzag 15: escaped too
    body = msgpack.unpackb(msgpack.packb(pack_steps(first, second)), raw=False)
    back = unpack_steps(body, 500, "x", Budget(2**20))
    assert np.array_equal(back[0], first) and np.array_equal(back[1], second)
    body["pairs"] = zstd.compress(bytes([226]) * 500)
    with pytest.raises(MessageError, match="beyond"):
        unpack_steps(body, 500, "x", Budget(2**20))


def test_colours_are_lossless() -> None:
    rng = _rng(2)
    image = np.clip(rng.normal(120, 40, (H, W, 3)), 0, 255).astype(np.uint8)
    image[10:20] = 255
    assert np.array_equal(_round_trip("image", image), image)


def test_retrieval_descriptors_in_eight_bits_with_a_scale_per_descriptor() -> None:
    rng = _rng(3)
    descriptors = torch.from_numpy(rng.normal(0, 0.1, (30, 64)).astype(np.float32))
    attention = torch.from_numpy(rng.random(30).astype(np.float32))
    back_d, back_a = _round_trip("retrieval", (descriptors, attention))
    step = descriptors.abs().amax(1, keepdim=True) / 127
    assert bool(((back_d - descriptors).abs() <= step / 2 + 1e-7).all())
    torch.testing.assert_close(back_a, attention, rtol=2**-11, atol=0)


def test_ascending_ids_are_lossless_and_others_travel_as_before() -> None:
    ids = np.array([0, 1, 7, 300, 65535, 70000, 2**30], np.int64)
    for value in (ids, ids[:0], ids[3:4]):
        back = _round_trip("ascending", value)
        assert back.dtype == np.int64 and np.array_equal(back, value)
    for value in (ids[::-1].copy(), ids.astype(np.int32), ids - 1, np.array([2, 2], np.int64)):
        assert coded_to_wire("ascending", value) is None
    wire = coded_to_wire("ascending", ids)
    assert wire is not None
    descending = {**wire, "count": 2, "steps": pack_ints(np.array([5, -1], np.int64))}
    for bad in ({**wire, "count": -1}, {**wire, "count": 3}, descending):
        with pytest.raises(MessageError):
            coded_from_wire(bad, "x", Budget(2**40))


def test_values_a_coding_cannot_hold_travel_as_before() -> None:
    X = _pointmap()
    X[5, 5] = 0.0  # no direction: the whole pointmap travels in float16
    C = torch.rand(H, W)
    C[0, 0] = 0.0
    assert coded_to_wire("pointmap", X) is None and coded_to_wire("confidence", C) is None
    refresh = PointmapRefresh(2, X, C, 3)
    back = decode(encode(refresh, lossy=True))
    torch.testing.assert_close(back.X_hat, X.half().float(), rtol=0, atol=0)
    torch.testing.assert_close(back.C_hat, C.half().float(), rtol=0, atol=0)


def test_a_lossy_packet_uses_every_coding_and_an_exact_one_none() -> None:
    X = _pointmap()
    packet = KeyframePacket(
        agent=0,
        kf_id=1,
        frame_index=3,
        timestamp=0.1,
        T_WC=torch.zeros(8, dtype=torch.float64),
        X_hat=X,
        C_hat=torch.rand(H, W) + 1,
        colors=_rng().integers(0, 256, (H, W, 3), dtype=np.uint8),
        encoding=MASt3REncoding(
            agent=0,
            index=3,
            shape=(32, 48),
            tokens=torch.randn(6, 16),
            pos=torch.arange(12, dtype=torch.int64).reshape(6, 2),
            grid=(2, 3),
        ),
        retrieval=(torch.randn(10, 32), torch.rand(10)),
        sequential_ij=_matches(1),
        sequential_ji=_matches(2),
        previous=PointmapRefresh(0, X, torch.rand(H, W) + 1, 2),
    )
    lossy = msgpack.unpackb(encode(packet, lossy=True), raw=False)["fields"]
    codings = {name: f.get("coding") for name, f in lossy.items() if isinstance(f, dict)}
    assert codings["X_hat"] == "pointmap" and codings["colors"] == "image"
    assert codings["sequential_ij"] == codings["sequential_ji"] == "matches"
    assert codings["retrieval"] == "retrieval" and codings["C_hat"] == "confidence"
    assert lossy["previous"]["fields"]["X_hat"]["coding"] == "pointmap"
    exact = msgpack.unpackb(encode(packet), raw=False)["fields"]
    assert all(field.get("#") != "coded" for field in exact.values() if isinstance(field, dict))
    back = decode(encode(packet, lossy=True))
    assert np.array_equal(back.colors, packet.colors)
    assert torch.equal(back.sequential_ij.valid, packet.sequential_ij.valid)


@pytest.mark.parametrize(
    "change",
    [
        lambda w: w.update(coding="nope"),
        lambda w: w.update(shape=[H, W]),
        lambda w: w["planes"][0].update(zstd=w["planes"][0]["zstd"][:-3]),
        lambda w: w["planes"][1].update(predictor="psychic"),
        lambda w: w["planes"][2].update(width=3),
        lambda w: w.update(extra=1),
        lambda w: w.update(pinhole=[1.0, 0.0, float("nan"), 0.0]),
        lambda w: w.update(pinhole=[1.0, 0.0]),
    ],
)
def test_malformed_pointmap_codings_are_message_errors(change: object) -> None:
    wire = coded_to_wire("pointmap", _pointmap())
    assert wire is not None
    change(wire)  # type: ignore[operator]
    with pytest.raises(MessageError):
        coded_from_wire(wire, "x", Budget(2**40))


def test_malformed_matches_image_and_retrieval_codings_are_message_errors() -> None:
    matches = coded_to_wire("matches", _matches())
    image = coded_to_wire("image", np.zeros((H, W, 3), np.uint8))
    retrieval = coded_to_wire("retrieval", (torch.randn(4, 8), torch.rand(4)))
    assert matches and image and retrieval
    bad = [
        {**matches, "count": H * W + 8},  # the mask holds other than count bits
        {**matches, "width": 7},  # rows that do not tile the pixels
        {**matches, "q_steps": 1},  # not a bool
        {**matches, "steps": {**matches["steps"], "extra": b""}},
        {**image, "shape": [H + 1, W, 3]},  # a size other than the image's
        {**image, "webp": b"RIFF0000WEBPgarbage"},
        {**retrieval, "scale": b"\x00" * 12},
    ]
    for wire in bad:
        with pytest.raises(MessageError):
            coded_from_wire(wire, "x", Budget(2**40))
    with pytest.raises(MessageError, match="decompress"):
        coded_from_wire(image, "x", Budget(10))  # a decompression bomb's budget


def test_retrieval_hits_are_identical_with_eight_bit_descriptors() -> None:
    pytest.importorskip("asmk", reason="the retrieval extra (asmk, faiss) is not installed")
    from como3r.config import RetrievalConfig
    from como3r.prior.codebook import train_codebook
    from como3r.prior.retrieval import Quantized, RetrievalDatabase

    rng = _rng(4)
    places = rng.normal(0, 1, (6, 40, 64)).astype(np.float32)
    views = [
        (agent, kf, places[(kf + agent) % 6] + rng.normal(0, 0.15, (40, 64)).astype(np.float32))
        for agent in (0, 1)
        for kf in range(6)
    ]
    codebook = train_codebook(np.concatenate([v for *_, v in views]), 32, seed=0)
    config = RetrievalConfig()  # the receiver's defaults: hits above min_similarity
    exact, coded = RetrievalDatabase(codebook, config), RetrievalDatabase(codebook, config)
    hits_seen = 0
    for agent, kf, features in views:
        words = exact.quantize(features).words  # the agent's words, from its own features
        attention = np.ones(len(features), np.float32)
        received, _ = _round_trip("retrieval", (torch.from_numpy(features), torch.ones(40)))
        want = exact.query_and_add(agent, kf, Quantized(features, words), attention)
        got = coded.query_and_add(agent, kf, Quantized(received, words), attention)
        assert [(h.agent, h.keyframe) for h in got] == [(h.agent, h.keyframe) for h in want]
        # a few residual sums near zero change sign: similarities move by a few percent
        np.testing.assert_allclose(
            [h.similarity for h in got], [h.similarity for h in want], rtol=0.05
        )
        hits_seen += len(want)
    assert hits_seen >= 6  # every view of agent 1 finds its place in agent 0's


def test_coding_names_are_the_registered_ones() -> None:
    from como3r.transport.codec_registry import REGISTRY

    used = {c for entry in REGISTRY.values() for _, c in entry.coded}
    assert used == set(codec_compact.CODINGS)


def test_inter_matches_keep_their_q_in_finer_steps() -> None:
    """An inter-agent edge's matches (the session store's): every valid index exact and
    ``q`` within 4.4 % (``2^-3`` log2 steps), against 19 % for a sequential edge's."""
    matches = _matches()
    fine, coarse = _round_trip("inter_matches", matches), _round_trip("matches", matches)
    valid = matches.valid
    for back, bits in ((fine, codec_compact.INTER_MATCH_Q_BITS), (coarse, MATCH_Q_BITS)):
        assert torch.equal(back.valid, valid) and torch.equal(back.idx[valid], matches.idx[valid])
        error = (back.q[valid] / matches.q[valid]).log2().abs()
        assert float(error.max()) <= 2.0 ** -(bits + 1) + 1e-6
    wire = coded_to_wire("inter_matches", matches)
    assert wire is not None and wire["q_bits"] == codec_compact.INTER_MATCH_Q_BITS
    for bad in ({**wire, "q_bits": 9}, {k: v for k, v in wire.items() if k != "q_bits"}):
        with pytest.raises(MessageError):
            coded_from_wire(bad, "x", Budget(2**40))


def test_an_aggregate_travels_losslessly_with_its_build_bits_against_the_querys() -> None:
    """A keyframe's ASMK aggregate on the lossy wire: bit for bit, the build words as a mask
    over the query's and only the build bits that differ from the query's sent."""
    from como3r.config import RetrievalConfig
    from como3r.prior.retrieval import Aggregated, RetrievalDatabase

    rng = _rng(7)
    database = RetrievalDatabase(rng.normal(size=(512, 64)).astype(np.float32), RetrievalConfig())
    aggregated = database.aggregate(rng.normal(size=(40, 64)).astype(np.float32))
    back = _round_trip("retrieval", aggregated)
    assert isinstance(back, Aggregated) and back.codebook_id == aggregated.codebook_id
    for name in ("query_words", "query_bits", "build_words", "build_bits"):
        a, b = getattr(aggregated, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    wire = coded_to_wire("retrieval", aggregated)
    assert wire is not None
    same = len(aggregated.build_words) - len(wire["build_bits"]) // (4 * wire["width"])
    assert same > 0  # words whose build bits are the query's travel once
    bad = [
        {**wire, "query_bits": wire["query_bits"][:-4]},
        {**wire, "build_bits": wire["build_bits"] + b"\0\0\0\0"},
        {**wire, "width": 0},
        {**wire, "same": b"garbage"},
    ]
    for body in bad:
        with pytest.raises(MessageError):
            coded_from_wire(body, "x", Budget(2**40))
    outside = dataclasses.replace(aggregated, build_words=aggregated.build_words + 10**6)
    assert coded_to_wire("retrieval", outside) is None  # travels as the object it is
