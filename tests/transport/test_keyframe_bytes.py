"""Bytes of a keyframe message per part (transport/keyframe_bytes.py)."""

from __future__ import annotations

import numpy as np
import torch

from como3r.frontend.packets import KeyframePacket, PointmapRefresh
from como3r.transport import codec
from como3r.transport.keyframe_bytes import PARTS, PartCounter, part_of, wire_parts
from como3r.transport.messages import KeyframeMessage

from ..keyframe_packets import mast3r_packet

H, W = 24, 32


def _packet(tokens: torch.Tensor) -> KeyframePacket:
    """A keyframe with every part: ``tokens``, a refreshed previous keyframe, retrieval
    words."""
    g = torch.Generator().manual_seed(1)
    previous = PointmapRefresh(0, torch.randn(H, W, 3, generator=g), torch.ones(H, W), 2)
    return mast3r_packet(
        H,
        W,
        tokens,
        previous=previous,
        retrieval_words=np.zeros((5, 3), np.int32),
        codebook_id="c",
    )


def test_field_paths_fall_into_their_parts() -> None:
    assert part_of("packet.encoding.tokens") == "tokens"
    assert part_of("packet.encoding.pos") == "encoding_rest"
    assert part_of("X_hat") == part_of("packet.X_hat") == "pointmap"
    assert part_of("packet.retrieval") == "retrieval_descriptors"
    assert part_of("packet.retrieval_words") == "retrieval_words"
    assert part_of("packet.sequential_ji.idx") == "sequential_matches"
    assert part_of("packet.previous.X_hat") == "previous_refresh"
    assert part_of("packet.T_WC") == part_of("applied_seq") == "other"


def test_wire_parts_add_up_to_the_message_less_its_framing() -> None:
    tokens = torch.randn(12, 16)
    message = KeyframeMessage(_packet(tokens), 2, None)
    for lossy in (False, True):
        parts = wire_parts(message, lossy=lossy)
        assert list(parts) == [*PARTS, "other"]
        total = len(codec.encode(message, lossy=lossy))
        assert 0 < total - sum(parts.values()) < 1000
        # random tokens do not compress: float32 exact, float16 across machines
        assert parts["tokens"] > tokens.numel() * (2 if lossy else 4)
        assert all(parts[name] > 0 for name in PARTS)
    for part in ("pointmap", "tokens", "retrieval_descriptors"):
        assert wire_parts(message, lossy=True)[part] < wire_parts(message)[part]


def test_part_counter_averages_per_keyframe() -> None:
    counter = PartCounter()
    assert counter.per_keyframe() is None
    counter.add({"tokens": 10, "pointmap": 4})
    counter.add({"tokens": 30, "pointmap": 0})
    assert counter.per_keyframe() == {"tokens": 20.0, "pointmap": 2.0}


def test_part_counter_sums_recorded_fields_and_agents_reports() -> None:
    message = KeyframeMessage(_packet(torch.randn(12, 16)), 2, None)
    counter = PartCounter()
    codec.record_parts(message, counter.add_fields)
    codec.encode(message, lossy=True)
    assert counter.keyframes == 1
    assert dict(counter.bytes) == wire_parts(message, lossy=True)
    merged = PartCounter()  # an agent that came back: two processes' reports
    merged.add_totals(counter.bytes, counter.keyframes)
    merged.add_totals({"pointmap": 10}, 1)
    assert merged.keyframes == 2
    assert merged.per_keyframe()["pointmap"] == (counter.bytes["pointmap"] + 10) / 2
