"""The session store's coded arrays (format version 6, issue 39): what the lossy wire gives
back is stored in its coding and read back bit for bit; what the coordinator makes itself
(a refined pointmap, an inter-agent edge's matches) is settled on its coded value (a run's
store) or stored exact; version-4 and 5 stores are read; retrieval aggregates are stored
and a resume indexes them, in the codebook they were made in only."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import torch

from como3r.config import Config
from como3r.coordination.association import Candidate, Verification
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.prior.retrieval import Aggregated
from como3r.runtime.ingest import received
from como3r.store.blobs import ARRAYS_MAGIC, OBJECT_MAGIC
from como3r.store.reader import read_session
from como3r.store.resume import open_store
from como3r.store.schema import FORMAT_VERSION, STORE_NAME
from como3r.store.writer import SessionStore
from como3r.transport import codec_compact

from ..keyframe_packets import random_matches, random_packet

H, W = 12, 16


def _matches(gen: torch.Generator) -> DirectedMatches:
    return random_matches(H * W, gen)


def _packet(agent: int, kf_id: int, gen: torch.Generator) -> KeyframePacket:
    return random_packet(agent, kf_id, gen, H, W, retrieval=True)


def _session(path: Path, settles: bool) -> tuple[Coordinator, PairLink]:
    """Three received keyframes (two of agent 0), then a pointmap and an edge the
    coordinator made itself (returned: the edge's matches as made)."""
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
    return coordinator, link


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
    coordinator, made = _session(path, settles)
    kinds = _blob_kinds(path)
    coded = {k for k, v in kinds.items() if v == OBJECT_MAGIC}
    assert {"colours 0", "X_hat 0", "retrieval 0", "colours 1", "edge sequential"} <= coded
    # the refined pointmap and the verification's matches (their q no coded value):
    # settled, else exact
    assert ("X_hat 1" in coded) == settles
    assert kinds["edge inter"] == (OBJECT_MAGIC if settles else ARRAYS_MAGIC)
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
    held = want.links[-1].link
    assert held.covisible_ij == made.covisible_ij and (held is made) != settles
    for d in ("ij", "ji"):
        a, b = getattr(held, d), getattr(made, d)
        # what the global BA reads (optim/factors.py): every valid match exactly, its q
        # in 2^-3 log2 steps (INTER_MATCH_Q_BITS); invalid pixels to themselves with q 0
        assert torch.equal(a.valid, b.valid) and torch.equal(a.idx[a.valid], b.idx[b.valid])
        ratio = a.q[a.valid] / b.q[b.valid]
        assert bool(((ratio - 1).abs() <= 2 ** (2**-4) - 1 + 1e-6).all())
        assert torch.equal(a.q, b.q) != settles


def test_received_arrays_are_not_coded_again_by_the_store(tmp_path, monkeypatch) -> None:
    """The store takes the coded maps the ingest decoded a keyframe's arrays from
    (transport/codec_reuse.py): its pointmap, confidence, colours and sequential matches
    are coded once, by the ingest; a pointmap the coordinator made is coded by the store;
    a read gives back what the coordinator holds."""
    calls: dict[str, int] = {}
    for name, (encoder, decoder) in list(codec_compact.CODINGS.items()):

        def counted(value, owner=None, _name=name, _encoder=encoder):
            calls[_name] = calls.get(_name, 0) + 1
            return _encoder(value, owner)

        monkeypatch.setitem(codec_compact.CODINGS, name, (counted, decoder))
    coordinator, gen = Coordinator(None, Config(), None, 1), torch.Generator().manual_seed(0)
    path = tmp_path / STORE_NAME
    with SessionStore.create(path, Config(), coordinator, settles=True) as store:
        for kf_id in (0, 1):
            coordinator.graph.add_keyframe(received(_packet(0, kf_id, gen)))
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
        # the ingest's: two pointmaps, confidences, images; one edge's two directions
        assert calls == {
            "pointmap": 2,
            "confidence": 2,
            "image": 2,
            "matches": 2,
            "retrieval": 4,  # a tuple: not referable, coded again by the store (small)
        }
        kf = coordinator.graph.keyframes[1]
        kf.X_hat = kf.X_hat * 1.01  # the coordinator's own: the store codes it
        store.record(coordinator, [])
        assert calls["pointmap"] == 3
    for kf, held in zip(read_session(path).graph.keyframes, coordinator.graph.keyframes):
        for name in ("X_hat", "C_hat", "X_init", "C_init"):
            assert torch.equal(getattr(kf, name), getattr(held, name)), name
        assert np.array_equal(kf.colors, held.colors)


def test_the_admitted_candidate_holds_its_settled_edge(tmp_path) -> None:
    """A candidate admitted with an inter-agent edge holds the edge's settled matches, as a
    resumed coordinator's candidate (its edge's, read back) does."""
    path, gen = tmp_path / STORE_NAME, torch.Generator().manual_seed(3)
    coordinator = Coordinator(None, Config(), None, 2)
    with SessionStore.create(path, Config(), coordinator, settles=True) as store:
        for agent in (0, 1):
            coordinator.graph.add_keyframe(received(_packet(agent, 0, gen)))
        link = PairLink(_matches(gen), _matches(gen), 0.5, 0.6)
        verification = Verification((0, 0), (1, 0), 0.3, link.ij, 0.5, link, 0.6, True)
        coordinator.candidates.append(Candidate(verification, 0, 1, "admitted"))
        coordinator.graph.add_inter_link(0, 1, link, 0.3)
        store.record(coordinator, [])
    held = coordinator.graph.links[-1].link
    assert held is not link and coordinator.candidates[0].verification.link is held
    assert coordinator.candidates[0].verification.ij is held.ij


@pytest.mark.parametrize("version", [4, 5])
def test_an_older_store_is_read_and_upgraded_when_resumed(tmp_path, caplog, version) -> None:
    path = tmp_path / STORE_NAME
    _session(path, settles=False)
    with sqlite3.connect(path) as db:  # as formats 4 and 5 wrote it: its blobs read the same
        db.execute(f"UPDATE meta SET value = '{version}' WHERE key = 'format_version'")
        db.execute(f"PRAGMA user_version={version}")
    session = read_session(path)
    assert len(session.graph) == 3 and session.meta["format_version"] == str(version)
    coordinator = Coordinator(None, Config(), None, 2)
    with open_store(tmp_path, Config(), coordinator, resume=True, session=session) as store:
        store.record(coordinator, [])
    assert f"upgraded to {FORMAT_VERSION} in place" in caplog.text
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


def test_retrieval_aggregates_are_stored_and_indexed_again_in_their_codebook_only(
    tmp_path,
) -> None:
    """Keyframes whose agents sent their retrieval aggregated: stored as sent, indexed
    again by a resume as they were; a resume with another codebook is refused, the store
    left as it is."""
    rng, gen = np.random.default_rng(5), torch.Generator().manual_seed(4)
    codebook, config = rng.normal(size=(16, 32)).astype(np.float32), Config()
    coordinator = Coordinator(None, config, codebook, 2)
    database = coordinator.retrieval.database
    path = tmp_path / STORE_NAME
    with SessionStore.create(path, config, coordinator, settles=True) as store:
        for agent in (0, 1):
            aggregated = database.aggregate(rng.normal(size=(10, 32)).astype(np.float32))
            packet = dataclasses.replace(_packet(agent, 0, gen), retrieval=aggregated)
            coordinator.graph.add_keyframe(received(packet))
            coordinator.retrieval.query_and_add(agent, 0, aggregated)
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
    session = read_session(path)
    for kf, held in zip(session.graph.keyframes, coordinator.graph.keyframes, strict=True):
        assert isinstance(kf.retrieval, Aggregated)
        assert kf.retrieval.codebook_id == held.retrieval.codebook_id
        for name in ("query_words", "query_bits", "build_words", "build_bits"):
            assert np.array_equal(getattr(kf.retrieval, name), getattr(held.retrieval, name))
    resumed = Coordinator(None, config, codebook, 2)
    with open_store(tmp_path, config, resumed, resume=True, session=session):
        pass
    probe = database.aggregate(rng.normal(size=(10, 32)).astype(np.float32))
    scores = resumed.retrieval.database.scores(probe)
    assert len(scores) == 2 and np.array_equal(scores, database.scores(probe))
    other = Coordinator(None, config, codebook + 1, 2)
    with pytest.raises(StoreError, match="codebook of the run that made the store"):
        open_store(tmp_path, config, other, resume=True, session=read_session(path))
    assert path.is_file()
