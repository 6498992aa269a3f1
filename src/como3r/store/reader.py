"""Reading a session store back (:mod:`como3r.store.writer`, issue 14).

:func:`read_session` opens ``session.db`` (of a finished run, or of a run killed at any
moment), checks that it is a como3r store of the format version this como3r reads and that
it is intact and consistent, and loads it into the objects the coordinator works with: a
:class:`~como3r.backend.global_graph.GlobalGraph` (keyframes with pointmaps, encodings where
stored, and current poses; sequential and inter-agent links with their matches; focal
lengths), the :class:`~como3r.coordination.gauge.GaugeComponents`, the retrieval entries in
the order the ASMK database indexed them, the candidates (with their matches while
pending), the per-agent progress and the configuration. Anything else is one
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

from como3r.backend.global_graph import GlobalGraph
from como3r.config import Config, config_from_dict, validate
from como3r.coordination.gauge import GaugeComponents
from como3r.errors import Como3rError, StoreError
from como3r.store.blobs import unpack_object
from como3r.store.rows import (
    PAGED_MATCHES,
    AgentRecord,
    Blobs,
    RetrievalEntry,
    StoredCandidate,
    load_keyframes,
    page_keyframes,
    read_candidate,
    read_gauges,
    read_link,
    read_retrieval,
)
from como3r.store.schema import APPLICATION_ID, FORMAT_VERSION, READABLE_VERSIONS, STORE_NAME
from como3r.transport.messages import AgentFinished

logger = logging.getLogger(__name__)

T = TypeVar("T")


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
        refused: the edges refused inside a gauge that await their recheck after the next
            in-stream global BA, ``(candidate index, refused by the scale watch)`` in the
            order they are tested (since version 8; none in older stores).
        deferred: the keyframes a batch budget deferred, not verified yet, oldest first, as
            ``(agent, kf_id, [(hit agent, hit keyframe, similarity), ...])`` (since
            version 9; none in older stores).
        finished: the terminal cleanup ran.
        runtime: the multi-process runtime's state (:mod:`como3r.runtime.runtime_state`),
            None if no such runtime wrote the store.
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
    refused: list[tuple[int, bool]] = field(default_factory=list)
    deferred: list[tuple[int, int, list[tuple[int, int, float]]]] = field(default_factory=list)
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
    """A como3r store of a format version this como3r reads (:data:`READABLE_VERSIONS`);
    with ``check``, structurally intact."""
    (application,) = connection.execute("PRAGMA application_id").fetchone()
    (version,) = connection.execute("PRAGMA user_version").fetchone()
    if application != APPLICATION_ID:
        raise StoreError(f"{path}: not a como3r session store")
    if version > FORMAT_VERSION:
        raise StoreError(
            f"{path}: session store format version {version} is newer than "
            f"this como3r reads ({FORMAT_VERSION}); upgrade como3r"
        )
    if version not in READABLE_VERSIONS:
        raise StoreError(
            f"{path}: session store format version {version} is older than this como3r "
            f"reads ({', '.join(map(str, READABLE_VERSIONS))}); read it with the como3r "
            f"that wrote it (the file is left as it is)"
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
    if (
        meta.get("format_version") not in [str(v) for v in READABLE_VERSIONS]
        or "config" not in meta
    ):
        raise StoreError(
            f"{path}: inconsistent session store (its meta table says format "
            f"{meta.get('format_version')!r})"
        )
    return meta, validate(config_from_dict(Config, json.loads(meta.pop("config"))))


def _load(connection: sqlite3.Connection, path: Path, paged: bool) -> Session:
    meta, config = _meta(connection, path)
    state = {key: json.loads(value) for key, value in connection.execute("SELECT * FROM state")}
    graph = GlobalGraph(config.tracking, config.global_ba)
    blobs = Blobs(connection)
    if paged:
        page_keyframes(connection, graph)
    else:
        load_keyframes(connection, graph, blobs)
    agents = [
        AgentRecord(*row) for row in connection.execute("SELECT * FROM agents ORDER BY agent")
    ]
    graph.focal = {a.agent: a.focal for a in agents if a.focal is not None}
    graph.own_focal = {a.agent: a.own_focal for a in agents if a.own_focal is not None}
    graph.links = [
        read_link(row, len(graph), paged)
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
        gauges=read_gauges(connection, len(agents)),
        agents=agents,
        retrieval=read_retrieval(connection, graph),
        candidates=[
            read_candidate(row, len(graph))
            for row in connection.execute("SELECT * FROM candidates ORDER BY n")
        ],
        stats=state.get("stats", {}),
        gauge_events=state.get("gauge_events", []),
        alternation=state.get("alternation", []),
        backlog=(
            state.get("backlog", {}).get("new_edges", 0),
            state.get("backlog", {}).get("roots", []),
        ),
        refused=[(int(n), bool(by_scale)) for n, by_scale in state.get("refused", [])],
        deferred=[
            (int(agent), int(kf_id), [(int(a), int(k), float(s)) for a, k, s in hits])
            for agent, kf_id, hits in state.get("deferred", [])
        ],
        finished=bool(state.get("finished", False)),
        runtime=state.get("runtime"),
        reports={
            agent: unpack_object(blob, AgentFinished, f"agent {agent}'s final report")
            for agent, blob in connection.execute("SELECT * FROM reports")
        },
    )
    _check_agents(session)
    _check_refused(session)
    _check_deferred(session)
    return session


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


def _check_deferred(session: Session) -> None:
    """The deferred keyframes and their hits are stored keyframes."""
    graph, agents = session.graph, len(session.agents)
    for agent, kf_id, hits in session.deferred:
        for a, k in [(agent, kf_id), *((a, k) for a, k, _ in hits)]:
            if not (0 <= a < agents and 0 <= k < len(graph.agent_keyframes(a))):
                raise StoreError("inconsistent session store: the deferred keyframes")


def _check_refused(session: Session) -> None:
    """The edges awaiting their recheck are the inconsistent candidates stored with their
    matches, each once."""
    awaiting = [n for n, _ in session.refused]
    kept = [
        n
        for n, c in enumerate(session.candidates)
        if c.status == "inconsistent" and c.link is not None
    ]
    if sorted(awaiting) != kept:
        raise StoreError("inconsistent session store: the edges awaiting their recheck")
