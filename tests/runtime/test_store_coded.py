"""The session store's coded arrays (format version 5, issue 39): what the lossy wire gives
back is stored in its coding and read back bit for bit; what the coordinator makes itself
is settled on its coded value (a run's store) or stored exact; version-4 stores are read."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import torch

from como3r.config import Config
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.runtime.ingest import received
from como3r.store.blobs import ARRAYS_MAGIC, OBJECT_MAGIC
from como3r.store.reader import read_session
from como3r.store.resume import open_store
from como3r.store.schema import FORMAT_VERSION, STORE_NAME
from como3r.store.writer import SessionStore

H, W = 12, 16


def _matches(gen: torch.Generator) -> DirectedMatches:
    return DirectedMatches(
        torch.randint(H * W, (H * W,), generator=gen),
        torch.rand(H * W, generator=gen) > 0.3,
        0.1 + torch.rand(H * W, generator=gen),
    )


def _packet(agent: int, kf_id: int, gen: torch.Generator) -> KeyframePacket:
    first = kf_id == 0
    return KeyframePacket(
        agent=agent,
        kf_id=kf_id,
        frame_index=kf_id,
        timestamp=float(kf_id),
        T_WC=torch.rand(8, generator=gen),
        X_hat=torch.rand(H, W, 3, generator=gen) + torch.tensor([0.0, 0.0, 1.0]),
        C_hat=1 + torch.rand(H, W, generator=gen),
        colors=torch.randint(256, (H, W, 3), generator=gen, dtype=torch.uint8).numpy(),
        encoding=None,
        retrieval=(torch.randn(5, 8, generator=gen), torch.rand(5, generator=gen)),
        sequential_ij=None if first else _matches(gen),
        sequential_ji=None if first else _matches(gen),
        previous=None,
    )


def _session(path: Path, settles: bool) -> Coordinator:
    """Three received keyframes (two of agent 0), then a pointmap and an edge the
    coordinator made itself."""
    coordinator, gen = Coordinator(None, Config(), None, 2), torch.Generator().manual_seed(0)
    with SessionStore.create(path, Config(), coordinator, settles=settles) as store:
        for agent, kf_id in ((0, 0), (0, 1), (1, 0)):
            coordinator.graph.add_keyframe(received(_packet(agent, kf_id, gen)))
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
        kf = coordinator.graph.keyframes[1]
        kf.X_hat = kf.X_hat * 1.01  # refined: not a coded value
        link = PairLink(_matches(gen), _matches(gen), 0.5, 0.6)  # a verification's
        coordinator.graph.add_inter_link(2, 1, link, 0.3)
        store.record(coordinator, [])
    return coordinator


def _blob_kinds(path: Path) -> dict[str, bytes]:
    """The magic of each keyframe's and edge's blobs, by ``"part g"`` / ``"edge kind"``."""
    with sqlite3.connect(path) as db:
        kinds = {
            f"{name} {g}": kind
            for g, *row in db.execute(
                "SELECT k.g, substr(c.data, 1, 4), substr(x.data, 1, 4), "
                "substr(r.features, 1, 4) FROM keyframes k JOIN blobs c ON c.id = k.colors "
                "JOIN pointmaps m USING (g) JOIN blobs x ON x.id = m.X_hat "
                "JOIN retrieval r USING (g)"
            )
            for name, kind in zip(("colours", "X_hat", "retrieval"), row)
        }
        for kind, magic in db.execute("SELECT kind, substr(matches, 1, 4) FROM edges"):
            kinds[f"edge {kind}"] = magic
    return kinds


@pytest.mark.parametrize("settles", [True, False])
def test_received_arrays_are_stored_coded_and_made_ones_settled_or_exact(tmp_path, settles) -> None:
    path = tmp_path / STORE_NAME
    coordinator = _session(path, settles)
    kinds = _blob_kinds(path)
    coded = {k for k, v in kinds.items() if v == OBJECT_MAGIC}
    assert {"colours 0", "X_hat 0", "retrieval 0", "colours 1", "edge sequential"} <= coded
    assert kinds["edge inter"] == ARRAYS_MAGIC  # its q is no coded value: exact
    assert ("X_hat 1" in coded) == settles  # the refined pointmap: settled, else exact
    graph, want = read_session(path).graph, coordinator.graph
    for kf, held in zip(graph.keyframes, want.keyframes):
        for name in ("X_hat", "C_hat", "X_init", "C_init"):
            assert torch.equal(getattr(kf, name), getattr(held, name)), name
        assert np.array_equal(kf.colors, held.colors)
        assert all(torch.equal(a, b) for a, b in zip(kf.retrieval, held.retrieval))
    for link, held_link in zip(graph.links, want.links, strict=True):
        for d in ("ij", "ji"):
            for f in ("idx", "valid", "q"):
                a, b = (getattr(getattr(x.link, d), f) for x in (link, held_link))
                assert torch.equal(a, b), (link.kind, d, f)
    refined, unrefined = want.keyframes[1].X_hat, want.keyframes[1].X_init * 1.01
    assert torch.equal(refined, unrefined) != settles  # settled: the coded value
    assert torch.allclose(refined, unrefined, rtol=1e-3)


def test_a_version_4_store_is_read_and_upgraded_when_resumed(tmp_path, caplog) -> None:
    path = tmp_path / STORE_NAME
    _session(path, settles=False)
    with sqlite3.connect(path) as db:  # as format 4 wrote it: its blobs read the same
        db.execute("UPDATE meta SET value = '4' WHERE key = 'format_version'")
        db.execute("PRAGMA user_version=4")
    session = read_session(path)
    assert len(session.graph) == 3 and session.meta["format_version"] == "4"
    coordinator = Coordinator(None, Config(), None, 2)
    with open_store(tmp_path, Config(), coordinator, resume=True, session=session) as store:
        store.record(coordinator, [])
    assert "upgraded to 5 in place" in caplog.text
    assert read_session(path).meta["format_version"] == str(FORMAT_VERSION)
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version=3")
    with pytest.raises(StoreError, match="format version 3 is older than this como3r reads"):
        read_session(path)
    assert path.is_file()  # refused, never deleted


def test_the_encoding_is_handed_over_as_its_agent_made_it() -> None:
    """MASt3R's tokens travel in float16 across machines, but no coordinator there uses
    them: it encodes the colours again, bit for bit. So every runtime hands the coordinator
    the encoding itself, its float32 tokens unrounded, while the arrays beside it come
    through the wire's codings."""
    gen = torch.Generator().manual_seed(1)
    tokens = torch.randn(12, 8, generator=gen) / 3  # float16 rounds them
    encoding = MASt3REncoding(
        agent=0,
        index=1,
        shape=(H, W),
        tokens=tokens,
        pos=torch.zeros(12, 2, dtype=torch.int64),
        grid=(3, 4),
    )
    packet = dataclasses.replace(_packet(0, 1, gen), encoding=encoding)
    assert not torch.equal(tokens.half().float(), tokens)
    got = received(packet)
    assert got.encoding is encoding
    assert not torch.equal(got.X_hat, packet.X_hat)  # the pointmap came through its coding
