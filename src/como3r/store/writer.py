"""The session store: the coordinator's durable state, written as it goes (issue 14, item 1).

A centralized run keeps ``session.db`` in its output folder (in ``OUT.partial`` while it
runs): one SQLite database in WAL mode, written by :class:`SessionStore`, the coordinator's
:class:`~como3r.coordination.coordinator.Journal`. After the coordinator has handled a
message (a keyframe, with its retrieval, verification, gauge merge and global BA; a
pointmap refresh; the terminal cleanup) the store takes everything that changed in ONE
transaction. A process killed at any moment (``kill -9``) therefore leaves a store that
opens and holds the coordinator's state after some message, complete; a power loss may
lose the last transactions (``synchronous=NORMAL``) but not the store's consistency.
:func:`como3r.store.reader.read_session` loads it back;
:mod:`como3r.store.resume` continues a killed run from it (``--resume``).

Layout (format version :data:`FORMAT_VERSION`; also ``PRAGMA user_version``, and ``PRAGMA
application_id`` = :data:`APPLICATION_ID` marks the file as a como3r store). Keyframes are
numbered by their global index ``g`` (arrival order at the coordinator); agent ids are the
coordinator's (a restarted agent process that starts a new map segment has its own).
``blob`` columns hold :mod:`.store_blobs` blobs (typed arrays or codec objects, Zstandard)::

    meta        key TEXT PK, value TEXT   format_version, como3r_version, created (UTC),
                                          config (JSON of the effective configuration)
    blobs       id PK, data BLOB          the large arrays, referenced by id below
    keyframes   g PK, agent, kf_id, frame_index, timestamp, colors -> blobs (H, W, 3) uint8,
                encoding -> blobs (the prior's Encoding, codec object); UNIQUE (agent, kf_id);
                written once
    pointmaps   g PK, fused_frames, X_hat, C_hat, X_init, C_init -> blobs ((H, W, 3) and
                (H, W) float32; X_init/C_init point at the same blob as X_hat/C_hat while
                they are the same arrays), K blob (3, 3) or NULL; rewritten on refresh, focal
                alignment, depth refinement (its old blobs deleted)
    poses       g PK, T_WC blob (8,)      the current pose, rewritten when it moves
    retrieval   g PK, agent, kf_id, position (insertion order in the coordinator's ASMK
                database, NULL if not indexed), features blob (descriptors (N, d),
                attention (N,))
    edges       n PK (graph order), i, j (global), kind 'sequential'|'inter', similarity,
                covisible_ij, covisible_ji, matches blob (ij.idx, ij.valid, ij.q, ji.idx,
                ji.valid, ji.q: every pixel of j in i and of i in j)
    candidates  n PK (verification order), i, j, status 'rejected'|'pending'|'admitted'|
                'inconsistent', residual_ratio, similarity, nu_i, nu_j, covisible_ratio,
                accepted, covisible_ij, covisible_ji, matches blob while pending (an admitted
                candidate's matches are its edge's)
    gauges      agent PK, component       the component's root (its lowest agent id)
    agents      agent PK, keyframes, last_keyframe_frame, updates_sent, focal
                                          per-agent progress: keyframes stored, the frame
                                          index of the last, pose updates made for it (the
                                          seq of the last PoseUpdateMessage), its focal
                                          length in the map (NULL: not aligned)
    state       key TEXT PK, value JSON   stats, gauge_events, alternation, backlog
                                          (inter edges since the last BA, their component
                                          roots), finished (the terminal cleanup ran),
                                          runtime (the multi-process runtime's view of its
                                          agents and map segments, and its transport's
                                          state: :mod:`.runtime_state`)
    reports     agent PK, message blob    an agent process's final report (AgentFinished,
                                          codec object) per coordinator agent: its
                                          trajectory relative to its keyframes, statistics

A reader refuses a file that is not such a store, is corrupted, or has another format
version, with one :class:`~como3r.errors.StoreError` line. The store is created complete
(schema and configuration in a file renamed into place), so it never exists half-made;
while it is written ``session.db-wal`` and ``session.db-shm`` sit beside it (a killed run
leaves them: they hold its last transactions), and closing it folds them back into one file.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import sqlite3
import weakref
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from como3r import __version__
from como3r.config import Config, config_to_dict
from como3r.coordination.coordinator import Candidate, Coordinator
from como3r.errors import StoreError
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.packets import PoseUpdate
from como3r.frontend.paging import POINTMAP_FIELDS, PagedKeyframe
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.prior.base import Encoding
from como3r.store.blobs import pack_arrays, pack_object, unpack_arrays, unpack_object
from como3r.store.paging import PagedLink, page_out
from como3r.transport.messages import AgentFinished

logger = logging.getLogger(__name__)

#: the store's file name in an output folder
STORE_NAME = "session.db"
#: the layout above; a reader refuses any other
FORMAT_VERSION = 3
#: SQLite page size of a new store, the largest: a keyframe writes megabytes of blobs
#: (13 MB of simulated-prior state, 2 MB per pointmap at 512x384) as chains of overflow
#: pages, and 15 transactions of 13 + 4 x 1.8 MB took 0.68 s at 64 KiB pages against 1.65 s
#: at SQLite's default 4 KiB (WAL, synchronous=NORMAL; 0.76 s against 1.37 s in another run
#: of ``benchmarks/depth_step_speed.py``). Stores made with other page sizes open as they are.
PAGE_SIZE = 65536

#: ``PRAGMA application_id`` of a como3r session store ("C3RS")
APPLICATION_ID = 0x43335253

SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE blobs (id INTEGER PRIMARY KEY, data BLOB NOT NULL);
CREATE TABLE keyframes (
    g INTEGER PRIMARY KEY, agent INTEGER NOT NULL, kf_id INTEGER NOT NULL,
    frame_index INTEGER NOT NULL, timestamp REAL NOT NULL,
    colors INTEGER NOT NULL REFERENCES blobs (id),
    encoding INTEGER NOT NULL REFERENCES blobs (id),
    UNIQUE (agent, kf_id));
CREATE TABLE pointmaps (
    g INTEGER PRIMARY KEY REFERENCES keyframes (g), fused_frames INTEGER NOT NULL,
    X_hat INTEGER NOT NULL REFERENCES blobs (id), C_hat INTEGER NOT NULL REFERENCES blobs (id),
    X_init INTEGER NOT NULL REFERENCES blobs (id), C_init INTEGER NOT NULL REFERENCES blobs (id),
    K BLOB);
CREATE TABLE poses (g INTEGER PRIMARY KEY REFERENCES keyframes (g), T_WC BLOB NOT NULL);
CREATE TABLE retrieval (
    g INTEGER PRIMARY KEY REFERENCES keyframes (g), agent INTEGER NOT NULL,
    kf_id INTEGER NOT NULL, position INTEGER UNIQUE, features BLOB NOT NULL);
CREATE TABLE edges (
    n INTEGER PRIMARY KEY, i INTEGER NOT NULL REFERENCES keyframes (g),
    j INTEGER NOT NULL REFERENCES keyframes (g), kind TEXT NOT NULL, similarity REAL,
    covisible_ij REAL, covisible_ji REAL, matches BLOB NOT NULL);
CREATE TABLE candidates (
    n INTEGER PRIMARY KEY, i INTEGER NOT NULL REFERENCES keyframes (g),
    j INTEGER NOT NULL REFERENCES keyframes (g), status TEXT NOT NULL, residual_ratio REAL,
    similarity REAL NOT NULL, nu_i REAL, nu_j REAL NOT NULL, covisible_ratio REAL,
    accepted INTEGER NOT NULL, covisible_ij REAL, covisible_ji REAL, matches BLOB);
CREATE TABLE gauges (agent INTEGER PRIMARY KEY, component INTEGER NOT NULL);
CREATE TABLE agents (
    agent INTEGER PRIMARY KEY, keyframes INTEGER NOT NULL,
    last_keyframe_frame INTEGER NOT NULL, updates_sent INTEGER NOT NULL, focal REAL);
CREATE TABLE state (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE reports (agent INTEGER PRIMARY KEY, message BLOB NOT NULL);
"""


def pack_link(link: PairLink) -> bytes:
    """Both directions' matches of a link in one blob (the ``matches`` columns)."""
    return pack_arrays(link.ij.idx, link.ij.valid, link.ij.q, link.ji.idx, link.ji.valid, link.ji.q)


@dataclass
class _Written:
    """What the store holds of one keyframe's pointmaps: the very tensors (weakly: compared
    by identity, so a replaced pointmap is seen without comparing its values, and a
    paged-out one is not kept alive) and their blob ids."""

    arrays: tuple[weakref.ref, ...]
    blobs: tuple[int, ...]
    K: Tensor | None
    fused_frames: int

    def holds(self, array: Tensor) -> int | None:
        """The blob id of ``array`` if it is one of these tensors."""
        return next((b for a, b in zip(self.arrays, self.blobs) if a() is array), None)


class SessionStore:
    """The coordinator's journal: its state in ``session.db``, one transaction per message.

    Made by :meth:`create`; as a context manager it is the coordinator's journal until the
    block ends, then closed (before the output folder is renamed into place).

    Args:
        connection: the open database (WAL, autocommit: transactions are explicit).
        path: its file.
    """

    def __init__(self, connection: sqlite3.Connection, path: Path) -> None:
        self.connection = connection
        self.path = path
        self.transactions = 0
        self._coordinator: Coordinator | None = None
        self._failed = False
        self._finished = False
        self._keyframes: list[_Written] = []
        self._poses = torch.zeros(0, 8)
        self._edges = 0
        self._candidates: list[tuple[str, float | None]] = []
        self._indexed = 0
        self._rows: dict[str, dict[Any, tuple]] = {"gauges": {}, "agents": {}, "state": {}}
        self._updates: dict[int, int] = {}
        self._reports: dict[int, AgentFinished] = {}
        #: bytes of blobs and text written, per part (:meth:`written_metrics`)
        self.written: Counter[str] = Counter()

    @classmethod
    def create(
        cls, path: str | Path, config: Config, coordinator: Coordinator | None = None
    ) -> SessionStore:
        """A new store at ``path`` (which must not exist) holding ``config``; it becomes
        ``coordinator``'s journal and takes its current state at once.

        Raises:
            StoreError: ``path`` exists, or the store cannot be written there.
        """
        path = Path(path)
        if path.exists():
            raise StoreError(f"{path}: a session store exists there already")
        partial = path.with_name(path.name + ".new")
        partial.unlink(missing_ok=True)
        try:
            connection = sqlite3.connect(partial, isolation_level=None)
            # set before the first table (WAL fixes it): the blobs are megabytes each
            connection.execute(f"PRAGMA page_size={PAGE_SIZE}")
            connection.execute("PRAGMA journal_mode=WAL")
            connection.executescript("BEGIN;" + SCHEMA + "COMMIT;")
            meta = {
                "format_version": str(FORMAT_VERSION),
                "como3r_version": __version__,
                "created": datetime.datetime.now(datetime.timezone.utc).isoformat(
                    timespec="seconds"
                ),
                "config": json.dumps(config_to_dict(config)),
            }
            with _transaction(connection):
                connection.executemany("INSERT INTO meta VALUES (?, ?)", meta.items())
                connection.execute(f"PRAGMA application_id={APPLICATION_ID}")
                connection.execute(f"PRAGMA user_version={FORMAT_VERSION}")
            connection.close()  # checkpoints the WAL into the file: one complete file
            partial.rename(path)
            connection = sqlite3.connect(path, isolation_level=None)
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.Error as exc:
            raise StoreError(f"{path}: cannot create the session store ({exc})") from None
        store = cls(connection, path)
        if coordinator is not None:
            store.attach(coordinator)
        return store

    @classmethod
    def reopen(cls, path: str | Path, coordinator: Coordinator) -> SessionStore:
        """The store at ``path`` written on by ``coordinator``, which holds its state already
        (:func:`como3r.store.resume.open_store` restored it); a WAL left by a killed
        writer is recovered on opening.

        Raises:
            StoreError: the store cannot be opened for writing.
        """
        path = Path(path)
        try:
            connection = sqlite3.connect(path, isolation_level=None)
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute("PRAGMA synchronous=NORMAL")
            store = cls(connection, path)
            store._held(coordinator)
        except sqlite3.Error as exc:
            raise StoreError(f"{path}: cannot open the session store ({exc})") from None
        store._coordinator = coordinator
        coordinator.journal = store
        return store

    def _held(self, coordinator: Coordinator) -> None:
        """Take what the store holds as written: the coordinator's restored tensors with their
        blob ids, and the rows of the small tables as they are."""
        graph, db = coordinator.graph, self.connection
        for g, *ids in db.execute(
            "SELECT g, X_hat, C_hat, X_init, C_init FROM pointmaps ORDER BY g"
        ):
            kf = graph.keyframes[g]
            if isinstance(kf, PagedKeyframe) and not kf.resident("pointmaps"):
                kf.evict(self, g)  # read back as paged: this store serves it
                arrays: tuple[weakref.ref, ...] = ()
            else:
                arrays = _refs(_pointmap_arrays(kf))
            self._keyframes.append(_Written(arrays, tuple(ids), kf.K, kf.fused_frames))
        for link in graph.links:
            if isinstance(link.link, PagedLink):
                link.link.serve(self)
        if len(graph):
            self._poses = graph.poses(range(len(graph))).detach().cpu().clone()
        self._edges = len(graph.links)
        self._candidates = [
            (c.status, None if c.residual_ratio != c.residual_ratio else c.residual_ratio)
            for c in coordinator.candidates
        ]
        self._indexed = 0 if coordinator.retrieval is None else len(coordinator.retrieval.database)
        for table in self._rows:
            self._rows[table] = {
                key: tuple(row) for key, *row in db.execute(f"SELECT * FROM {table}")
            }
        self._updates = {
            agent: sent for agent, sent in db.execute("SELECT agent, updates_sent FROM agents")
        }
        self._finished = json.loads(self._rows["state"].get("finished", ("false",))[0])

    def attach(self, coordinator: Coordinator) -> None:
        """Become ``coordinator``'s journal and store its current state."""
        self._coordinator = coordinator
        coordinator.journal = self
        self.record(coordinator, [])

    def __enter__(self) -> SessionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop recording and close the database: its WAL folded into the file, which is
        left in rollback-journal mode, one self-contained file (a writer that opens it
        again turns WAL on)."""
        if self._coordinator is not None and self._coordinator.journal is self:
            self._coordinator.journal = None
        self._coordinator = None
        try:
            self.connection.execute("PRAGMA journal_mode=DELETE")
        except sqlite3.Error as exc:
            logger.warning("%s: the session store stays in WAL mode (%s)", self.path, exc)
        self.connection.close()

    # ------------------------------------------------------------------ recording

    def record(
        self, coordinator: Coordinator, updates: Sequence[PoseUpdate], finished: bool = False
    ) -> None:
        """Store what changed in ``coordinator`` since the last call, in one transaction.

        Args:
            coordinator: the coordinator after one message's effect.
            updates: the pose updates that effect made (counted per agent).
            finished: the terminal cleanup has run.

        Raises:
            StoreError: the database cannot be written (the store is then unusable: a run
                whose durable state stops being kept fails rather than carry on).
        """
        if self._failed:
            raise StoreError(f"{self.path}: the session store failed earlier")
        for update in updates:
            self._updates[update.agent] = self._updates.get(update.agent, 0) + 1
        try:
            with _transaction(self.connection):
                self._record_keyframes(coordinator)
                self._record_poses(coordinator)
                self._record_retrieval(coordinator)
                self._record_edges(coordinator)
                self._record_candidates(coordinator.candidates)
                self._record_agents(coordinator)
                self._record_state(coordinator, finished)
        except sqlite3.Error as exc:
            self._failed = True
            raise StoreError(f"{self.path}: cannot write the session store ({exc})") from None
        self.transactions += 1
        page_out(coordinator, self)

    # ------------------------------------------------------------------ paging

    def load_keyframe(self, g: int, group: str) -> dict[str, Any]:
        """The current arrays of ``group`` (:data:`como3r.frontend.paging.GROUPS`) of keyframe
        ``g``, read back from the store (a paged-out keyframe's).

        Raises:
            StoreError: the store cannot be read.
        """
        try:
            if group == "pointmaps":
                return self._load_pointmaps(g)
            (blob_id,) = self.connection.execute(
                f"SELECT {group} FROM keyframes WHERE g = ?", (g,)
            ).fetchone()
            data, what = self._read_blob(blob_id), f"keyframe {g} {group}"
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot read the session store ({exc})") from None
        if group == "encoding":
            return {group: unpack_object(data, Encoding, what)}
        return {group: unpack_arrays(data, what)[0].numpy()}

    def _load_pointmaps(self, g: int) -> dict[str, Any]:
        """A keyframe's pointmaps from the blobs last written (one tensor per blob), which
        the store then holds as written."""
        written = self._keyframes[g]
        arrays: dict[int, Tensor] = {}
        for blob_id in written.blobs:
            if blob_id not in arrays:
                (arrays[blob_id],) = unpack_arrays(self._read_blob(blob_id), f"keyframe {g}")
        values = tuple(arrays[b] for b in written.blobs)
        written.arrays = _refs(values)
        return dict(zip(POINTMAP_FIELDS, values))

    def load_matches(self, n: int) -> tuple[DirectedMatches, DirectedMatches]:
        """Both directions' matches of edge ``n``, read back from the store.

        Raises:
            StoreError: the store cannot be read.
        """
        try:
            (blob,) = self.connection.execute(
                "SELECT matches FROM edges WHERE n = ?", (n,)
            ).fetchone()
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot read the session store ({exc})") from None
        arrays = unpack_arrays(blob, f"edge {n} matches")
        return DirectedMatches(*arrays[:3]), DirectedMatches(*arrays[3:])

    def _read_blob(self, blob_id: int) -> bytes:
        (data,) = self.connection.execute(
            "SELECT data FROM blobs WHERE id = ?", (blob_id,)
        ).fetchone()
        return data

    def record_runtime(
        self, state: dict[str, Any] | None, reports: Mapping[int, AgentFinished]
    ) -> None:
        """Store the multi-process runtime's state and the agents' final reports that are
        new, in one transaction (nothing when neither changed).

        Args:
            state: JSON-able (:func:`como3r.runtime.runtime_state.snapshot`); None: no
                runtime state (the single-process runtime keeps none).
            reports: each coordinator agent's final report, where it has one.

        Raises:
            StoreError: as :meth:`record`.
        """
        if self._failed:
            raise StoreError(f"{self.path}: the session store failed earlier")
        rows = {} if state is None else {"runtime": (json.dumps(state),)}
        new = {
            agent: report
            for agent, report in reports.items()
            if self._reports.get(agent) is not report
        }
        if not new and all(self._rows["state"].get(k) == row for k, row in rows.items()):
            return
        try:
            with _transaction(self.connection):
                self._upsert("state", rows)
                self.connection.executemany(
                    "INSERT OR REPLACE INTO reports VALUES (?, ?)",
                    [
                        (agent, self._count("reports", pack_object(report)))
                        for agent, report in new.items()
                    ],
                )
        except sqlite3.Error as exc:
            self._failed = True
            raise StoreError(f"{self.path}: cannot write the session store ({exc})") from None
        self._reports.update(new)
        self.transactions += 1

    def _blob(self, data: bytes, part: str) -> int:
        return int(
            self.connection.execute(
                "INSERT INTO blobs (data) VALUES (?)", (self._count(part, data),)
            ).lastrowid
        )

    def _count(self, part: str, data: bytes) -> bytes:
        """``data``, counted as written for ``part``."""
        self.written[part] += len(data)
        return data

    def written_metrics(self) -> dict[str, Any]:
        """``metrics.json``'s ``store`` entry: the bytes of blobs and text written so far
        (rewrites included; SQLite's pages and WAL add to them), in all, per keyframe and per
        part (``colours``, ``encoding``, ``pointmaps`` (the canonical pointmaps, their
        confidences and intrinsics, written again when they change), ``retrieval``,
        ``poses`` (rewritten when they move), ``edges``, ``candidates``, ``reports``,
        ``state``), and the bytes the store's files hold now (``session.db`` and its WAL)."""
        keyframes = len(self._keyframes)
        total = sum(self.written.values())
        files = sum(
            p.stat().st_size
            for p in (self.path, self.path.with_name(self.path.name + "-wal"))
            if p.is_file()
        )
        return {
            "keyframes": keyframes,
            "bytes_written": total,
            "bytes_written_per_keyframe": total / keyframes if keyframes else None,
            "bytes_written_per_keyframe_by_part": (
                {k: v / keyframes for k, v in sorted(self.written.items())} if keyframes else {}
            ),
            "file_bytes": files,
            "file_bytes_per_keyframe": files / keyframes if keyframes else None,
        }

    def _record_keyframes(self, coordinator: Coordinator) -> None:
        """New keyframes, and the pointmaps of known ones that were replaced."""
        graph = coordinator.graph
        for g, kf in enumerate(graph.keyframes[: len(self._keyframes)]):
            written = self._keyframes[g]
            if isinstance(kf, PagedKeyframe) and not kf.resident("pointmaps"):
                if not kf.served_by(self):
                    # parked by the terminal cleanup (KeyframeParking): the pointmaps it
                    # changed are read back (the others from this store, as written) and
                    # written, one keyframe in memory at a time
                    self._keyframes[g] = self._write_pointmaps(g, kf, written)
                    kf.evict(self, g)
                continue  # else as written: a pointmap that changes is read back first
            if (
                any(b() is not a for a, b in zip(_pointmap_arrays(kf), written.arrays))
                or kf.K is not written.K
                or kf.fused_frames != written.fused_frames
            ):
                self._keyframes[g] = self._write_pointmaps(g, kf, written)
        for g in range(len(self._keyframes), len(graph.keyframes)):
            kf = graph.keyframes[g]
            self.connection.execute(
                "INSERT INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    g,
                    graph.agent_of[g],
                    kf.kf_id,
                    kf.frame_index,
                    kf.timestamp,
                    self._blob(pack_arrays(kf.colors), "colours"),
                    self._blob(pack_object(kf.encoding), "encoding"),
                ),
            )
            self._keyframes.append(self._write_pointmaps(g, kf, None))
            if kf.retrieval is not None:
                self.connection.execute(
                    "INSERT INTO retrieval VALUES (?, ?, ?, NULL, ?)",
                    (
                        g,
                        graph.agent_of[g],
                        kf.kf_id,
                        self._count("retrieval", pack_arrays(*kf.retrieval)),
                    ),
                )

    def _write_pointmaps(self, g: int, kf: Keyframe, before: _Written | None) -> _Written:
        """Write a keyframe's pointmaps row: a blob per distinct array (one for ``X_init``
        and ``X_hat`` while they are the same tensor), the replaced ones deleted."""
        arrays = _pointmap_arrays(kf)
        ids: list[int] = []
        for k, array in enumerate(arrays):
            same = next((ids[m] for m in range(k) if arrays[m] is array), None)
            kept = None if before is None else before.holds(array)
            ids.append(
                same
                if same is not None
                else kept
                if kept is not None
                else self._blob(pack_arrays(array), "pointmaps")
            )
        K = None if kf.K is None else self._count("pointmaps", pack_arrays(kf.K))
        self.connection.execute(
            "INSERT OR REPLACE INTO pointmaps VALUES (?, ?, ?, ?, ?, ?, ?)",
            (g, kf.fused_frames, *ids, K),
        )
        if before is not None:
            self.connection.executemany(
                "DELETE FROM blobs WHERE id = ?", [(b,) for b in set(before.blobs) - set(ids)]
            )
        return _Written(_refs(arrays), tuple(ids), kf.K, kf.fused_frames)

    def _record_poses(self, coordinator: Coordinator) -> None:
        graph = coordinator.graph
        if not len(graph):
            return
        poses = graph.poses(range(len(graph))).detach().cpu()
        known = min(len(self._poses), len(poses))
        moved = (poses[:known] != self._poses[:known].to(poses)).any(dim=1).nonzero()
        changed = [int(g) for g in moved[:, 0]] + list(range(known, len(poses)))
        self.connection.executemany(
            "INSERT OR REPLACE INTO poses VALUES (?, ?)",
            [(g, self._count("poses", pack_arrays(poses[g]))) for g in changed],
        )
        self._poses = poses.clone()

    def _record_retrieval(self, coordinator: Coordinator) -> None:
        """Positions of the keyframes the ASMK database indexed since the last call."""
        if coordinator.retrieval is None:
            return
        keys = coordinator.retrieval.database.keys
        self.connection.executemany(
            "UPDATE retrieval SET position = ? WHERE agent = ? AND kf_id = ?",
            [
                (n, agent, kf_id)
                for n, (agent, kf_id) in enumerate(keys[self._indexed :], self._indexed)
            ],
        )
        self._indexed = len(keys)

    def _record_edges(self, coordinator: Coordinator) -> None:
        links = coordinator.graph.links
        self.connection.executemany(
            "INSERT INTO edges VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            [
                (
                    n,
                    link.i,
                    link.j,
                    link.kind,
                    link.similarity,
                    link.link.covisible_ij,
                    link.link.covisible_ji,
                    self._count("edges", pack_link(link.link)),
                )
                for n, link in enumerate(links[self._edges :], self._edges)
            ],
        )
        self._edges = len(links)

    def _record_candidates(self, candidates: Sequence[Candidate]) -> None:
        """New candidates; the status and residual ratio of known ones that changed."""
        for n, c in enumerate(candidates):
            ratio = None if c.residual_ratio != c.residual_ratio else c.residual_ratio
            if n < len(self._candidates) and self._candidates[n] == (c.status, ratio):
                continue
            v, pending = c.verification, c.status == "pending"
            link = v.link if pending else None
            self.connection.execute(
                "INSERT OR REPLACE INTO candidates VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    n,
                    c.i,
                    c.j,
                    c.status,
                    ratio,
                    v.similarity,
                    v.nu_i,
                    v.nu_j,
                    v.covisible_ratio,
                    int(v.accepted),
                    None if v.link is None else v.link.covisible_ij,
                    None if v.link is None else v.link.covisible_ji,
                    None if link is None else self._count("candidates", pack_link(link)),
                ),
            )
            if n < len(self._candidates):
                self._candidates[n] = (c.status, ratio)
            else:
                self._candidates.append((c.status, ratio))

    def _record_agents(self, coordinator: Coordinator) -> None:
        """Gauge components and per-agent progress."""
        graph = coordinator.graph
        gauges = {agent: (members[0],) for members in coordinator.components() for agent in members}
        agents = {}
        for agent in range(coordinator.num_agents):
            own = graph.agent_keyframes(agent)
            agents[agent] = (
                len(own),
                graph.keyframes[own[-1]].frame_index if own else -1,
                self._updates.get(agent, 0),
                graph.focal.get(agent),
            )
        self._upsert("gauges", gauges)
        self._upsert("agents", agents)

    def _record_state(self, coordinator: Coordinator, finished: bool) -> None:
        new_edges, roots = coordinator.backlog
        self._finished = self._finished or finished
        state = {
            "stats": dataclasses.asdict(coordinator.stats),
            "gauge_events": coordinator.gauge_events,
            "alternation": coordinator.alternation,
            "backlog": {"new_edges": new_edges, "roots": roots},
            "finished": self._finished,
        }
        self._upsert("state", {key: (json.dumps(value),) for key, value in state.items()})

    def _upsert(self, table: str, rows: dict[Any, tuple]) -> None:
        """Write the rows of a small keyed table that differ from what it holds."""
        known = self._rows[table]
        changed = [(key, *row) for key, row in rows.items() if known.get(key) != row]
        if changed:
            text = sum(len(v) for row in changed for v in row[1:] if isinstance(v, (str, bytes)))
            if text:
                self.written[table] += text
            marks = ", ".join("?" * len(changed[0]))
            self.connection.executemany(f"INSERT OR REPLACE INTO {table} VALUES ({marks})", changed)
            known.update((key, tuple(row)) for key, *row in changed)


def _pointmap_arrays(kf: Keyframe) -> tuple[Tensor, ...]:
    return tuple(getattr(kf, name) for name in POINTMAP_FIELDS)


def _refs(arrays: Sequence[Tensor]) -> tuple[weakref.ref, ...]:
    return tuple(weakref.ref(a) for a in arrays)


@contextmanager
def _transaction(connection: sqlite3.Connection) -> Iterator[None]:
    """``BEGIN IMMEDIATE`` ... ``COMMIT``; rolled back on any error."""
    connection.execute("BEGIN IMMEDIATE")
    try:
        yield
    except BaseException:
        if connection.in_transaction:  # SQLite rolled back already on a full disk
            connection.execute("ROLLBACK")
        raise
    connection.execute("COMMIT")
