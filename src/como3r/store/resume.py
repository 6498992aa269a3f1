"""Continuing a run from its session store (issue 14, item 2: ``como3r run --resume``).

A run killed at any moment leaves ``OUT.partial/session.db`` holding the coordinator's state
after its last complete message (:mod:`como3r.store.writer`). ``--resume`` starts the same
run again: :func:`open_store` reads the store, puts its state into the new run's coordinator
(:func:`restore_coordinator`) and keeps writing the store. The agents process their inputs
again from the start and send their keyframes again; the coordinator ignores the keyframes
it holds already and answers the last of them with the current poses of all the agent's
keyframes (a ``"resume"`` pose update,
:meth:`~como3r.coordination.coordinator.Coordinator.add_keyframe`), so the agent tracks on
in the shared frame, and takes the keyframes after them as new.

The coordinator comes back exactly: keyframes with their pointmaps, encodings (those the
store does not keep, MASt3R's, are encoded again from the stored colours when a verification
needs them: :mod:`como3r.coordination.encodings`) and poses, links with their matches, gauge
components, the retrieval database (rebuilt from the stored features in their order),
pending candidates with their matches, counters and the BA backlog. Edges refused inside
a gauge that await their recheck after the next global BA come back with their matches and
wait again (issue 41: else a resumed run would not test them again), and so do the
keyframes a batch budget deferred, with their retrieval hits. Other candidates that
were rejected or found inconsistent keep only their figures (:class:`StoredVerification`):
nothing uses their matches again.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

from como3r.config import Config, differing_key
from como3r.coordination.association import Candidate, Verification
from como3r.coordination.coordinator import Coordinator, CoordinatorStats
from como3r.errors import InputError, StoreError
from como3r.prior.retrieval import Aggregated
from como3r.store.paging import NO_MATCHES, StoredVerification
from como3r.store.reader import Session, read_session
from como3r.store.rows import RetrievalEntry, StoredCandidate
from como3r.store.schema import STORE_NAME
from como3r.store.writer import SessionStore

logger = logging.getLogger(__name__)


def open_store(
    folder: Path,
    config: Config,
    coordinator: Coordinator,
    resume: bool = False,
    session: Session | None = None,
) -> SessionStore:
    """The session store of a run in ``folder``, journal of ``coordinator``: a new one, or
    with ``resume`` the one there, whose state ``coordinator`` (new) takes first. It
    settles the pointmaps the coordinator makes on their coded values
    (:class:`~.writer.SessionStore`, ``settles``).

    Args:
        session: (resume) the store's contents, where the caller read them already; a
            session given may have finished (its agents' processes ran on: the outputs are
            still to be written), one read here may not.

    Raises:
        StoreError: (resume) no store there, or one that cannot be read, that finished, or
            that was made with another configuration or number of agents.
    """
    path = folder / STORE_NAME
    if not resume:
        return SessionStore.create(path, config, coordinator, settles=True)
    if session is None:
        session = read_session(path, paged=True)
        if session.finished:
            raise StoreError(
                f"{path}: the stored session finished (its run was stopped "
                f"while writing its outputs); run again without --resume"
            )
    restore_coordinator(session, coordinator)
    logger.info(
        "resuming from %s: %d keyframes of %d agents, %d edges",
        path,
        len(session.graph),
        len(session.agents),
        len(session.graph.links),
    )
    return SessionStore.reopen(path, coordinator, settles=True)


def restore_coordinator(session: Session, coordinator: Coordinator) -> None:
    """Give a new coordinator a stored session's state.

    Raises:
        StoreError: its configuration, number of agents or use of cross-agent retrieval
            differ from the coordinator's.
    """
    where = session.path
    difference = differing_key(session.config, coordinator.config)
    if difference is not None:
        raise StoreError(f"{where}: the stored session has another configuration ({difference})")
    if len(session.agents) != coordinator.num_agents:
        raise StoreError(
            f"{where}: the stored session has {len(session.agents)} agents, this "
            f"run {coordinator.num_agents}"
        )
    indexed = sorted(
        (e for e in session.retrieval if e.position is not None), key=lambda e: e.position or 0
    )
    if bool(indexed) != (coordinator.retrieval is not None) and len(session.graph):
        raise StoreError(
            f"{where}: the stored session was run "
            f"{'with' if indexed else 'without'} cross-agent retrieval, this run "
            f"{'without' if indexed else 'with'} (another prior or codebook?)"
        )
    load_state(session, coordinator, CoordinatorStats(**session.stats), session.backlog, indexed)
    # the edges awaiting their recheck: only a resumed run waits for them again (a map
    # seeded from a finished run starts its counters afresh,
    # :func:`como3r.runtime.map_session.seed_map`, which an admission would take below zero)
    coordinator.restore_refused(session.refused)
    # the keyframes a batch budget deferred: their hits came from the database as it was
    # when they were queried, which cannot be queried again as it was
    coordinator.restore_deferred(session.deferred)


def load_state(
    session: Session,
    coordinator: Coordinator,
    stats: CoordinatorStats,
    backlog: tuple[int, list[int]],
    indexed: Sequence[RetrievalEntry],
) -> None:
    """Put a stored session's keyframes, links, gauge components (its agents are the
    coordinator's first ones; the others stay in components of their own), candidates and
    gauge events into ``coordinator``, with ``stats`` and the BA ``backlog``, and the
    ``indexed`` retrieval entries, in that order, into its retrieval database (if it has
    one)."""
    gauges = session.gauges
    for agent in range(len(session.agents), coordinator.num_agents):
        gauges.add(agent)
    coordinator.restore(
        session.graph,
        gauges,
        [_candidate(c, session) for c in session.candidates],
        stats,
        session.gauge_events,
        backlog,
    )
    if coordinator.retrieval is not None:
        database = coordinator.retrieval.database
        for entry in indexed:
            if not isinstance(entry.features, Aggregated):
                database.add(entry.agent, entry.kf_id, *entry.features)
                continue
            try:
                database.add(entry.agent, entry.kf_id, entry.features)
            except InputError as exc:  # another codebook's words
                raise StoreError(
                    f"{session.path}: agent {entry.agent} keyframe {entry.kf_id}: {exc} "
                    "(run with the codebook of the run that made the store)"
                ) from None


def _candidate(stored: StoredCandidate, session: Session) -> Candidate:
    """A coordinator candidate from its stored record: admitted ones with their edge's
    matches, pending ones and those awaiting their recheck with theirs, the others with
    their figures."""
    graph = session.graph
    keys = [(graph.agent_of[g], graph.keyframes[g].kf_id) for g in (stored.i, stored.j)]
    link = stored.link
    if stored.status == "admitted":
        link = next(
            (
                e.link
                for e in graph.links
                if e.kind == "inter" and (e.i, e.j) == (stored.i, stored.j)
            ),
            None,
        )
        if link is None:
            raise StoreError(
                f"{session.path}: inconsistent session store: admitted candidate "
                f"{stored.i}-{stored.j} has no edge"
            )
    if link is not None:
        verification: Verification = Verification(
            keys[0],
            keys[1],
            stored.similarity,
            link.ij,
            link.covisible_ij,
            link,
            link.covisible_ji,
            stored.accepted,
        )
    else:
        verification = StoredVerification(
            keys[0],
            keys[1],
            stored.similarity,
            NO_MATCHES,
            None,
            None,
            None,
            stored.accepted,
            figures=(stored.nu_i, stored.nu_j, stored.covisible_ratio),
        )
    ratio = math.nan if stored.residual_ratio is None else stored.residual_ratio
    return Candidate(verification, stored.i, stored.j, stored.status, ratio)
