"""The layout of the session store's ``session.db`` (:mod:`como3r.store.writer` writes it,
:mod:`como3r.store.reader` reads it).

Layout (format version :data:`FORMAT_VERSION`; also ``PRAGMA user_version``, and ``PRAGMA
application_id`` = :data:`APPLICATION_ID` marks the file as a como3r store). Keyframes are
numbered by their global index ``g`` (arrival order at the coordinator); agent ids are the
coordinator's (a restarted agent process that starts a new map segment has its own).
``blob`` columns hold :mod:`.blobs` blobs (typed arrays or codec objects, Zstandard)::

    meta        key TEXT PK, value TEXT   format_version, como3r_version, created (UTC),
                                          config (JSON of the effective configuration)
    blobs       id PK, data BLOB          the large arrays, referenced by id below; since
                                          version 5 a keyframe's arrays (colours, pointmaps,
                                          retrieval features, matches) in the wire's compact
                                          codings where these give them back exactly
                                          (:mod:`.coded`), else exact; since version 6
                                          the inter-agent edges' matches coded too (the
                                          coordinator takes their coded values) and the
                                          retrieval features an agent sent aggregated
    keyframes   g PK, agent, kf_id, frame_index, timestamp, colors -> blobs (H, W, 3) uint8,
                encoding -> blobs (the prior's Encoding, codec object) or NULL where the
                coordinator's prior encodes the colours again (Prior.can_reencode: MASt3R,
                the simulated prior with the agent's ground truth); UNIQUE (agent, kf_id);
                written once
    pointmaps   g PK, fused_frames, X_hat, C_hat, X_init, C_init -> blobs ((H, W, 3) and
                (H, W) float32; X_init/C_init point at the same blob as X_hat/C_hat while
                they are the same arrays), K blob (3, 3) or NULL; rewritten on refresh, focal
                alignment, depth refinement (its old blobs deleted)
    poses       g PK, T_WC blob (8,)      the current pose, rewritten when it moves
    retrieval   g PK, agent, kf_id, position (insertion order in the coordinator's ASMK
                database, NULL if not indexed), features blob (descriptors (N, d),
                attention (N,)), or since version 6 their ASMK aggregate (codec object
                prior.retrieval.Aggregated) where the agent sent that
    edges       n PK (graph order), i, j (global), kind 'sequential'|'loop'|'inter', similarity,
                covisible_ij, covisible_ji, matches blob (ij.idx, ij.valid, ij.q, ji.idx,
                ji.valid, ji.q: every pixel of j in i and of i in j)
    candidates  n PK (verification order), i, j, status 'rejected'|'pending'|'admitted'|
                'inconsistent', residual_ratio, similarity, nu_i, nu_j, covisible_ratio,
                accepted, covisible_ij, covisible_ji, matches blob while pending (an admitted
                candidate's matches are its edge's) and, since version 8, while an
                inconsistent one awaits its recheck (state ``refused``)
    gauges      agent PK, component       the component's root (its lowest agent id)
    agents      agent PK, keyframes, last_keyframe_frame, updates_sent, focal, own_focal
                                          per-agent progress: keyframes stored, the frame
                                          index of the last, pose updates made for it (the
                                          seq of the last PoseUpdateMessage), its focal
                                          length in the map (NULL: not aligned); since
                                          version 7 the focal length its own
                                          self-calibration gave its latest keyframe (NULL:
                                          none; the centre of the focal BA's prior)
    state       key TEXT PK, value JSON   stats, gauge_events, alternation, backlog
                                          (inter edges since the last BA, their component
                                          roots), refused (since version 8: the edges
                                          refused inside a gauge that await their recheck
                                          after the next global BA, [candidate n, refused
                                          by the scale watch] in test order), deferred
                                          (since version 9: the keyframes a batch budget
                                          deferred, [agent, kf_id, [[agent, keyframe,
                                          similarity] of its hits]], oldest first), finished
                                          (the terminal cleanup ran),
                                          runtime (the multi-process runtime's view of its
                                          agents and map segments, and its transport's
                                          state: :mod:`como3r.runtime.runtime_state`)
    reports     agent PK, message blob    an agent process's final report (AgentFinished,
                                          codec object) per coordinator agent: its
                                          trajectory relative to its keyframes, statistics
"""

from __future__ import annotations

#: the store's file name in an output folder
STORE_NAME = "session.db"
#: the layout above; a reader refuses any other than :data:`READABLE_VERSIONS`
FORMAT_VERSION = 9
#: the versions a reader reads: version 4 differs only in holding every array exact, 5 in
#: holding the inter-agent edges' matches exact and no retrieval aggregates, which version 6
#: reads as they are, 6 in having no ``agents.own_focal`` (read as unknown: the focal BA's
#: prior then centres on the focal length an agent holds), 7 in keeping no edges awaiting
#: their recheck (read as none: a resumed run does not test them again), 8 in keeping no
#: deferred keyframes (read as none; a list written there by the como3r that added the
#: deferral before version 9 is read). A reader of 8 would drop the list without a word
#: and a run it resumed would never verify those keyframes, hence version 9, which it
#: refuses. An older store resumed is marked version 9 once written on (one before 7 gets
#: agents.own_focal; the blobs stay as they were written)
READABLE_VERSIONS = (4, 5, 6, 7, 8, 9)
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
    encoding INTEGER REFERENCES blobs (id),
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
    last_keyframe_frame INTEGER NOT NULL, updates_sent INTEGER NOT NULL, focal REAL,
    own_focal REAL);
CREATE TABLE state (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE reports (agent INTEGER PRIMARY KEY, message BLOB NOT NULL);
"""
