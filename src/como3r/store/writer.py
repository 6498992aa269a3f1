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

Its layout is :mod:`.schema`'s. A reader refuses a file that is not such a store, is
corrupted, or has another format version, with one :class:`~como3r.errors.StoreError` line. The store is created complete
(schema and configuration in a file renamed into place), so it never exists half-made;
while it is written ``session.db-wal`` and ``session.db-shm`` sit beside it (a killed run
leaves them: they hold its last transactions), and closing it folds them back into one file.
"""

from __future__ import annotations

import datetime
import json
import logging
import sqlite3
import weakref
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from como3r import __version__
from como3r.config import Config, config_to_dict
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.packets import PoseUpdate
from como3r.frontend.paging import POINTMAP_FIELDS, PagedKeyframe
from como3r.frontend.pairs import DirectedMatches
from como3r.prior.base import Encoding
from como3r.store.ahead import Ahead
from como3r.store.blobs import pack_object, unpack_object
from como3r.store.coded import unpack_matches, unpack_one
from como3r.store.paging import PagedLink, page_out
from como3r.store.schema import APPLICATION_ID, FORMAT_VERSION, PAGE_SIZE, SCHEMA
from como3r.store.tables import TableWriter, Written, candidate_rows, pointmap_arrays, refs
from como3r.transport.messages import AgentFinished

logger = logging.getLogger(__name__)

#: edges whose matches :meth:`SessionStore.load_matches` keeps after reading them (a
#: solve's factor batch reads 8 edges twice: their match counts, then their matches)
RECENT_EDGES = 16


class SessionStore(TableWriter):
    """The coordinator's journal: its state in ``session.db``, one transaction per message.

    Made by :meth:`create`; as a context manager it is the coordinator's journal until the
    block ends, then closed (before the output folder is renamed into place).

    Args:
        connection: the open database (WAL, autocommit: transactions are explicit).
        path: its file.
        settles: a pointmap its coding does not give back unchanged is written coded and
            the coordinator takes the coded value in its place (:mod:`.coded`; a run's
            store, :func:`~.resume.open_store`); else it is written exact.
    """

    def __init__(self, connection: sqlite3.Connection, path: Path, settles: bool = False) -> None:
        self.connection = connection
        self.path = path
        self.settles = settles
        self.transactions = 0
        self._coordinator: Coordinator | None = None
        self._failed = False
        self._finished = False
        self._keyframes: list[Written] = []
        self._poses = torch.zeros(0, 8)
        self._edges = 0
        self._candidates: list[tuple[str, float | None, bool]] = []
        self._indexed = 0
        self._rows: dict[str, dict[Any, tuple]] = {"gauges": {}, "agents": {}, "state": {}}
        self._updates: dict[int, int] = {}
        self._reports: dict[int, AgentFinished] = {}
        self._width = 1
        self.ahead = Ahead()
        self._recent: OrderedDict[int, tuple[DirectedMatches, DirectedMatches]] = OrderedDict()
        #: bytes of blobs and text written, per part (:meth:`written_metrics`)
        self.written: Counter[str] = Counter()
        #: called after each :meth:`record` has committed (a disk guard)
        self.on_commit: Callable[[SessionStore], None] | None = None

    @classmethod
    def create(
        cls,
        path: str | Path,
        config: Config,
        coordinator: Coordinator | None = None,
        settles: bool = False,
    ) -> SessionStore:
        """A new store at ``path`` (which must not exist) holding ``config``; it becomes
        ``coordinator``'s journal and takes its current state at once (``settles``: as
        the class says).

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
            # the pages of replaced blobs (refreshed, refined pointmaps) go back to the
            # file system when the store is closed (:meth:`close`)
            connection.execute("PRAGMA auto_vacuum=INCREMENTAL")
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
        store = cls(connection, path, settles)
        if coordinator is not None:
            store.attach(coordinator)
        return store

    @classmethod
    def reopen(
        cls, path: str | Path, coordinator: Coordinator, settles: bool = False
    ) -> SessionStore:
        """The store at ``path`` written on by ``coordinator``, which holds its state already
        (:func:`como3r.store.resume.open_store` restored it); a WAL left by a killed
        writer is recovered on opening (``settles``: as the class says).

        Raises:
            StoreError: the store cannot be opened for writing.
        """
        path = Path(path)
        try:
            connection = sqlite3.connect(path, isolation_level=None)
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute("PRAGMA synchronous=NORMAL")
            _upgrade(connection, path)
            store = cls(connection, path, settles)
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
                arrays = refs(pointmap_arrays(kf))
                self._width = int(kf.X_hat.shape[1])
            self._keyframes.append(Written(arrays, tuple(ids), kf.K, kf.fused_frames))
        for link in graph.links:
            if isinstance(link.link, PagedLink):
                link.link.serve(self)
        if len(graph):
            self._poses = graph.poses(range(len(graph))).detach().cpu().clone()
        self._edges = len(graph.links)
        self._candidates = candidate_rows(coordinator)
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
        self.ahead.close()
        try:
            self.connection.execute("PRAGMA incremental_vacuum")
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
        self.prepare(coordinator)  # what is not coded yet is coded in parallel
        try:
            with _transaction(self.connection):
                self._record_keyframes(coordinator)
                self._record_poses(coordinator)
                self._record_retrieval(coordinator)
                self._record_edges(coordinator)
                self._record_candidates(coordinator)
                self._record_agents(coordinator)
                self._record_state(coordinator, finished)
        except sqlite3.Error as exc:
            self._failed = True
            raise StoreError(f"{self.path}: cannot write the session store ({exc})") from None
        finally:
            self.ahead.drop()
        self.transactions += 1
        page_out(coordinator, self)
        if self.on_commit is not None:
            self.on_commit(self)

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
            if blob_id is None:  # an encoding not kept: the coordinator encodes it again
                return {group: None}
            data, what = self._read_blob(blob_id), f"keyframe {g} {group}"
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot read the session store ({exc})") from None
        if group == "encoding":
            return {group: unpack_object(data, Encoding, what)}
        return {group: unpack_one(data, what).numpy()}

    def _load_pointmaps(self, g: int) -> dict[str, Any]:
        """A keyframe's pointmaps from the blobs last written (one tensor per blob), which
        the store then holds as written."""
        written = self._keyframes[g]
        arrays: dict[int, Tensor] = {}
        for blob_id in written.blobs:
            if blob_id not in arrays:
                arrays[blob_id] = unpack_one(self._read_blob(blob_id), f"keyframe {g}")
        values = tuple(arrays[b] for b in written.blobs)
        written.arrays = refs(values)
        return dict(zip(POINTMAP_FIELDS, values))

    def load_matches(self, n: int) -> tuple[DirectedMatches, DirectedMatches]:
        """Both directions' matches of edge ``n``, read back from the store; the last
        :data:`RECENT_EDGES` edges read are kept (a solve reads a paged edge's directions
        one array at a time: :class:`~.paging.PagedDirection`).

        Raises:
            StoreError: the store cannot be read.
        """
        if n in self._recent:
            self._recent.move_to_end(n)
            return self._recent[n]
        try:
            (blob,) = self.connection.execute(
                "SELECT matches FROM edges WHERE n = ?", (n,)
            ).fetchone()
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot read the session store ({exc})") from None
        arrays = unpack_matches(blob, f"edge {n} matches")
        matches = DirectedMatches(*arrays[:3]), DirectedMatches(*arrays[3:])
        self._recent[n] = matches
        while len(self._recent) > RECENT_EDGES:
            self._recent.popitem(last=False)
        return matches

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


def _upgrade(connection: sqlite3.Connection, path: Path) -> None:
    """Mark an older store this como3r reads (:data:`~.schema.READABLE_VERSIONS`) as of
    :data:`~.schema.FORMAT_VERSION` before it is written on (its blobs stay as they are;
    one of format 6 or older gets the ``agents.own_focal`` column, NULL until written)."""
    (version,) = connection.execute("PRAGMA user_version").fetchone()
    if version == FORMAT_VERSION:
        return
    logger.warning(
        "%s: session store format version %d upgraded to %d in place (what it holds is "
        "kept as it is; a como3r older than this one no longer reads it)",
        path,
        version,
        FORMAT_VERSION,
    )
    with _transaction(connection):
        columns = {row[1] for row in connection.execute("PRAGMA table_info(agents)")}
        if "own_focal" not in columns:
            connection.execute("ALTER TABLE agents ADD COLUMN own_focal REAL")
        connection.execute(
            "UPDATE meta SET value = ? WHERE key = 'format_version'", (str(FORMAT_VERSION),)
        )
        connection.execute(f"PRAGMA user_version={FORMAT_VERSION}")


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
