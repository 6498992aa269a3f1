"""The coordinator's ingest: a keyframe its agent coded (pipes, network) is only decoded;
one handed over in the agent's own arrays (one process) is coded once, to the same values."""

from __future__ import annotations

import dataclasses
import multiprocessing

import numpy as np
import pytest
import torch

from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.runtime import ingest
from como3r.transport import codec
from como3r.transport.messages import FROM_AGENT, KeyframeMessage
from como3r.transport.pipes import Channel

from ..keyframe_packets import mast3r_packet

H, W = 12, 16


def _packet() -> KeyframePacket:
    return mast3r_packet(H, W)


def _same(a: KeyframePacket, b: KeyframePacket) -> None:
    for name in ("X_hat", "C_hat", "T_WC"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.colors, b.colors)
    assert a.retrieval is not None and b.retrieval is not None
    for x, y in zip(a.retrieval, b.retrieval):  # type: ignore[arg-type]
        assert torch.equal(x, y)
    for m, n in ((a.sequential_ij, b.sequential_ij), (a.sequential_ji, b.sequential_ji)):
        assert m is not None and n is not None
        for field in ("idx", "valid", "q"):
            assert torch.equal(getattr(m, field), getattr(n, field)), field
    assert isinstance(a.encoding, MASt3REncoding) and isinstance(b.encoding, MASt3REncoding)
    assert torch.equal(a.encoding.tokens, b.encoding.tokens)


def _no_encode(*args: object, **kwargs: object) -> bytes:
    raise AssertionError("the ingest coded a packet its agent had coded")


def test_a_keyframe_its_agent_coded_on_a_pipe_is_only_decoded(monkeypatch) -> None:
    """An agent process's channel codes as across machines (its encoding exact): the
    coordinator decodes it on arrival and its ingest takes it as it is, the values the
    single-process ingest gives."""
    packet = _packet()
    in_one_process = ingest.received(packet)
    assert not torch.equal(in_one_process.X_hat, packet.X_hat)  # the coding is lossy
    reader, writer = multiprocessing.Pipe(duplex=False)
    agent = Channel(None, writer, max_bytes=2**24, accepts=(), coded=True)
    coordinator = Channel(reader, None, max_bytes=2**24, accepts=FROM_AGENT)
    try:
        agent.send(KeyframeMessage(packet=packet, applied_seq=0, T_WC_previous=None))
        message, seconds = coordinator.receive_timed()
    finally:
        agent.close()
        coordinator.close()
    assert seconds > 0.0
    monkeypatch.setattr(codec, "encode", _no_encode)
    assert ingest.coded(message.packet)
    assert ingest.received(message.packet) is message.packet
    _same(message.packet, in_one_process)
    assert torch.equal(message.packet.encoding.tokens, packet.encoding.tokens)  # exact


def test_the_network_coding_is_not_coded_again(monkeypatch) -> None:
    """What a Zenoh agent sends (all lossy) and what the single-process ingest hands over
    are taken as they are: no packet or refresh is coded twice."""
    packet = _packet()
    refresh = PointmapRefresh(0, packet.X_hat, packet.C_hat, 1)
    over_the_network = codec.decode(codec.encode(packet, lossy=True), expected=KeyframePacket)
    once = ingest.received(refresh)
    monkeypatch.setattr(codec, "encode", _no_encode)
    assert ingest.received(over_the_network) is over_the_network
    assert ingest.received(once) is once
    with pytest.raises(AssertionError, match="coded a packet"):
        ingest.received(_packet())  # the agent's own arrays: coded here


def test_a_changed_or_uncoded_field_is_coded_again() -> None:
    """A decoded pointmap changed in place, or a confidence not decoded, is no longer what
    its sender coded."""
    once = ingest.received(_packet())
    assert ingest.coded(once)
    assert not ingest.coded(dataclasses.replace(once, C_hat=once.C_hat.clone()))
    once.X_hat[0, 0, 2] += 1.0
    assert not ingest.coded(once)
