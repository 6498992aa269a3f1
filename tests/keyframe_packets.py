"""Seeded keyframe packets that tests of the session store, the ingest and the wire build
alike (``from ..keyframe_packets import ...``)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches
from como3r.prior.mast3r.prior import MASt3REncoding


def random_matches(n: int, gen: torch.Generator) -> DirectedMatches:
    """``n`` pixels' matches into ``n`` pixels: random targets, 70 % valid, confidences
    from 0.1."""
    return DirectedMatches(
        torch.randint(n, (n,), generator=gen),
        torch.rand(n, generator=gen) > 0.3,
        0.1 + torch.rand(n, generator=gen),
    )


def random_packet(
    agent: int, kf_id: int, gen: torch.Generator, h: int, w: int, retrieval: bool = False
) -> KeyframePacket:
    """Keyframe ``kf_id`` (frame ``kf_id``, at ``kf_id`` seconds) of ``agent``, ``h x w``
    pixels drawn from ``gen``: points in front of the camera, random colours, no encoding,
    with ``retrieval`` five 8-wide retrieval features, and (but the first keyframe)
    :func:`random_matches` to its predecessor both ways."""
    first = kf_id == 0
    return KeyframePacket(
        agent=agent,
        kf_id=kf_id,
        frame_index=kf_id,
        timestamp=float(kf_id),
        T_WC=torch.rand(8, generator=gen),
        X_hat=torch.rand(h, w, 3, generator=gen) + torch.tensor([0.0, 0.0, 1.0]),
        C_hat=1 + torch.rand(h, w, generator=gen),
        colors=torch.randint(256, (h, w, 3), generator=gen, dtype=torch.uint8).numpy(),
        encoding=None,
        retrieval=(
            (torch.randn(5, 8, generator=gen), torch.rand(5, generator=gen)) if retrieval else None
        ),
        sequential_ij=None if first else random_matches(h * w, gen),
        sequential_ji=None if first else random_matches(h * w, gen),
        previous=None,
    )


def mast3r_packet(
    h: int, w: int, tokens: torch.Tensor | None = None, **fields: Any
) -> KeyframePacket:
    """Agent 0's keyframe 1 (frame 4, at 0.2 s), ``h x w`` pixels, seeded: points in front
    of the camera (the pointmap coding fits them), random colours, MASt3R's encoding of 12
    ``tokens`` (default: float32 values float16 cannot hold, so an exact crossing shows),
    five 16-wide retrieval features, and identity matches with random confidences both
    ways; ``fields`` replace any of the packet's fields."""
    g = torch.Generator().manual_seed(0)
    matches = DirectedMatches(
        torch.arange(h * w), torch.ones(h * w, dtype=torch.bool), torch.rand(h * w, generator=g)
    )
    X_hat = torch.rand(h, w, 3, generator=g) + torch.tensor([-0.5, -0.5, 1.0])
    C_hat = 1 + torch.rand(h, w, generator=g)
    if tokens is None:
        tokens = torch.randn(12, 8, generator=g) / 3
    packet = KeyframePacket(
        agent=0,
        kf_id=1,
        frame_index=4,
        timestamp=0.2,
        T_WC=torch.tensor([0, 0, 0, 0, 0, 0, 1, 1], dtype=torch.float64),
        X_hat=X_hat,
        C_hat=C_hat,
        colors=np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8),
        encoding=MASt3REncoding(
            agent=0,
            index=1,
            shape=(h, w),
            tokens=tokens,
            pos=torch.zeros(len(tokens), 2, dtype=torch.int64),
            grid=(3, 4),
        ),
        retrieval=(torch.randn(5, 16, generator=g), torch.rand(5, generator=g)),
        sequential_ij=matches,
        sequential_ji=matches,
        previous=None,
    )
    return dataclasses.replace(packet, **fields) if fields else packet
