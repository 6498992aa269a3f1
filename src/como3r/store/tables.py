"""What one transaction of the session store writes, table by table
(:class:`~como3r.store.writer.SessionStore` is a :class:`TableWriter`; the tables are
:mod:`.schema`'s): new keyframes and replaced pointmaps, moved poses, retrieval positions,
new edges, changed candidates, gauges and per-agent progress, the coordinator's state.
Each writer compares with what the store holds already (kept here, so nothing is read back)
and writes only what changed.
"""

from __future__ import annotations

import dataclasses
import json
import sqlite3
import weakref
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from torch import Tensor

from como3r.backend.global_graph import GlobalGraph
from como3r.coordination.association import Candidate
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.paging import POINTMAP_FIELDS, PagedKeyframe
from como3r.frontend.pairs import PairLink
from como3r.store.ahead import Ahead
from como3r.store.blobs import pack_arrays, pack_object
from como3r.store.coded import (
    pack_colours,
    pack_matches,
    pack_pointmap,
    pack_retrieval,
    settle_matches,
)
from como3r.transport import codec_reuse


def pack_link(link: PairLink, width: int) -> bytes:
    """Both directions' matches of a link in one blob (the ``matches`` columns; ``width``:
    the keyframes' row length, which the coding's offsets are split by)."""
    return pack_matches(link.ij, link.ji, width)


@dataclass
class Written:
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


def _settle_candidates(candidates: Sequence[Candidate], old: PairLink, new: PairLink) -> None:
    """The candidates whose verification holds ``old`` (the one admitted with it) hold
    ``new`` in its place, as a resumed coordinator's do (their edge's, read back)."""
    for c in candidates:
        v = c.verification
        if v.link is old:
            c.verification = dataclasses.replace(v, link=new, ij=new.ij if v.ij is old.ij else v.ij)


def candidate_rows(coordinator: Coordinator) -> list[tuple[str, float | None, bool]]:
    """What the store keeps of each of ``coordinator.candidates`` beyond its verification's
    figures: its status, residual ratio (None for NaN) and whether it awaits its recheck
    (:meth:`~como3r.coordination.linking.InterAgentLinking.refused_edges`)."""
    awaiting = {n for n, _ in coordinator.refused_edges()}
    return [
        (
            c.status,
            None if c.residual_ratio != c.residual_ratio else c.residual_ratio,
            n in awaiting,
        )
        for n, c in enumerate(coordinator.candidates)
    ]


class TableWriter:
    """The per-table writes of :meth:`~como3r.store.writer.SessionStore.record`, and what
    the store holds already that they compare with (set up by the store)."""

    connection: sqlite3.Connection
    #: bytes of blobs and text written, per part
    written: Counter[str]
    _keyframes: list[Written]
    _poses: Tensor
    _edges: int
    #: per candidate: status, residual ratio (None: NaN), awaiting its recheck
    _candidates: list[tuple[str, float | None, bool]]
    _indexed: int
    _rows: dict[str, dict[Any, tuple]]
    _updates: dict[int, int]
    _finished: bool
    #: the row length of the keyframes written last (the matches' coding splits by it)
    _width: int
    #: pointmaps that do not code to themselves are settled on their coded values
    settles: bool
    #: the codings started before the transaction (:meth:`prepare`)
    ahead: Ahead
    #: the store reads a paged-out keyframe's arrays back (SessionStore.load_keyframe): what
    #: makes the store a keyframe's KeyframePages
    load_keyframe: Callable[[int, str], dict[str, Any]]

    def _blob(self, data: bytes, part: str) -> int:
        row_id = self.connection.execute(
            "INSERT INTO blobs (data) VALUES (?)", (self._count(part, data),)
        ).lastrowid
        if row_id is None:  # sqlite3 sets it on every INSERT
            raise StoreError(f"{part}: the store gave no id to a blob it wrote")
        return row_id

    def _count(self, part: str, data: bytes) -> bytes:
        """``data``, counted as written for ``part``."""
        self.written[part] += len(data)
        return data

    def prepare(self, coordinator: Coordinator) -> None:
        """Start coding, on :attr:`ahead`'s workers, what the next transaction writes as
        ``coordinator`` holds it now (:mod:`.ahead`): the pointmaps of new keyframes and the
        replaced ones of keyframes in memory, and the matches of new edges the coordinator
        made (inter-agent edges, settled where the store settles; loop edges). Arrays as the
        ingest decoded them are left to the transaction: their coding is taken again, not
        made (:func:`~.coded.code`)."""
        graph = coordinator.graph
        # the row length the transaction will split the matches by: the newest keyframe's
        # (where it guesses wrong, the matches are coded there)
        width = self._width
        for g, kf in enumerate(graph.keyframes):
            if isinstance(kf, PagedKeyframe) and not kf.resident("pointmaps"):
                continue  # as written (or parked by the cleanup: written one at a time)
            written = self._keyframes[g] if g < len(self._keyframes) else None
            arrays = pointmap_arrays(kf)
            if written is None:
                width = int(arrays[0].shape[1])
            for array in {id(a): a for a in arrays}.values():
                if (written is None or written.holds(array) is None) and not _decoded(array):
                    self.ahead.submit(pack_pointmap, array)
        for link in graph.links[self._edges :]:
            if link.kind == "inter" and self.settles:
                self.ahead.submit(settle_matches, link.link.ij, link.link.ji, width)
            elif not codec_reuse.held("matches", link.link.ij):  # a loop edge's, say
                self.ahead.submit(pack_link, link.link, width)

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
                    self._keyframes[g] = self._write_pointmaps(graph, g, kf, written)
                    kf.evict(self, g)
                continue  # else as written: a pointmap that changes is read back first
            if (
                any(b() is not a for a, b in zip(pointmap_arrays(kf), written.arrays))
                or kf.K is not written.K
                or kf.fused_frames != written.fused_frames
            ):
                self._keyframes[g] = self._write_pointmaps(graph, g, kf, written)
        for g in range(len(self._keyframes), len(graph.keyframes)):
            kf, agent = graph.keyframes[g], graph.agent_of[g]
            # not kept where the coordinator's prior encodes the colours again (what can be
            # recomputed from the input is not stored twice), else what it needs to
            # (Encoding.portable: the simulated prior's ground truth)
            encoding = (
                None
                if kf.encoding is None or coordinator.encodings.can_reencode(agent)
                else self._blob(pack_object(kf.encoding.portable()), "encoding")
            )
            self.connection.execute(
                "INSERT INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    g,
                    agent,
                    kf.kf_id,
                    kf.frame_index,
                    kf.timestamp,
                    self._blob(pack_colours(kf.colors), "colours"),
                    encoding,
                ),
            )
            self._keyframes.append(self._write_pointmaps(graph, g, kf, None))
            if kf.retrieval is not None:
                self.connection.execute(
                    "INSERT INTO retrieval VALUES (?, ?, ?, NULL, ?)",
                    (
                        g,
                        graph.agent_of[g],
                        kf.kf_id,
                        self._count("retrieval", pack_retrieval(kf.retrieval)),
                    ),
                )

    def _write_pointmaps(
        self, graph: GlobalGraph, g: int, kf: Keyframe, before: Written | None
    ) -> Written:
        """Write a keyframe's pointmaps row: a blob per distinct array (one for ``X_init``
        and ``X_hat`` while they are the same tensor), the replaced ones deleted.

        An array its coding does not give back unchanged (one the coordinator made: a
        refined or rescaled pointmap) is written exact, or where the store :attr:`settles`
        coded, the keyframe taking the coded value in its place (:mod:`.coded`), its
        pointmap version moved on: what the coordinator holds on is what a read gives
        back."""
        arrays = pointmap_arrays(kf)
        ids: list[int] = []
        settled: dict[int, Tensor] = {}  # position -> the coded value taken in its place
        for k, array in enumerate(arrays):
            same = next((m for m in range(k) if arrays[m] is array), None)
            kept = None if before is None else before.holds(array)
            if same is not None:
                ids.append(ids[same])
                if same in settled:
                    settled[k] = settled[same]
            elif kept is not None:
                ids.append(kept)
            else:
                blob, value = self.ahead.take(pack_pointmap, array)
                if value is not array and not self.settles:
                    blob = pack_arrays(array)
                elif value is not array:
                    settled[k] = value
                ids.append(self._blob(blob, "pointmaps"))
        for k, value in settled.items():
            setattr(kf, POINTMAP_FIELDS[k], value)
        if settled:
            graph.versions[g] += 1
        self._width = int(arrays[0].shape[1])
        K = None if kf.K is None else self._count("pointmaps", pack_arrays(kf.K))
        self.connection.execute(
            "INSERT OR REPLACE INTO pointmaps VALUES (?, ?, ?, ?, ?, ?, ?)",
            (g, kf.fused_frames, *ids, K),
        )
        if before is not None:
            self.connection.executemany(
                "DELETE FROM blobs WHERE id = ?", [(b,) for b in set(before.blobs) - set(ids)]
            )
        return Written(refs(pointmap_arrays(kf)), tuple(ids), kf.K, kf.fused_frames)

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
        """New edges; where the store :attr:`settles`, an inter-agent edge's matches (the
        coordinator's own, which do not code to themselves) written coded and taken by the
        graph in their place (since format 6), as its pointmaps are."""
        links = coordinator.graph.links
        rows = []
        for n, link in enumerate(links[self._edges :], self._edges):
            if link.kind == "inter" and self.settles:
                blob, settled = self.ahead.take(
                    settle_matches, link.link.ij, link.link.ji, self._width
                )
                if settled is not None:
                    old = link.link
                    links[n] = link = dataclasses.replace(
                        link, link=dataclasses.replace(old, ij=settled[0], ji=settled[1])
                    )
                    _settle_candidates(coordinator.candidates, old, link.link)
            else:
                blob = self.ahead.take(pack_link, link.link, self._width)
            rows.append(
                (
                    n,
                    link.i,
                    link.j,
                    link.kind,
                    link.similarity,
                    link.link.covisible_ij,
                    link.link.covisible_ji,
                    self._count("edges", blob),
                )
            )
        self.connection.executemany("INSERT INTO edges VALUES (?, ?, ?, ?, ?, ?, ?, ?)", rows)
        self._edges = len(links)

    def _record_candidates(self, coordinator: Coordinator) -> None:
        """New candidates; the status and residual ratio of known ones that changed, and
        whether they await their recheck (then, as while pending, with their matches)."""
        for n, (c, row) in enumerate(zip(coordinator.candidates, candidate_rows(coordinator))):
            if n < len(self._candidates) and self._candidates[n] == row:
                continue
            status, ratio, awaiting = row
            v = c.verification
            link = v.link if status == "pending" or awaiting else None
            self.connection.execute(
                "INSERT OR REPLACE INTO candidates VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    n,
                    c.i,
                    c.j,
                    status,
                    ratio,
                    v.similarity,
                    v.nu_i,
                    v.nu_j,
                    v.covisible_ratio,
                    int(v.accepted),
                    None if v.link is None else v.link.covisible_ij,
                    None if v.link is None else v.link.covisible_ji,
                    None
                    if link is None
                    else self._count("candidates", pack_link(link, self._width)),
                ),
            )
            if n < len(self._candidates):
                self._candidates[n] = row
            else:
                self._candidates.append(row)

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
                graph.own_focal.get(agent),
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
            "refused": coordinator.refused_edges(),
            "deferred": coordinator.deferred_keyframes(),
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


def pointmap_arrays(kf: Keyframe) -> tuple[Tensor, ...]:
    return tuple(getattr(kf, name) for name in POINTMAP_FIELDS)


def refs(arrays: Sequence[Tensor]) -> tuple[weakref.ref, ...]:
    return tuple(weakref.ref(a) for a in arrays)


def _decoded(array: Tensor) -> bool:
    """A pointmap field as the ingest decoded it (its coding is taken again: no work)."""
    return codec_reuse.held("pointmap" if array.ndim == 3 else "confidence", array)
