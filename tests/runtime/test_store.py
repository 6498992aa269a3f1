"""The session store (store/writer.py, tables.py, schema.py, reader.py, blobs.py; issue 14 item 1).

A run keeps its coordinator's state in ``session.db`` and reading it back gives the run's
keyframes, poses, pointmaps and edges; a writer killed with SIGKILL at random moments leaves a
store that opens and holds exactly the state after some transaction; a newer format version
and corrupted files are refused with one error line.

The writer the SIGKILL test kills is a forked copy of the test's process (:func:`_writer`):
a scripted session of keyframes, links, merges and pose updates, forever.
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import random
import signal
import sqlite3
import time
from pathlib import Path
from typing import TextIO

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from como3r.cli import app
from como3r.config import Config
from como3r.coordination.association import Candidate, Verification
from como3r.coordination.coordinator import Coordinator
from como3r.errors import StoreError
from como3r.frontend.packets import KeyframePacket, PointmapRefresh, PoseUpdate
from como3r.frontend.pairs import DirectedMatches, PairLink
from como3r.io.keyframe_data import read_keyframe_data
from como3r.io.tum import read_tum
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.runtime.ingest import received
from como3r.store.blobs import pack_arrays, unpack_arrays
from como3r.store.reader import Session, read_session
from como3r.store.schema import FORMAT_VERSION, PAGE_SIZE, STORE_NAME
from como3r.store.writer import SessionStore

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

AGENTS = 3
HEIGHT, WIDTH = 48, 64  # the scripted session's keyframes


# ------------------------------------------------------------------------------ a real run


@pytest.fixture(scope="module")
def scene(tiny_scene) -> Path:
    return tiny_scene(frames=8, seed=1, overlap=0.2)


@pytest.mark.slow
@pytest.mark.parametrize("runtime", ["processes", "single-process"])
def test_a_run_keeps_its_coordinator_state_in_the_store(scene, tmp_path, runtime) -> None:
    out = tmp_path / "run"
    args = [
        "run",
        "--agent",
        str(scene / "agent_0"),
        "--agent",
        str(scene / "agent_1"),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--set",
        "input.long_side=64",
        "-q",
    ]
    result = CliRunner().invoke(
        app, args + (["--single-process"] if runtime != "processes" else [])
    )
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.glob(STORE_NAME + "*")) == [STORE_NAME]  # one file
    session = read_session(out / STORE_NAME)
    graph_json = json.loads((out / "graph.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    graph = session.graph
    assert session.finished and session.config.input.long_side == 64
    assert len(graph) == len(graph_json["keyframes"]) == metrics["coordinator"]["keyframes"]
    stored = {(graph.agent_of[g], kf.kf_id): kf for g, kf in enumerate(graph.keyframes)}
    for entry in graph_json["keyframes"]:
        kf = stored[(entry["agent"], entry["keyframe"])]
        assert (kf.frame_index, kf.timestamp) == (entry["frame"], entry["timestamp"])
        assert kf.T_WC.tolist() == entry["T_WC"]
        data = read_keyframe_data(out, entry["agent"], entry["keyframe"])
        assert np.array_equal(data.X, kf.X_hat.numpy())
        assert np.array_equal(data.C, kf.mean_confidence().numpy())
    for agent in range(2):  # the keyframe trajectory files, to their printed precision
        tum = read_tum(out / "keyframes" / f"agent_{agent}.txt")
        poses = torch.stack([graph.keyframes[g].T_WC for g in graph.agent_keyframes(agent)])
        assert np.allclose(np.asarray(tum.positions), poses[:, :3].numpy(), atol=1e-5)
    edges = [e for e in graph_json["edges"] if e["type"] in ("sequential", "inter")]
    assert [(e["type"], e["global"], e.get("similarity"), e["nu_i"], e["nu_j"]) for e in edges] == [
        (
            link.kind,
            [link.i, link.j],
            link.similarity,
            link.link.ji.match_fraction,
            link.link.ij.match_fraction,
        )
        for link in graph.links
    ]
    assert any(link.kind == "inter" for link in graph.links)
    assert [
        (c["status"], c["similarity"], c["nu_j"], c["residual_ratio"])
        for c in graph_json["candidates"]
    ] == [(c.status, c.similarity, c.nu_j, c.residual_ratio) for c in session.candidates]
    assert session.gauges.components() == graph_json["components"] == [[0, 1]]
    assert session.gauge_events == graph_json["gauge_events"]
    assert [e.position for e in session.retrieval] == list(range(len(graph)))
    for record in session.agents:
        assert record.keyframes == len(graph.agent_keyframes(record.agent))
        assert record.updates_sent >= 1  # the gauge merge or the cleanup moved it
    written = metrics["store"]  # the bytes written, per part: colours and encodings once
    with sqlite3.connect(out / STORE_NAME) as db:
        for column, part in (("colors", "colours"), ("encoding", "encoding")):
            (held,) = db.execute(
                f"SELECT sum(length(b.data)) FROM keyframes k JOIN blobs b ON b.id = k.{column}"
            ).fetchone()
            assert written["bytes_written_per_keyframe_by_part"][part] * len(graph) == (
                pytest.approx(held)
            )
    assert written["keyframes"] == len(graph) and written["file_bytes"] > 0
    assert written["bytes_written"] == pytest.approx(
        written["bytes_written_per_keyframe"] * len(graph)
    )
    assert written["bytes_written_per_keyframe_by_part"]["pointmaps"] > 0
    print(
        f"{runtime}: {len(graph)} keyframes, store "
        f"{(out / STORE_NAME).stat().st_size / len(graph) / 1024:.0f} kB per keyframe"
    )


# ------------------------------------------------------------------------------ a scripted session


def _scripted_coordinator() -> Coordinator:
    """A coordinator that is only driven by :func:`_step` (no prior: nothing is decoded)."""
    return Coordinator(None, Config(), None, AGENTS)


def _step(coordinator: Coordinator, seed: int, step: int) -> list[PoseUpdate]:
    """Step ``step`` of a deterministic session: a keyframe of agent ``step % 3`` with its
    sequential edge and a refresh of its predecessor; every third step a cross-agent
    candidate (admitted: an inter edge, a gauge merge and new poses for the component;
    or pending with its matches, later found inconsistent); now and then a frozen X_init."""
    gen = torch.Generator().manual_seed(seed * 1_000_003 + step)
    graph, agent = coordinator.graph, step % AGENTS
    kf_id, pixels = len(graph.agent_keyframes(agent)), HEIGHT * WIDTH

    def rand(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=gen)

    def matches() -> DirectedMatches:
        return DirectedMatches(
            torch.randint(pixels, (pixels,), generator=gen), rand(pixels) > 0.3, rand(pixels)
        )

    first = kf_id == 0
    packet = received(  # as every runtime hands a keyframe to the coordinator
        KeyframePacket(
            agent=agent,
            kf_id=kf_id,
            frame_index=3 * kf_id,
            timestamp=float(step),
            T_WC=rand(8),
            X_hat=rand(HEIGHT, WIDTH, 3),
            C_hat=1 + rand(HEIGHT, WIDTH),
            colors=torch.randint(256, (HEIGHT, WIDTH, 3), generator=gen, dtype=torch.uint8).numpy(),
            encoding=MASt3REncoding(
                agent,
                3 * kf_id,
                (HEIGHT, WIDTH),
                rand(12, 16),
                torch.zeros(12, 2, dtype=torch.int64),
                (3, 4),
            ),
            retrieval=(rand(20, 8), rand(20)),
            sequential_ij=None if first else matches(),
            sequential_ji=None if first else matches(),
            previous=None
            if first
            else PointmapRefresh(kf_id - 1, rand(HEIGHT, WIDTH, 3), 1 + rand(HEIGHT, WIDTH), 2),
        )
    )
    g = graph.add_keyframe(packet)
    coordinator.stats.keyframes += 1
    updates = []
    for c in coordinator.candidates:
        if c.status == "pending" and step % 5 == 0:
            c.status, c.residual_ratio = "inconsistent", 0.5
    others = [h for h in range(g) if graph.agent_of[h] != agent]
    if step % 3 == 2 and others:
        i = others[int(torch.randint(len(others), (1,), generator=gen))]
        link = PairLink(matches(), matches(), 0.5, 0.6)
        pending = step % 2 == 0
        coordinator.candidates.append(
            Candidate(
                Verification(
                    (graph.agent_of[i], graph.keyframes[i].kf_id),
                    (agent, kf_id),
                    0.1,
                    link.ij,
                    0.5,
                    link,
                    0.6,
                    True,
                ),
                i,
                g,
                "pending" if pending else "admitted",
                math.nan if pending else 0.01,
            )
        )
        if not pending:
            graph.add_inter_link(i, g, link, 0.1)
            coordinator.gauges.union(graph.agent_of[i], agent)
            for member in coordinator.gauges.members(agent):
                own = graph.agent_keyframes(member)
                graph.set_poses(own, graph.poses(own) + 0.01 * rand(len(own), 8))
                updates.append(
                    PoseUpdate(member, torch.arange(len(own)), graph.poses(own), "gauge")
                )
    if step % 4 == 3:
        frozen = graph.keyframes[int(torch.randint(g + 1, (1,), generator=gen))]
        frozen.X_init = frozen.X_hat
    return updates


def _scripted_session(seed: int, steps: int) -> tuple[Coordinator, dict[int, int]]:
    """The scripted coordinator after ``steps`` steps and the pose updates per agent."""
    coordinator, sent = _scripted_coordinator(), {}
    for step in range(steps):
        for update in _step(coordinator, seed, step):
            sent[update.agent] = sent.get(update.agent, 0) + 1
    return coordinator, sent


def _write_store(path: Path, seed: int, steps: int | None, say: TextIO | None = None) -> None:
    """Write the scripted session to a new store, one transaction per step (None: forever);
    ``say``: write ``record k`` to it before step k's transaction and ``done k`` after it."""
    coordinator = _scripted_coordinator()
    with SessionStore.create(path, Config(), coordinator) as store:
        step = 0
        while steps is None or step < steps:
            updates = _step(coordinator, seed, step)
            if say is not None:
                print(f"record {step}", file=say, flush=True)
            store.record(coordinator, updates)
            if say is not None:
                print(f"done {step}", file=say, flush=True)
            step += 1


def _writer(path: Path, seed: int, said: Path) -> None:
    """The writer the SIGKILL test kills, forever, saying each step in ``said`` (each line
    reaches the file before the step it names: a kill loses none).

    Each transaction waits 50 ms halfway, its keyframes and poses written and its edges not
    (a slow disk): the store's own writes are now about a quarter of the writer's time
    (about half before the store stopped coding again what the ingest decoded), and the
    kills must land inside transactions, not only between them."""
    record_edges = SessionStore._record_edges

    def slow_record_edges(store: SessionStore, coordinator: Coordinator) -> None:
        time.sleep(0.05)
        record_edges(store, coordinator)

    SessionStore._record_edges = slow_record_edges  # type: ignore[method-assign]
    with open(said, "w") as say:
        _write_store(path, seed, steps=None, say=say)


def _assert_holds(session: Session, coordinator: Coordinator, sent: dict[int, int]) -> None:
    """The store holds exactly the scripted coordinator's state."""
    graph, expected = session.graph, coordinator.graph
    assert graph.agent_of == expected.agent_of and len(graph) == len(expected)
    for kf, want in zip(graph.keyframes, expected.keyframes):
        assert (kf.kf_id, kf.frame_index, kf.timestamp, kf.fused_frames) == (
            want.kf_id,
            want.frame_index,
            want.timestamp,
            want.fused_frames,
        )
        for name in ("T_WC", "X_hat", "C_hat", "X_init", "C_init"):
            assert torch.equal(getattr(kf, name), getattr(want, name)), name
        assert (kf.X_init is kf.X_hat) == (want.X_init is want.X_hat)
        assert np.array_equal(kf.colors, want.colors)
        assert torch.equal(kf.encoding.tokens, want.encoding.tokens)
        assert all(torch.equal(a, b) for a, b in zip(kf.retrieval, want.retrieval))
    assert len(graph.links) == len(expected.links)
    for link, want in zip(graph.links, expected.links):
        assert (link.i, link.j, link.kind, link.similarity) == (
            want.i,
            want.j,
            want.kind,
            want.similarity,
        )
        assert all(
            torch.equal(getattr(getattr(link.link, d), f), getattr(getattr(want.link, d), f))
            for d in ("ij", "ji")
            for f in ("idx", "valid", "q")
        )
    assert [
        (c.i, c.j, c.status, c.residual_ratio, c.link is not None) for c in session.candidates
    ] == [
        (
            c.i,
            c.j,
            c.status,
            None if math.isnan(c.residual_ratio) else c.residual_ratio,
            c.status == "pending",
        )
        for c in coordinator.candidates
    ]
    for stored, want in zip(session.candidates, coordinator.candidates):
        if stored.link is not None:
            assert torch.equal(stored.link.ji.q, want.verification.link.ji.q)
    assert session.gauges.components() == coordinator.components()
    assert [(a.keyframes, a.updates_sent) for a in session.agents] == [
        (len(expected.agent_keyframes(a)), sent.get(a, 0)) for a in range(AGENTS)
    ]
    assert session.stats == json.loads(json.dumps(dataclasses.asdict(coordinator.stats)))


def test_the_store_holds_the_state_after_every_transaction(tmp_path) -> None:
    path = tmp_path / STORE_NAME
    _write_store(path, seed=3, steps=15)
    coordinator, sent = _scripted_session(seed=3, steps=15)
    session = read_session(path)
    _assert_holds(session, coordinator, sent)
    assert {c.status for c in session.candidates} >= {"admitted", "pending", "inconsistent"}
    assert any(link.kind == "inter" for link in session.graph.links)
    with sqlite3.connect(path) as db:  # replaced pointmaps leave no blob behind
        referenced = db.execute(
            "SELECT COUNT(DISTINCT id) FROM (SELECT colors AS id FROM keyframes UNION ALL "
            "SELECT encoding FROM keyframes UNION ALL SELECT X_hat FROM pointmaps UNION ALL "
            "SELECT C_hat FROM pointmaps UNION ALL SELECT X_init FROM pointmaps UNION ALL "
            "SELECT C_init FROM pointmaps)"
        ).fetchone()[0]
        assert db.execute("SELECT COUNT(*) FROM blobs").fetchone()[0] == referenced
        assert db.execute("PRAGMA page_size").fetchone()[0] == PAGE_SIZE  # set before WAL


@pytest.mark.slow
def test_a_writer_killed_at_random_moments_leaves_a_consistent_store(tmp_path) -> None:
    rng, inside = random.Random(0), 0
    for seed in range(4):
        path = tmp_path / f"kill{seed}" / STORE_NAME
        path.parent.mkdir()
        # forked: a new interpreter would spend seconds importing torch before it wrote
        writer = multiprocessing.get_context("fork").Process(
            target=_writer, args=(path, seed, path.parent / "said.txt"), daemon=True
        )
        writer.start()
        deadline = time.monotonic() + 60
        while not path.exists() and writer.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert path.exists(), "the writer made no store"
        time.sleep(rng.uniform(0.3, 2.0))
        os.kill(writer.pid, signal.SIGKILL)
        writer.join()
        said = (path.parent / "said.txt").read_text().split()
        assert writer.exitcode == -signal.SIGKILL
        started = max(
            [int(k) for word, k in zip(said[::2], said[1::2]) if word == "record"], default=-1
        )
        done = max([int(k) for word, k in zip(said[::2], said[1::2]) if word == "done"], default=-1)
        session = read_session(path)  # opens, intact, consistent
        steps = len(session.graph)
        coordinator, sent = _scripted_session(seed, steps)
        _assert_holds(session, coordinator, sent)  # exactly the state after `steps` steps
        # killed inside step k's transaction: k or k + 1 steps stored, else every step done
        assert steps in ((started, started + 1) if started > done else (done + 1,))
        inside += started > done
        with sqlite3.connect(path) as db:
            assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        print(
            f"seed {seed}: killed {'inside' if started > done else 'between'} "
            f"transactions, {steps} stored"
        )
    assert inside >= 1  # about 80 % of the writer's time is spent in them (_writer)


# ------------------------------------------------------------------------------ refusals


@pytest.fixture
def small_store(tmp_path) -> Path:
    path = tmp_path / STORE_NAME
    _write_store(path, seed=0, steps=4)
    return path


def _refused(path: Path, *fragments: str) -> str:
    with pytest.raises(StoreError) as caught:
        read_session(path)
    message = str(caught.value)
    assert len(message.splitlines()) == 1 and message.startswith(str(path)), message
    assert all(f in message for f in fragments), message
    return message


def test_a_store_of_a_newer_format_version_is_refused(small_store) -> None:
    with sqlite3.connect(small_store) as db:
        db.execute(f"PRAGMA user_version={FORMAT_VERSION + 1}")
    _refused(small_store, f"format version {FORMAT_VERSION + 1}", "newer", "upgrade como3r")


@pytest.mark.parametrize(
    "damage", ["not sqlite", "another sqlite file", "first page", "truncated", "middle", "blob"]
)
def test_corrupted_files_are_refused(small_store, damage) -> None:
    data = small_store.read_bytes()
    if damage == "not sqlite":
        small_store.write_text("keyframes: 12\n")
    elif damage == "another sqlite file":
        small_store.unlink()
        with sqlite3.connect(small_store) as db:
            db.execute("CREATE TABLE t (x)")
    elif damage == "first page":  # the schema's b-tree, after the 100-byte file header
        small_store.write_bytes(data[:100] + bytes(range(256)) * 8 + data[2148:])
    elif damage == "truncated":
        small_store.write_bytes(data[: len(data) // 2])
    elif damage == "middle":  # four pages zeroed
        middle = len(data) // 2 // 4096 * 4096
        small_store.write_bytes(data[:middle] + bytes(4 * 4096) + data[middle + 4 * 4096 :])
    else:
        with sqlite3.connect(small_store) as db:
            blob_id, blob = db.execute(
                "SELECT b.id, b.data FROM pointmaps m JOIN blobs b ON b.id = m.X_hat WHERE m.g = 2"
            ).fetchone()
            middle = len(blob) // 2
            db.execute(
                "UPDATE blobs SET data = ? WHERE id = ?",
                (blob[:middle] + bytes(16) + blob[middle + 16 :], blob_id),
            )
    _refused(small_store, "not a como3r session store" if "sqlite" in damage else "corrupted")


def test_blobs_keep_dtypes_and_shapes_and_reject_damage() -> None:
    arrays = [
        torch.randn(3, 4, 2),
        torch.arange(7),
        torch.rand(5) > 0.5,
        torch.randn(2, 3).to(torch.bfloat16),
        np.arange(12, dtype=np.uint8).reshape(3, 4),
        torch.zeros(0, 3),
    ]
    back = unpack_arrays(pack_arrays(*arrays), "test")
    for array, restored in zip(arrays, back):
        expected = torch.as_tensor(array)
        assert restored.dtype == expected.dtype and torch.equal(restored, expected)
    blob = pack_arrays(torch.randn(100))
    for bad in (blob[:-3], blob + b"x", b"C3RX" + blob[4:], blob[:30] + b"\0" * 8 + blob[38:]):
        with pytest.raises(StoreError):
            unpack_arrays(bad, "test")
