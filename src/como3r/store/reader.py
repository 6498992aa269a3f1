"""Reading a session store back (:mod:`como3r.store.writer`, issue 14).

:func:`read_session` opens ``session.db`` (of a finished run, or of a run killed at any
moment), checks that it is a como3r store of the format version this como3r reads and that
it is intact and consistent, and loads it into the objects the coordinator works with: a
:class:`~como3r.backend.global_graph.GlobalGraph` (keyframes with pointmaps, encodings and
current poses; sequential and inter-agent links with their matches; focal lengths), the
:class:`~como3r.coordination.gauge.GaugeComponents`, the retrieval entries in the order the
ASMK database indexed them, the candidates (with their matches while pending), the
per-agent progress and the configuration. Anything else is one
:class:`~como3r.errors.StoreError` line.
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from torch import Tensor

from como3r.backend.global_graph import GlobalGraph, GraphLink
from como3r.config import Config, config_from_dict, validate
from como3r.coordination.gauge import GaugeComponents
from como3r.errors import Como3rError, StoreError
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.paging import PagedKeyframe
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.prior.base import Encoding
from como3r.store.blobs import unpack_arrays, unpack_object
from como3r.store.paging import PagedLink
from como3r.store.schema import APPLICATION_ID, FORMAT_VERSION, STORE_NAME
from como3r.transport.messages import AgentFinished

logger = logging.getLogger(__name__)

T = TypeVar("T")

STATUSES = ("rejected", "pending", "admitted", "inconsistent")
#: the edges' matches read when their session is read paged: the inter-agent edges' only
PAGED_MATCHES = "CASE kind WHEN 'inter' THEN matches END"
KINDS = ("sequential", "inter")


@dataclass(frozen=True)
class RetrievalEntry:
    """One keyframe's retrieval features.

    Attributes:
        agent, kf_id: the keyframe.
        descriptors: ``(N, d)`` its retrieval descriptors.
        attention: ``(N,)`` their attention.
        position: its place in the coordinator's ASMK database (insertion order), None if
            it was not indexed (cross-agent retrieval off).
    """

    agent: int
    kf_id: int
    descriptors: Tensor
    attention: Tensor
    position: int | None


@dataclass(frozen=True)
class StoredCandidate:
    """A verified or rejected cross-agent candidate as graph.json reports it.

    Attributes:
        i, j: global indices of the candidate (retrieved) and query (new) keyframes.
        status: ``"rejected"``, ``"pending"``, ``"admitted"`` or ``"inconsistent"``.
        residual_ratio: the last consistency test's measure, None if untested.
        similarity, nu_i, nu_j, covisible_ratio, accepted: the verification's figures.
        link: both directions' matches while pending (a waiting edge), else None.
    """

    i: int
    j: int
    status: str
    residual_ratio: float | None
    similarity: float
    nu_i: float | None
    nu_j: float
    covisible_ratio: float | None
    accepted: bool
    link: PairLink | None


@dataclass(frozen=True)
class AgentRecord:
    """Per-agent progress.

    Attributes:
        agent: the coordinator's agent id.
        keyframes: keyframes stored.
        last_keyframe_frame: frame index of the last of them (-1: none).
        updates_sent: pose updates the coordinator made for it (the last one's seq).
        focal: its focal length in the map [px], None until aligned.
    """

    agent: int
    keyframes: int
    last_keyframe_frame: int
    updates_sent: int
    focal: float | None


@dataclass
class Session:
    """A session store's contents.

    Attributes:
        path: the store.
        config: the run's effective configuration.
        meta: ``format_version``, ``como3r_version``, ``created``.
        graph: keyframes (global order), their links and the agents' focal lengths.
        gauges: the gauge components.
        agents: per-agent progress, by agent id (every agent of the coordinator).
        retrieval: retrieval entries of the keyframes that had features, in keyframe order.
        candidates: every verification, in order.
        stats: the coordinator's counters (``CoordinatorStats`` as a dict).
        gauge_events, alternation: as in metrics.json.
        backlog: ``(inter edges since the last in-stream BA, their component roots)``.
        finished: the terminal cleanup ran.
        runtime: the multi-process runtime's state (:mod:`como3r.runtime.runtime_state`), None if no
            such runtime wrote the store.
        reports: each coordinator agent's final report, where its process sent one.
    """

    path: Path
    config: Config
    meta: dict[str, str]
    graph: GlobalGraph
    gauges: GaugeComponents
    agents: list[AgentRecord]
    retrieval: list[RetrievalEntry] = field(default_factory=list)
    candidates: list[StoredCandidate] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    gauge_events: list[dict[str, Any]] = field(default_factory=list)
    alternation: list[dict[str, Any]] = field(default_factory=list)
    backlog: tuple[int, list[int]] = (0, [])
    finished: bool = False
    runtime: dict[str, Any] | None = None
    reports: dict[int, AgentFinished] = field(default_factory=dict)


def read_session(path: str | Path, paged: bool = False) -> Session:
    """Load a session store.

    Args:
        paged: leave the keyframes' encodings, images and pointmaps and the sequential
            edges' matches in the store (:class:`~como3r.frontend.paging.PagedKeyframe`,
            :class:`~.paging.PagedLink`; they read nothing until the store that
            continues the session, :meth:`~.writer.SessionStore.reopen`, serves them): a
            resumed session takes the memory of its working set, not of its whole map.

    Raises:
        StoreError: no file, not a como3r session store, another format version,
            corrupted, or inconsistent (one line naming the file and what is wrong).
    """
    path = Path(path)
    return _read(path, lambda connection: _load(connection, path, paged), check=True)


def read_config(path: str | Path) -> Config:
    """Only the configuration of a session store (without checking the rest of it).

    Raises:
        StoreError: as :func:`read_session`.
    """
    path = Path(path)
    return _read(path, lambda connection: _meta(connection, path)[1], check=False)


def resumable(folder: str | Path, finished: bool = False) -> bool:
    """Whether ``folder`` has a session store a run can be resumed from, work that only
    ``--overwrite`` deletes: one holding a keyframe, whose terminal cleanup has not run
    (with ``finished``, whose has too: ``como3r coordinator --resume`` writes its outputs),
    or one that cannot be read (``--resume`` then says what is wrong)."""
    path = Path(folder) / STORE_NAME
    if not path.is_file():
        return False

    def load(connection: sqlite3.Connection) -> bool:
        done = connection.execute("SELECT value FROM state WHERE key = 'finished'").fetchone()
        held = connection.execute("SELECT EXISTS (SELECT 1 FROM keyframes)").fetchone()[0]
        return held == 1 and (finished or done is None or not json.loads(done[0]))

    try:
        return _read(path, load, check=False)
    except StoreError:
        return True


def _read(path: Path, load: Callable[[sqlite3.Connection], T], check: bool) -> T:
    """``load`` on the store at ``path`` opened read-only, in one snapshot, after its header
    (and with ``check`` its structure) was checked; every error as one StoreError line."""
    if not path.is_file():
        raise StoreError(f"{path}: no session store there")
    try:
        connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True, isolation_level=None)
    except sqlite3.Error as exc:
        raise StoreError(f"{path}: cannot open the session store ({exc})") from None
    try:
        connection.execute("BEGIN")  # one snapshot, even while a run still writes
        try:
            _check_header(connection, path, check)
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"{path}: not a como3r session store, or corrupted ({_one_line(exc)})"
            ) from None
        return load(connection)
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"{path}: corrupted session store ({_one_line(exc)})") from None
    except StoreError as exc:
        message = str(exc)
        raise StoreError(
            message if message.startswith(str(path)) else f"{path}: {message}"
        ) from None
    except Como3rError as exc:
        raise StoreError(f"{path}: {_one_line(exc)}") from None
    finally:
        connection.close()


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _check_header(connection: sqlite3.Connection, path: Path, check: bool) -> None:
    """A como3r store of :data:`FORMAT_VERSION`; with ``check``, structurally intact."""
    (application,) = connection.execute("PRAGMA application_id").fetchone()
    (version,) = connection.execute("PRAGMA user_version").fetchone()
    if application != APPLICATION_ID:
        raise StoreError(f"{path}: not a como3r session store")
    if version > FORMAT_VERSION:
        raise StoreError(
            f"{path}: session store format version {version} is newer than "
            f"this como3r reads ({FORMAT_VERSION}); upgrade como3r"
        )
    if version != FORMAT_VERSION:
        raise StoreError(
            f"{path}: session store format version {version} is not the one "
            f"this como3r reads ({FORMAT_VERSION})"
        )
    problems = [
        " ".join(row[0].split())
        for row in connection.execute("PRAGMA quick_check" if check else "SELECT 'ok'")
    ]
    if problems != ["ok"]:
        raise StoreError(f"{path}: corrupted session store ({'; '.join(problems[:3])})")


def _meta(connection: sqlite3.Connection, path: Path) -> tuple[dict[str, str], Config]:
    """The meta table (without the configuration) and the configuration."""
    meta = dict(connection.execute("SELECT key, value FROM meta"))
    if meta.get("format_version") != str(FORMAT_VERSION) or "config" not in meta:
        raise StoreError(
            f"{path}: inconsistent session store (its meta table says format "
            f"{meta.get('format_version')!r})"
        )
    return meta, validate(config_from_dict(Config, json.loads(meta.pop("config"))))


def _load(connection: sqlite3.Connection, path: Path, paged: bool) -> Session:
    meta, config = _meta(connection, path)
    state = {key: json.loads(value) for key, value in connection.execute("SELECT * FROM state")}
    graph = GlobalGraph(config.tracking, config.global_ba)
    blobs = _Blobs(connection)
    if paged:
        _page_keyframes(connection, graph)
    else:
        _load_keyframes(connection, graph, blobs)
    agents = [
        AgentRecord(*row) for row in connection.execute("SELECT * FROM agents ORDER BY agent")
    ]
    graph.focal = {a.agent: a.focal for a in agents if a.focal is not None}
    graph.links = [
        _link(row, len(graph), paged)
        for row in connection.execute(
            "SELECT i, j, kind, similarity, covisible_ij, covisible_ji, "
            f"{PAGED_MATCHES if paged else 'matches'}, "
            "n FROM edges ORDER BY n"
        )
    ]
    session = Session(
        path=path,
        config=config,
        meta=meta,
        graph=graph,
        gauges=_gauges(connection, len(agents)),
        agents=agents,
        retrieval=_retrieval(connection, graph),
        candidates=[
            _candidate(row, len(graph))
            for row in connection.execute("SELECT * FROM candidates ORDER BY n")
        ],
        stats=state.get("stats", {}),
        gauge_events=state.get("gauge_events", []),
        alternation=state.get("alternation", []),
        backlog=(
            state.get("backlog", {}).get("new_edges", 0),
            state.get("backlog", {}).get("roots", []),
        ),
        finished=bool(state.get("finished", False)),
        runtime=state.get("runtime"),
        reports={
            agent: unpack_object(blob, AgentFinished, f"agent {agent}'s final report")
            for agent, blob in connection.execute("SELECT * FROM reports")
        },
    )
    _check_agents(session)
    return session


class _Blobs:
    """The ``blobs`` table, read by id."""

    def __init__(self, connection: sqlite3.Connection) -> None:
        self.connection = connection

    def get(self, blob_id: int, what: str) -> bytes:
        row = self.connection.execute("SELECT data FROM blobs WHERE id = ?", (blob_id,)).fetchone()
        if row is None:
            raise StoreError(f"inconsistent session store: {what} refers to a missing blob")
        return row[0]

    def array(self, blob_id: int, what: str) -> Tensor:
        arrays = unpack_arrays(self.get(blob_id, what), what)
        if len(arrays) != 1:
            raise StoreError(f"{what}: holds {len(arrays)} arrays, not one")
        return arrays[0]


def _load_keyframes(connection: sqlite3.Connection, graph: GlobalGraph, blobs: _Blobs) -> None:
    rows = connection.execute(
        "SELECT k.g, k.agent, k.kf_id, k.frame_index, k.timestamp, k.colors, k.encoding, "
        "m.fused_frames, m.X_hat, m.C_hat, m.X_init, m.C_init, m.K, p.T_WC "
        "FROM keyframes k LEFT JOIN pointmaps m USING (g) LEFT JOIN poses p USING (g) "
        "ORDER BY k.g"
    )
    for (
        g,
        agent,
        kf_id,
        frame,
        timestamp,
        colors,
        encoding,
        fused,
        X_hat,
        C_hat,
        X_init,
        C_init,
        K,
        T_WC,
    ) in rows:
        what = _check_keyframe(graph, g, agent, kf_id, fused, T_WC)
        maps = {}
        for name, blob_id in (
            ("X_hat", X_hat),
            ("C_hat", C_hat),
            ("X_init", X_init),
            ("C_init", C_init),
        ):  # one tensor per blob, as written
            maps.setdefault(blob_id, blobs.array(blob_id, f"{what} {name}"))
        (pose,) = unpack_arrays(T_WC, f"{what} T_WC")
        graph.append(
            Keyframe(
                kf_id=kf_id,
                frame_index=frame,
                timestamp=timestamp,
                encoding=unpack_object(blobs.get(encoding, what), Encoding, f"{what} encoding"),
                T_WC=pose,
                X_hat=maps[X_hat],
                C_hat=maps[C_hat],
                X_init=maps[X_init],
                C_init=maps[C_init],
                colors=blobs.array(colors, f"{what} colors").numpy(),
                fused_frames=fused,
                K=None if K is None else unpack_arrays(K, f"{what} K")[0],
            ),
            agent,
        )


def _check_keyframe(
    graph: GlobalGraph, g: int, agent: int, kf_id: int, fused: int | None, T_WC: bytes | None
) -> str:
    """Keyframe ``g`` comes next, with its pointmaps and pose; returns how errors name it."""
    what = f"keyframe {g} (agent {agent}, kf {kf_id})"
    if g != len(graph) or kf_id != len(graph.local_to_global.get(agent, [])):
        raise StoreError(f"inconsistent session store: {what} out of order")
    if fused is None or T_WC is None:
        raise StoreError(
            f"inconsistent session store: {what} has no {'pointmaps' if fused is None else 'pose'}"
        )
    return what


def _page_keyframes(connection: sqlite3.Connection, graph: GlobalGraph) -> None:
    """The keyframes without their large arrays (:class:`~como3r.frontend.paging.PagedKeyframe`),
    after checking that every blob they refer to is there."""
    (missing,) = connection.execute(
        "SELECT COUNT(*) FROM (SELECT colors AS id FROM keyframes UNION SELECT encoding FROM "
        "keyframes UNION SELECT X_hat FROM pointmaps UNION SELECT C_hat FROM pointmaps UNION "
        "SELECT X_init FROM pointmaps UNION SELECT C_init FROM pointmaps) "
        "WHERE id NOT IN (SELECT id FROM blobs)"
    ).fetchone()
    if missing:
        raise StoreError(
            f"inconsistent session store: {missing} keyframe arrays refer to missing blobs"
        )
    rows = connection.execute(
        "SELECT k.g, k.agent, k.kf_id, k.frame_index, k.timestamp, m.fused_frames, m.K, "
        "p.T_WC FROM keyframes k LEFT JOIN pointmaps m USING (g) LEFT JOIN poses p USING (g) "
        "ORDER BY k.g"
    )
    for g, agent, kf_id, frame, timestamp, fused, K, T_WC in rows:
        what = _check_keyframe(graph, g, agent, kf_id, fused, T_WC)
        (pose,) = unpack_arrays(T_WC, f"{what} T_WC")
        kf = PagedKeyframe(
            kf_id=kf_id,
            frame_index=frame,
            timestamp=timestamp,
            encoding=None,
            T_WC=pose,
            X_hat=None,
            C_hat=None,
            X_init=None,
            C_init=None,
            colors=None,
            fused_frames=fused,
            K=None if K is None else unpack_arrays(K, f"{what} K")[0],
        )
        kf.evict(None, g)
        graph.append(kf, agent)


def _retrieval(connection: sqlite3.Connection, graph: GlobalGraph) -> list[RetrievalEntry]:
    entries = []
    for g, agent, kf_id, position, features in connection.execute(
        "SELECT * FROM retrieval ORDER BY g"
    ):
        if g >= len(graph) or (graph.agent_of[g], graph.keyframes[g].kf_id) != (agent, kf_id):
            raise StoreError(
                f"inconsistent session store: retrieval entry {g} names no such keyframe"
            )
        descriptors, attention = unpack_arrays(features, f"keyframe {g} retrieval features")
        graph.keyframes[g].retrieval = (descriptors, attention)
        entries.append(RetrievalEntry(agent, kf_id, descriptors, attention, position))
    positions = sorted(e.position for e in entries if e.position is not None)
    if positions != list(range(len(positions))):
        raise StoreError("inconsistent session store: retrieval positions have gaps")
    return entries


def _matches(blob: bytes, what: str) -> tuple[DirectedMatches, DirectedMatches]:
    arrays = unpack_arrays(blob, what)
    if len(arrays) != 6:
        raise StoreError(f"{what}: holds {len(arrays)} arrays, not 6")
    return DirectedMatches(*arrays[:3]), DirectedMatches(*arrays[3:])


def _link(row: tuple, keyframes: int, paged: bool) -> GraphLink:
    i, j, kind, similarity, covisible_ij, covisible_ji, blob, n = row
    if kind not in KINDS or not (0 <= i < keyframes and 0 <= j < keyframes):
        raise StoreError(f"inconsistent session store: edge {n} ({kind} {i}-{j})")
    if paged and kind == "sequential":
        return GraphLink(i, j, kind, PagedLink(None, n, covisible_ij, covisible_ji), similarity)
    ij, ji = _matches(blob, f"edge {n} matches")
    return GraphLink(i, j, kind, PairLink(ij, ji, covisible_ij, covisible_ji), similarity)


def _candidate(row: tuple, keyframes: int) -> StoredCandidate:
    (
        n,
        i,
        j,
        status,
        ratio,
        similarity,
        nu_i,
        nu_j,
        covisible_ratio,
        accepted,
        covisible_ij,
        covisible_ji,
        blob,
    ) = row
    if (
        status not in STATUSES
        or not (0 <= i < keyframes and 0 <= j < keyframes)
        or (status == "pending") != (blob is not None)
    ):
        raise StoreError(f"inconsistent session store: candidate {n} ({status} {i}-{j})")
    link = None
    if blob is not None:
        link = PairLink(*_matches(blob, f"candidate {n} matches"), covisible_ij, covisible_ji)
    return StoredCandidate(
        i, j, status, ratio, similarity, nu_i, nu_j, covisible_ratio, bool(accepted), link
    )


def _gauges(connection: sqlite3.Connection, agents: int) -> GaugeComponents:
    gauges = GaugeComponents()
    rows = list(connection.execute("SELECT agent, component FROM gauges ORDER BY agent"))
    roots = {agent: root for agent, root in rows}
    if sorted(roots) != list(range(agents)) or any(
        roots.get(root) != root or root > agent for agent, root in rows
    ):
        raise StoreError("inconsistent session store: gauge components")
    for agent, root in rows:
        gauges.add(agent)
        gauges.union(root, agent)
    return gauges


def _check_agents(session: Session) -> None:
    """Per-agent progress agrees with the keyframes stored."""
    graph = session.graph
    if [a.agent for a in session.agents] != list(range(len(session.agents))) or any(
        agent >= len(session.agents) for agent in [*graph.local_to_global, *session.reports]
    ):
        raise StoreError("inconsistent session store: the agents table")
    for a in session.agents:
        own = graph.agent_keyframes(a.agent)
        last = graph.keyframes[own[-1]].frame_index if own else -1
        if (a.keyframes, a.last_keyframe_frame) != (len(own), last):
            raise StoreError(
                f"inconsistent session store: agent {a.agent} has "
                f"{len(own)} keyframes stored, its progress says {a.keyframes}"
            )
    if session.stats.get("keyframes", len(graph)) != len(graph):
        raise StoreError("inconsistent session store: the coordinator's keyframe count")
