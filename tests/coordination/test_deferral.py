"""Deferred verification (coordination/deferral.py, issue 41): keyframes a batch budget
(``verification.max_decodes_per_batch``) skips are verified later, newest first, with what a
later batch leaves of its budget, one at a time when the runtime is idle, and all that
remain before the terminal cleanup; each keyframe with hits is verified exactly once; the
session store keeps the list for a resumed run."""

from __future__ import annotations

import shutil
import sqlite3

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.coordination.coordinator import Coordinator
from como3r.frontend.packets import KeyframePacket
from como3r.prior.simulated import SimulatedPrior

from .ring_keyframes import AGENTS, HEIGHT, SHORT_RUN, WIDTH, ring_keyframes

OVERRIDES = [*SHORT_RUN]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[SimulatedPrior, list[KeyframePacket]]:
    """Three agents on a ring, every second frame a keyframe, interleaved in time; the agents
    send encoding records, as in a multi-process run (the coordinator encodes again)."""
    config = apply_overrides(Config(), OVERRIDES)
    return ring_keyframes(
        tmp_path_factory.mktemp("deferral"), config, AGENTS, WIDTH, HEIGHT, portable_from=0
    )


class _Watched(Coordinator):
    """Records the keyframes retrieval found hits for and every verification's keyframe."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.with_hits: list[tuple[int, int]] = []
        self.verified: list[tuple[int, int]] = []

    def _retrieve(self, packet):
        hits = super()._retrieve(packet)
        if hits:
            self.with_hits.append((packet.agent, packet.kf_id))
        return hits

    def _verify(self, packet, hits):
        if hits:
            self.verified.append((packet.agent, packet.kf_id))
        return super()._verify(packet, hits)


def _coordinator(prior: SimulatedPrior, per_batch: int) -> _Watched:
    config = apply_overrides(
        Config(), [*OVERRIDES, f"verification.max_decodes_per_batch={per_batch}"]
    )
    return _Watched(prior, config, prior.codebook(), AGENTS)


def _keys(coordinator: Coordinator) -> list[tuple[int, int]]:
    return [(agent, kf_id) for agent, kf_id, _ in coordinator.deferred_keyframes()]


def test_every_keyframe_with_hits_is_verified_once_by_the_end(scene) -> None:
    """Batches of six under a budget of one keyframe's worst case: keyframes are skipped
    (deferred) in-stream; finish verifies every one still deferred before the cleanup, so
    the keyframes verified are those a run without the budget verifies, each once; without
    a budget nothing is deferred."""
    prior, order = scene
    per_keyframe = Config().verification.max_decodes_per_keyframe
    bounded, free = _coordinator(prior, per_keyframe), _coordinator(prior, 0)
    for run in (bounded, free):
        for start in range(0, len(order), 6):
            run.add_keyframes(order[start : start + 6])
    stats = bounded.stats
    waiting = _keys(bounded)
    assert stats.verification_skipped > 0 and waiting
    assert stats.verification_deferred == stats.verification_skipped - len(waiting)
    assert not set(waiting) & set(bounded.verified)  # deferred: not verified yet
    assert bounded.stats.prior_decodes < free.stats.prior_decodes
    bounded.finish()
    free.finish()
    assert bounded.deferred_keyframes() == []
    assert stats.verification_deferred == stats.verification_skipped
    assert stats.verification_deferred_at_finish == len(waiting)
    assert bounded.verified[-len(waiting) :] == waiting[::-1]  # newest first
    assert len(bounded.verified) == len(set(bounded.verified))
    assert sorted(bounded.verified) == sorted(bounded.with_hits) == sorted(free.verified)
    assert free.stats.verification_skipped == free.stats.verification_deferred == 0
    assert bounded.stats.edges_tried > 0


def test_a_later_batch_verifies_the_newest_deferred_with_its_leftover(scene) -> None:
    """A batch of one after a skipping batch: its own keyframe first, then the newest
    deferred keyframes while the batch budget leaves one keyframe's worst case; the batch's
    decodes stay within the budget."""
    prior, order = scene
    per_keyframe = Config().verification.max_decodes_per_keyframe
    coordinator = _coordinator(prior, 2 * per_keyframe)
    coordinator.add_keyframes(order[:9])
    waiting = _keys(coordinator)
    assert len(waiting) >= 2
    verified, decodes = len(coordinator.verified), coordinator.stats.prior_decodes
    coordinator.add_keyframes([order[9]])
    after = coordinator.verified[verified:]
    own = (order[9].agent, order[9].kf_id)
    later = [k for k in after if k != own]
    assert later and later == waiting[::-1][: len(later)]  # the newest deferred ones
    assert _keys(coordinator) == waiting[: len(waiting) - len(later)]
    assert coordinator.stats.verification_deferred == len(later)
    assert coordinator.stats.prior_decodes - decodes <= 2 * per_keyframe
    coordinator.pool.shutdown()


def test_an_idle_coordinator_verifies_one_deferred_keyframe_at_a_time(scene) -> None:
    prior, order = scene
    coordinator = _coordinator(prior, Config().verification.max_decodes_per_keyframe)
    assert coordinator.verify_deferred_one() == []  # nothing deferred: nothing happens
    coordinator.add_keyframes(order[:9])
    waiting = _keys(coordinator)
    assert len(waiting) >= 2
    verified = len(coordinator.verified)
    coordinator.verify_deferred_one()
    assert coordinator.verified[verified:] == [waiting[-1]]
    assert _keys(coordinator) == waiting[:-1]
    assert coordinator.stats.verification_deferred == 1
    coordinator.pool.shutdown()


def test_finish_lets_go_of_the_encodings_once_no_deferred_verification_needs_them(
    scene, monkeypatch
) -> None:
    """The end's deferred verification keeps, chunk by chunk, only the re-encoded keyframes
    the keyframes still deferred and their hits are (nothing decodes after it) and none
    once done; it re-encodes no keyframe more than keeping all of them does, and verifies
    the same pairs with the same outcomes."""
    from como3r.coordination.encodings import KeyframeEncodings

    prior, order = scene
    runs = []
    for retained in (True, False):
        if not retained:  # the cache as it was: bounded by session.encoding_cache alone
            monkeypatch.setattr(KeyframeEncodings, "retain", lambda self, needed: None)
        coordinator = _coordinator(prior, Config().verification.max_decodes_per_keyframe)
        coordinator.add_keyframes(order[:9])
        assert coordinator.deferred_keyframes() and coordinator.encodings.cached()
        reencodes = coordinator.stats.reencodes
        coordinator.finish()
        outcomes = [(c.i, c.j, c.status) for c in coordinator.candidates]
        runs.append((coordinator, coordinator.stats.reencodes - reencodes, outcomes))
    (kept, reencoded, outcomes), (unbounded, reencoded_all, outcomes_all) = runs
    assert kept.encodings.cached() == [] and unbounded.encodings.cached()
    assert reencoded == reencoded_all > 0
    assert kept.verified == unbounded.verified and outcomes == outcomes_all
    assert torch.equal(kept.graph.poses(range(9)), unbounded.graph.poses(range(9)))


def test_finish_lets_go_of_the_encodings_with_nothing_deferred(scene) -> None:
    """Without a batch budget nothing is deferred, and the re-encoded keyframes still go
    when the stream ends: the terminal cleanup decodes nothing (issue 41: at 16 agents the
    cache held 1.5 GB through the cleanup)."""
    prior, order = scene
    coordinator = _coordinator(prior, 0)
    coordinator.add_keyframes(order[:9])
    assert not coordinator.deferred_keyframes() and coordinator.encodings.cached()
    coordinator.finish()
    assert coordinator.encodings.cached() == []


def test_a_resumed_coordinator_verifies_the_deferred_keyframes(scene, tmp_path) -> None:
    """The session store keeps the deferred keyframes with their hits (format version 9);
    the resumed coordinator verifies them as the interrupted one would have; a version-8
    store (no list) resumes with none deferred and is marked version 9 once written on."""
    from como3r.errors import StoreError
    from como3r.store.reader import read_session
    from como3r.store.resume import restore_coordinator
    from como3r.store.schema import FORMAT_VERSION
    from como3r.store.writer import SessionStore

    prior, order = scene
    coordinator = _coordinator(prior, Config().verification.max_decodes_per_keyframe)
    path = tmp_path / "session.db"
    store = SessionStore.create(path, coordinator.config, coordinator, settles=True)
    coordinator.journal = store
    coordinator.add_keyframes(order[:9])
    coordinator.pool.shutdown()
    store.close()
    deferred = coordinator.deferred_keyframes()
    assert deferred and all(hits for _, _, hits in deferred)
    # version 9 is the first to keep the list (a reader of 8 would drop it unawares)
    assert FORMAT_VERSION >= 9
    assert read_session(path).meta["format_version"] == str(FORMAT_VERSION)

    older = tmp_path / "older.db"
    shutil.copy(path, older)
    with sqlite3.connect(older) as db:  # as version 8 wrote it
        db.execute("DELETE FROM state WHERE key = 'deferred'")
        db.execute("UPDATE meta SET value = '8' WHERE key = 'format_version'")
        db.execute("PRAGMA user_version=8")
    db.close()
    session = read_session(older, paged=True)
    assert session.deferred == [] and session.meta["format_version"] == "8"
    resumed = _coordinator(prior, Config().verification.max_decodes_per_keyframe)
    restore_coordinator(session, resumed)
    assert resumed.deferred_keyframes() == []
    store = SessionStore.reopen(older, resumed, settles=True)
    store.close()
    resumed.pool.shutdown()
    with sqlite3.connect(older) as db:
        assert db.execute("PRAGMA user_version").fetchone() == (FORMAT_VERSION,)
    db.close()
    assert read_session(older).meta["format_version"] == str(FORMAT_VERSION)
    # a list that names a keyframe the store does not hold is refused
    with sqlite3.connect(older) as db:
        db.execute("INSERT OR REPLACE INTO state VALUES ('deferred', '[[0, 99, [[1, 0, 0.5]]]]')")
    db.close()
    with pytest.raises(StoreError, match="the deferred keyframes"):
        read_session(older)

    session = read_session(path, paged=True)
    assert session.deferred == deferred
    resumed = _coordinator(prior, Config().verification.max_decodes_per_keyframe)
    restore_coordinator(session, resumed)
    assert resumed.deferred_keyframes() == deferred
    skipped = resumed.stats.verification_skipped
    store = SessionStore.reopen(path, resumed, settles=True)
    resumed.journal = store
    resumed.finish()
    store.close()
    assert resumed.verified == [(a, k) for a, k, _ in deferred[::-1]]
    assert resumed.stats.verification_deferred == skipped
    assert read_session(path).deferred == []
