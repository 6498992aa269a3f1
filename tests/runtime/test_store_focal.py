"""The agents' own focal lengths in the session store (format version 7, issue 41): each
agent's own self-calibration, the centre of the focal BA's prior, is stored and read back;
a store of format 6 (no such column) is read with none and gets the column once resumed."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
import torch

from como3r.config import Config
from como3r.coordination.coordinator import Coordinator
from como3r.frontend.packets import KeyframePacket
from como3r.runtime.ingest import received
from como3r.store.reader import read_session
from como3r.store.resume import open_store
from como3r.store.schema import FORMAT_VERSION, STORE_NAME
from como3r.store.writer import SessionStore

H, W = 12, 16


def _packet(agent: int, focal: float, gen: torch.Generator) -> KeyframePacket:
    K = torch.tensor([[focal, 0.0, W / 2], [0.0, focal, H / 2], [0.0, 0.0, 1.0]])
    return KeyframePacket(
        agent=agent,
        kf_id=0,
        frame_index=0,
        timestamp=0.0,
        T_WC=torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]),
        X_hat=torch.rand(H, W, 3, generator=gen) + torch.tensor([0.0, 0.0, 1.0]),
        C_hat=1 + torch.rand(H, W, generator=gen),
        colors=torch.randint(256, (H, W, 3), generator=gen, dtype=torch.uint8).numpy(),
        encoding=None,
        retrieval=None,
        sequential_ij=None,
        sequential_ji=None,
        previous=None,
        K=K,
    )


def _store(path: Path) -> Coordinator:
    """Two agents' first keyframes (own focal lengths 20 and 22 px), then agent 1 moved
    onto 21 px (a merge's alignment)."""
    coordinator, gen = Coordinator(None, Config(), None, 2), torch.Generator().manual_seed(0)
    with SessionStore.create(path, Config(), coordinator) as store:
        for agent, focal in ((0, 20.0), (1, 22.0)):
            coordinator.graph.add_keyframe(received(_packet(agent, focal, gen)))
            coordinator.stats.keyframes += 1
        coordinator.graph.rescale_focal(1, float(torch.tensor(21.0 / 22.0).log()))
        store.record(coordinator, [])
    return coordinator


def test_the_agents_own_focal_lengths_are_stored(tmp_path) -> None:
    coordinator = _store(tmp_path / STORE_NAME)
    graph = read_session(tmp_path / STORE_NAME).graph
    assert graph.own_focal == coordinator.graph.own_focal == {0: 20.0, 1: 22.0}
    assert graph.focal == pytest.approx({1: 21.0})


def test_a_format_6_store_is_read_without_them_and_gets_them_when_resumed(tmp_path, caplog) -> None:
    path = tmp_path / STORE_NAME
    _store(path)
    with sqlite3.connect(path) as db:  # as format 6 wrote it
        db.execute("ALTER TABLE agents DROP COLUMN own_focal")
        db.execute("UPDATE meta SET value = '6' WHERE key = 'format_version'")
        db.execute("PRAGMA user_version=6")
    session = read_session(path)
    assert session.graph.own_focal == {} and session.graph.focal == pytest.approx({1: 21.0})
    assert session.meta["format_version"] == "6"
    coordinator = Coordinator(None, Config(), None, 2)
    with open_store(tmp_path, Config(), coordinator, resume=True, session=session) as store:
        coordinator.graph.own_focal[0] = 20.0  # agent 0's next keyframe said so
        store.record(coordinator, [])
    assert f"upgraded to {FORMAT_VERSION} in place" in caplog.text
    session = read_session(path)
    assert session.meta["format_version"] == str(FORMAT_VERSION)
    assert session.graph.own_focal == {0: 20.0}


def test_a_rescaled_keyframe_keeps_one_tensor_for_its_unfused_pointmap(tmp_path) -> None:
    """A keyframe whose pointmap was not replaced since insertion (``X_init`` is ``X_hat``)
    keeps them one tensor when a merge moves its focal length: the store codes one
    pointmap for both, and a read gives back what the coordinator holds."""
    path = tmp_path / STORE_NAME
    coordinator = _store(path)
    kf = coordinator.graph.keyframes[1]
    assert kf.X_init is kf.X_hat
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT X_hat = X_init FROM pointmaps WHERE g = 1").fetchone() == (1,)
    stored = read_session(path).graph.keyframes[1]
    assert torch.equal(stored.X_init, kf.X_hat) and torch.equal(stored.X_hat, kf.X_hat)
