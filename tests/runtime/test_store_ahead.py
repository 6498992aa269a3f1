"""The session store's codings started ahead of its transaction (store/ahead.py, issue 41):
a worker's result is taken only for the very same inputs, unchanged since; a store that
codes ahead writes the bytes, and leaves the coordinator the settled values, of one that
codes everything on the spot; a page-out that lets go of nothing gives no memory back."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import pytest
import torch

from como3r.backend.graph_link import GraphLink
from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.runtime.ingest import received
from como3r.store import paging
from como3r.store.ahead import Ahead
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME
from como3r.store.writer import SessionStore

from ..keyframe_packets import random_packet

H, W = 12, 16


def _total(x: torch.Tensor, scale: int = 1) -> torch.Tensor:
    return x.sum() * scale


def _fails(x: torch.Tensor) -> None:
    raise ValueError(f"cannot code {tuple(x.shape)}")


def test_a_coding_ahead_is_taken_only_for_the_same_unchanged_inputs() -> None:
    ahead = Ahead(2)
    try:
        x = torch.arange(6.0)
        ahead.submit(_total, x)
        assert torch.equal(ahead.take(_total, x), torch.tensor(15.0))
        assert (ahead.taken, ahead.inline) == (1, 0)

        changed = torch.arange(6.0)
        ahead.submit(_total, changed)
        changed.add_(1)  # in place after the submit: its version moved on
        assert torch.equal(ahead.take(_total, changed), torch.tensor(21.0))
        assert (ahead.taken, ahead.inline) == (1, 1)

        ahead.submit(_total, x, 2)
        assert torch.equal(ahead.take(_total, x, 3), torch.tensor(45.0))  # other arguments
        assert torch.equal(ahead.take(_total, x.clone()), torch.tensor(15.0))  # another tensor
        assert (ahead.taken, ahead.inline) == (1, 3)

        ahead.submit(_fails, x)
        with pytest.raises(ValueError, match="cannot code"):  # raised where it is taken
            ahead.take(_fails, x)
        ahead.submit(_total, x)
        ahead.drop()  # not taken by the transaction: not kept for the next one
        ahead.take(_total, x)
        assert ahead.inline == 4
    finally:
        ahead.close()


def _packet(agent: int, kf_id: int, gen: torch.Generator) -> KeyframePacket:
    return random_packet(agent, kf_id, gen, H, W)


def _session(path: Path, workers: int) -> tuple[Coordinator, Ahead]:
    """Received keyframes, then the coordinator's own pointmaps (one refined in place of a
    received one, one made at insertion), an inter-agent and a loop edge; the store told
    before each transaction as the coordinator tells it (Coordinator._prepare)."""
    coordinator, gen = Coordinator(None, Config(), None, 2), torch.Generator().manual_seed(5)
    path.parent.mkdir()
    with SessionStore.create(path, Config(), coordinator, settles=True) as store:
        store.ahead.close()
        store.ahead = ahead = Ahead(workers)
        for agent, kf_id in ((0, 0), (0, 1), (1, 0)):
            coordinator.graph.add_keyframe(received(_packet(agent, kf_id, gen)))
            coordinator.stats.keyframes += 1
            store.prepare(coordinator)
            store.record(coordinator, [])
        graph = coordinator.graph
        graph.keyframes[1].X_hat = graph.keyframes[1].X_hat * 1.01
        graph.add_keyframe(_packet(1, 1, gen))  # not through the ingest: nothing to reuse
        coordinator.stats.keyframes += 1
        store.prepare(coordinator)
        made = [DirectedMatches(m.idx, m.valid, m.q * 1.01) for m in (graph.links[0].link.ij,) * 2]
        graph.add_inter_link(2, 1, PairLink(*made, 0.5, 0.6), 0.3)
        graph.links.append(GraphLink(0, 1, "loop", PairLink(*made[::-1], 0.4, 0.7), 0.2))
        store.prepare(coordinator)
        store.record(coordinator, [])
    return coordinator, ahead


def _rows(path: Path) -> dict[str, list[Any]]:
    with sqlite3.connect(path) as db:
        blobs = dict(db.execute("SELECT id, data FROM blobs"))
        return {
            "pointmaps": [
                (g, *(blobs[b] for b in ids))
                for g, *ids in db.execute(
                    "SELECT g, X_hat, C_hat, X_init, C_init FROM pointmaps ORDER BY g"
                )
            ],
            "edges": list(db.execute("SELECT * FROM edges ORDER BY n")),
        }


def test_a_store_coding_ahead_writes_what_coding_on_the_spot_writes(tmp_path) -> None:
    on_spot, inline = _session(tmp_path / "a" / STORE_NAME, workers=0)
    ahead_of, ahead = _session(tmp_path / "b" / STORE_NAME, workers=2)
    # the coordinator's own: the refined pointmap, the unreceived keyframe's pointmap,
    # confidence and sequential edge, the inter-agent and the loop edge
    assert ahead.taken == 6 and inline.taken == 0
    assert _rows(tmp_path / "a" / STORE_NAME) == _rows(tmp_path / "b" / STORE_NAME)
    read = read_session(tmp_path / "b" / STORE_NAME).graph
    for kf, same, held in zip(on_spot.graph.keyframes, ahead_of.graph.keyframes, read.keyframes):
        for name in ("X_hat", "C_hat", "X_init", "C_init"):  # settled alike, read back so
            assert torch.equal(getattr(kf, name), getattr(same, name)), name
            assert torch.equal(getattr(held, name), getattr(same, name)), name
    for link, same in zip(on_spot.graph.links, ahead_of.graph.links, strict=True):
        assert torch.equal(link.link.ij.q, same.link.ij.q), link.kind


def test_a_page_out_that_lets_go_of_nothing_gives_no_memory_back(tmp_path, monkeypatch) -> None:
    trims: list[int] = []
    monkeypatch.setattr(paging, "give_back_freed_memory", lambda: trims.append(1))
    # the setting is the point of the test: the first keyframes stay, then they are paged
    config = apply_overrides(Config(), ["session.resident_keyframes=2"])
    coordinator, gen = Coordinator(None, config, None, 1), torch.Generator().manual_seed(1)
    with SessionStore.create(tmp_path / STORE_NAME, config, coordinator) as store:
        for kf_id in range(3):
            coordinator.graph.add_keyframe(_packet(0, kf_id, gen))
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
            assert len(trims) == (kf_id == 2)  # the third pages the first out
        store.record(coordinator, [])
        assert len(trims) == 1
