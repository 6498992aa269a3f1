"""The rows of a session store read back, table by table (:mod:`.reader` assembles them into
a :class:`~.reader.Session`): keyframes with their pointmaps and poses (or paged, read on
access), links with their matches, retrieval entries, candidates, gauge components; each
checked against the keyframes it names (a :class:`~como3r.errors.StoreError` otherwise).
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass

from torch import Tensor

from como3r.backend.global_graph import GlobalGraph
from como3r.backend.graph_link import GraphLink
from como3r.coordination.gauge import GaugeComponents
from como3r.errors import StoreError
from como3r.frontend.keyframes import Keyframe
from como3r.frontend.paging import PagedKeyframe
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.prior.base import Encoding
from como3r.prior.retrieval import Aggregated
from como3r.store.blobs import unpack_arrays, unpack_object
from como3r.store.coded import unpack_matches, unpack_one, unpack_retrieval
from como3r.store.paging import PagedLink

STATUSES = ("rejected", "pending", "admitted", "inconsistent")
#: the edges' matches read when their session is read paged: all but the sequential edges'
#: (those are paged; a loop or inter-agent edge's is read, and the coordinator's first
#: page-out pages it where it lies outside the working set: :func:`~.paging.page_out`)
PAGED_MATCHES = "CASE kind WHEN 'sequential' THEN NULL ELSE matches END"
KINDS = ("sequential", "loop", "inter")


@dataclass(frozen=True)
class RetrievalEntry:
    """One keyframe's retrieval features.

    Attributes:
        agent, kf_id: the keyframe.
        features: ``(descriptors (N, d), attention (N,))``, or what the ASMK database
            reads of them (:class:`~como3r.prior.retrieval.Aggregated`, as an agent with a
            codebook sends them; stores of format 6 on).
        position: its place in the coordinator's ASMK database (insertion order), None if
            it was not indexed (cross-agent retrieval off).
    """

    agent: int
    kf_id: int
    features: tuple[Tensor, Tensor] | Aggregated
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
        own_focal: the focal length [px] its own self-calibration gave its latest keyframe
            (``GlobalGraph.own_focal``), None if none or a store of format 6 or older.
    """

    agent: int
    keyframes: int
    last_keyframe_frame: int
    updates_sent: int
    focal: float | None
    own_focal: float | None = None


class Blobs:
    """The ``blobs`` table, read by id."""

    def __init__(self, connection: sqlite3.Connection) -> None:
        self.connection = connection

    def get(self, blob_id: int, what: str) -> bytes:
        row = self.connection.execute("SELECT data FROM blobs WHERE id = ?", (blob_id,)).fetchone()
        if row is None:
            raise StoreError(f"inconsistent session store: {what} refers to a missing blob")
        return row[0]

    def array(self, blob_id: int, what: str) -> Tensor:
        return unpack_one(self.get(blob_id, what), what)


def load_keyframes(connection: sqlite3.Connection, graph: GlobalGraph, blobs: Blobs) -> None:
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
        maps: dict[int, Tensor] = {}
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
                encoding=(
                    None  # not kept: the coordinator encodes the colours again
                    if encoding is None
                    else unpack_object(blobs.get(encoding, what), Encoding, f"{what} encoding")
                ),
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


def page_keyframes(connection: sqlite3.Connection, graph: GlobalGraph) -> None:
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


def read_retrieval(connection: sqlite3.Connection, graph: GlobalGraph) -> list[RetrievalEntry]:
    entries = []
    for g, agent, kf_id, position, features in connection.execute(
        "SELECT * FROM retrieval ORDER BY g"
    ):
        if g >= len(graph) or (graph.agent_of[g], graph.keyframes[g].kf_id) != (agent, kf_id):
            raise StoreError(
                f"inconsistent session store: retrieval entry {g} names no such keyframe"
            )
        retrieval = unpack_retrieval(features, f"keyframe {g} retrieval features")
        graph.keyframes[g].retrieval = retrieval
        entries.append(RetrievalEntry(agent, kf_id, retrieval, position))
    positions = sorted(e.position for e in entries if e.position is not None)
    if positions != list(range(len(positions))):
        raise StoreError("inconsistent session store: retrieval positions have gaps")
    return entries


def _matches(blob: bytes, what: str) -> tuple[DirectedMatches, DirectedMatches]:
    arrays = unpack_matches(blob, what)
    return DirectedMatches(*arrays[:3]), DirectedMatches(*arrays[3:])


def read_link(row: tuple, keyframes: int, paged: bool) -> GraphLink:
    i, j, kind, similarity, covisible_ij, covisible_ji, blob, n = row
    if kind not in KINDS or not (0 <= i < keyframes and 0 <= j < keyframes):
        raise StoreError(f"inconsistent session store: edge {n} ({kind} {i}-{j})")
    if paged and kind == "sequential":
        return GraphLink(i, j, kind, PagedLink(None, n, covisible_ij, covisible_ji), similarity)
    ij, ji = _matches(blob, f"edge {n} matches")
    return GraphLink(i, j, kind, PairLink(ij, ji, covisible_ij, covisible_ji), similarity)


def read_candidate(row: tuple, keyframes: int) -> StoredCandidate:
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
        or (status == "pending" and blob is None)
        or (status in ("rejected", "admitted") and blob is not None)
    ):
        raise StoreError(f"inconsistent session store: candidate {n} ({status} {i}-{j})")
    link = None
    if blob is not None:
        link = PairLink(*_matches(blob, f"candidate {n} matches"), covisible_ij, covisible_ji)
    return StoredCandidate(
        i, j, status, ratio, similarity, nu_i, nu_j, covisible_ratio, bool(accepted), link
    )


def read_gauges(connection: sqlite3.Connection, agents: int) -> GaugeComponents:
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
