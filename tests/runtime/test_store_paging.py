"""Keyframes outside the working set paged out to the session store (store/paging.py;
issue 14 item 4): what is paged out is let go of (nothing keeps it alive), reads back exactly
as written, changes made to it are stored; a run that pages everything out has the outputs of
one that pages nothing."""

from __future__ import annotations

import gc
import json
import weakref
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from como3r.backend.paged_refinement import ProblemSpill
from como3r.cli import app
from como3r.config import Config, apply_overrides
from como3r.coordination.association import Candidate, Verification
from como3r.coordination.coordinator import Coordinator, CoordinatorStats
from como3r.errors import StoreError
from como3r.frontend.packets import KeyframePacket
from como3r.frontend.paging import KeyframeParking, PagedKeyframe
from como3r.frontend.pairs import DirectedMatches
from como3r.io.packed_arrays import read_packed
from como3r.prior.mast3r.prior import MASt3REncoding
from como3r.store.paging import PagedLink, StoredVerification, working_set
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME
from como3r.store.writer import SessionStore

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

H, W = 6, 8


def _packet(agent: int, kf_id: int, gen: torch.Generator) -> KeyframePacket:
    def matches() -> DirectedMatches:
        return DirectedMatches(
            torch.randint(H * W, (H * W,), generator=gen),
            torch.rand(H * W, generator=gen) > 0.3,
            torch.rand(H * W, generator=gen),
        )

    first = kf_id == 0
    return KeyframePacket(
        agent=agent,
        kf_id=kf_id,
        frame_index=2 * kf_id,
        timestamp=float(kf_id),
        T_WC=torch.rand(8, generator=gen),
        X_hat=torch.rand(H, W, 3, generator=gen),
        C_hat=1 + torch.rand(H, W, generator=gen),
        colors=torch.randint(256, (H, W, 3), generator=gen, dtype=torch.uint8).numpy(),
        encoding=MASt3REncoding(
            agent,
            2 * kf_id,
            (H, W),
            torch.rand(12, 16, generator=gen),
            torch.zeros(12, 2, dtype=torch.int64),
            (3, 4),
        ),
        retrieval=None,
        sequential_ij=None if first else matches(),
        sequential_ji=None if first else matches(),
        previous=None,
    )


def test_keyframes_outside_the_working_set_are_let_go_and_read_back(tmp_path) -> None:
    # this setting is the point of the test: the newest 2 keyframes of each agent resident
    config = apply_overrides(Config(), ["session.resident_keyframes=2"])
    coordinator = Coordinator(None, config, None, 2)  # no prior: nothing is decoded
    gen, written, alive = torch.Generator().manual_seed(0), {}, {}
    with SessionStore.create(tmp_path / STORE_NAME, config, coordinator) as store:
        for step in range(10):
            packet = _packet(step % 2, step // 2, gen)
            g = coordinator.graph.add_keyframe(packet)
            coordinator.stats.keyframes += 1
            written[g] = (packet.X_hat.clone(), packet.colors.copy(), packet.encoding.tokens)
            alive[g] = weakref.ref(packet.X_hat)
            del packet
            store.record(coordinator, [])
        graph = coordinator.graph
        kept = {g for own in graph.local_to_global.values() for g in own[-2:]}
        assert kept == {6, 7, 8, 9}
        gc.collect()
        for g, kf in enumerate(graph.keyframes):
            assert isinstance(kf, PagedKeyframe) == (g not in kept)
            assert (alive[g]() is None) == (g not in kept)  # nothing keeps it alive
        links = [link for link in graph.links if link.i not in kept and link.j not in kept]
        assert links and all(isinstance(link.link, PagedLink) for link in links)
        assert all(isinstance(link.link, PagedLink) == (link in links) for link in graph.links)

        paged = graph.keyframes[2]
        assert not paged.resident("pointmaps") and not paged.resident("encoding")
        assert torch.equal(paged.X_hat, written[2][0]) and paged.X_init is paged.X_hat
        assert np.array_equal(paged.colors, written[2][1])
        assert torch.equal(paged.encoding.tokens, written[2][2])
        assert paged.resident("pointmaps") and paged.resident("colors")
        link = graph.links[1]  # keyframes 0 and 2 of agent 0, as stored
        assert torch.equal(link.link.ij.idx, read_session(store.path).graph.links[1].link.ij.idx)

        changed = paged.X_hat + 1  # a change to a paged-out keyframe is stored
        paged.X_hat = changed
        coordinator.candidates.append(
            Candidate(Verification((1, 0), (0, 4), 0.2, link.link.ij, 0.5, None, None, False), 1, 8)
        )
        store.record(coordinator, [])
        assert not paged.resident("pointmaps")
        assert isinstance(coordinator.candidates[0].verification, StoredVerification)
        assert coordinator.candidates[0].verification.nu_j == pytest.approx(
            link.link.ij.match_fraction
        )
        assert torch.equal(paged.X_hat, changed) and not torch.equal(paged.X_init, changed)
        store.record(coordinator, [])
        confidence = paged.C_hat + 1  # set while paged out: reading the rest keeps it
        paged.C_hat = confidence
        assert torch.equal(paged.X_hat, changed) and paged.C_hat is confidence
        store.record(coordinator, [])
    stored = read_session(tmp_path / STORE_NAME)
    assert torch.equal(stored.graph.keyframes[2].C_hat, confidence)
    assert torch.equal(stored.graph.keyframes[2].X_hat, changed)
    assert torch.equal(stored.graph.keyframes[2].X_init, written[2][0])


def test_a_global_solve_reads_paged_out_pointmaps_without_keeping_them(tmp_path) -> None:
    """Issue 41: a global BA (and its scene depth) over a component read each paged-out
    keyframe's pointmap for the solve only, and solve as over resident ones."""
    config = apply_overrides(Config(), ["session.resident_keyframes=2"])
    paged_run, resident_run = (Coordinator(None, config, None, 1) for _ in range(2))
    gen = torch.Generator().manual_seed(1)
    with SessionStore.create(tmp_path / STORE_NAME, config, paged_run) as store:
        for kf_id in range(8):
            packet = _packet(0, kf_id, gen)
            for coordinator in (paged_run, resident_run):
                coordinator.graph.add_keyframe(packet)
            store.record(paged_run, [])
        paged = [kf for kf in paged_run.graph.keyframes if isinstance(kf, PagedKeyframe)]
        assert len(paged) == 6 and not any(kf.resident("pointmaps") for kf in paged)
        depths = [c.graph.scene_depth([0]) for c in (paged_run, resident_run)]
        results = [c.graph.optimize([0], anchor=0, max_iters=3) for c in (paged_run, resident_run)]
        assert not any(kf.resident("pointmaps") for kf in paged)
        assert depths[0] == depths[1] and results[0].iterations == results[1].iterations > 0
        assert torch.equal(paged_run.graph.poses(range(8)), resident_run.graph.poses(range(8)))


def test_a_rescale_into_a_parking_leaves_paged_out_keyframes_paged_out(tmp_path) -> None:
    """Issue 41: the terminal cleanup's focal rescale parks a paged-out keyframe's rescaled
    pointmaps (one keyframe in memory at a time) where it had made every keyframe's
    resident until the store wrote them: the same values, the store takes them."""
    config = apply_overrides(Config(), ["session.resident_keyframes=2"])
    paged_run, resident_run = (Coordinator(None, config, None, 1) for _ in range(2))
    gen = torch.Generator().manual_seed(3)
    K = torch.tensor([[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]])
    with SessionStore.create(tmp_path / STORE_NAME, config, paged_run) as store:
        for kf_id in range(6):
            packet = replace(_packet(0, kf_id, gen), K=K)
            for coordinator in (paged_run, resident_run):
                coordinator.graph.add_keyframe(packet)
            paged_run.stats.keyframes += 1
            store.record(paged_run, [])
        paged = [kf for kf in paged_run.graph.keyframes if isinstance(kf, PagedKeyframe)]
        assert len(paged) == 4 and not any(kf.resident("pointmaps") for kf in paged)
        parking = KeyframeParking(tmp_path / "spill")
        focal = paged_run.graph.rescale_focal(0, 0.1, parking)
        assert focal == resident_run.graph.rescale_focal(0, 0.1)
        assert not any(kf.resident("pointmaps") for kf in paged)
        assert all(kf.served_by(parking) for kf in paged)
        assert paged_run.graph.versions == resident_run.graph.versions
        for a, b in zip(paged_run.graph.keyframes, resident_run.graph.keyframes, strict=True):
            assert torch.equal(a.K, b.K) and torch.equal(a.X_hat, b.X_hat)
            assert torch.equal(a.X_init, b.X_init)
        store.record(paged_run, [])  # the store takes the parked pointmaps
        held = [(kf.X_hat, kf.X_init) for kf in paged_run.graph.keyframes]
    for kf, (X_hat, X_init) in zip(read_session(tmp_path / STORE_NAME).graph.keyframes, held):
        assert torch.equal(kf.X_hat, X_hat) and torch.equal(kf.X_init, X_init)


def test_an_agent_with_fewer_keyframes_than_the_working_set_keeps_them_all(tmp_path) -> None:
    """6 keyframes of agent 0 and 3 of agent 1 under 4 resident each: agent 0's newest 4 and
    all of agent 1's stay in memory (a slice from ``len - resident`` counted 6 - 8 = -2 from
    the end and paged out 6 of the demo scene's 14 keyframes before its terminal cleanup)."""
    # the setting is the point of the test: more resident keyframes than agent 1 has
    config = apply_overrides(Config(), ["session.resident_keyframes=4"])
    coordinator = Coordinator(None, config, None, 2)
    gen = torch.Generator().manual_seed(3)
    with SessionStore.create(tmp_path / STORE_NAME, config, coordinator) as store:
        for agent, kf_id in (
            [(0, k) for k in range(3)] + [(1, k) for k in range(3)] + [(0, k) for k in range(3, 6)]
        ):
            coordinator.graph.add_keyframe(_packet(agent, kf_id, gen))
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
        graph = coordinator.graph
        kept = set(graph.agent_keyframes(0)[2:]) | set(graph.agent_keyframes(1))
        assert working_set(coordinator) == kept
        assert {
            g for g, kf in enumerate(graph.keyframes) if not isinstance(kf, PagedKeyframe)
        } == kept


def test_the_team_bound_keeps_the_newest_keyframes_across_agents(tmp_path) -> None:
    """Issue 41: three agents arriving unevenly, 3 resident each and 4 across the team: the
    coordinator keeps the 4 newest arrivals of the agents' own newest 3 (global index is
    arrival order), and pages out the rest."""
    # the settings are the point of the test: a team bound below the agents' working sets
    config = apply_overrides(
        Config(), ["session.resident_keyframes=3", "session.team_resident_keyframes=4"]
    )
    coordinator = Coordinator(None, config, None, 3)
    gen = torch.Generator().manual_seed(4)
    arrivals = [0, 0, 1, 0, 2, 0, 1, 0, 2, 0, 0]  # agent 0 fast, 1 and 2 slow
    with SessionStore.create(tmp_path / STORE_NAME, config, coordinator) as store:
        for agent in arrivals:
            kf_id = len(coordinator.graph.local_to_global.get(agent, []))
            g = coordinator.graph.add_keyframe(_packet(agent, kf_id, gen))
            assert g == len(coordinator.graph.keyframes) - 1  # global index = arrival order
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
        graph = coordinator.graph
        per_agent = {g for own in graph.local_to_global.values() for g in own[-3:]}
        assert per_agent == {2, 4, 6, 7, 8, 9, 10}
        assert working_set(coordinator) == {7, 8, 9, 10}  # agent 0's 7, 9, 10 and agent 2's 8
        resident = {g for g, kf in enumerate(graph.keyframes) if not isinstance(kf, PagedKeyframe)}
        assert resident == {7, 8, 9, 10}
    # 0: no team-wide bound
    coordinator.config = replace(config, session=replace(config.session, team_resident_keyframes=0))
    assert working_set(coordinator) == per_agent


@pytest.fixture(scope="module")
def scene(tiny_scene) -> Path:
    return tiny_scene(frames=16, seed=1, overlap=0.2)


def _run(scene: Path, out: Path, resident: int, team: int = 0) -> Path:
    # the settings compared are the point of the test: everything paged out, or nothing;
    # the team-wide bound (0: none), or not
    result = CliRunner().invoke(
        app,
        [
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
            "--single-process",
            "-q",
            "--set",
            f"session.resident_keyframes={resident}",
            "--set",
            f"session.team_resident_keyframes={team}",
        ],
    )
    assert result.exit_code == 0, result.output
    return out


def _same_outputs(a: Path, b: Path) -> None:
    """``a`` and ``b`` wrote the same trajectories, graph, keyframes and merged map."""
    for name in ("trajectories/agent_0.txt", "trajectories/agent_1.txt", "graph.json"):
        assert (a / name).read_text() == (b / name).read_text(), name
    keyframes = sorted(p.relative_to(b) for p in b.glob("keyframes/*/*.c3z"))
    assert len(keyframes) >= 8
    for name in keyframes:
        x, y = read_packed(a / name), read_packed(b / name)
        assert x.keys() == y.keys(), name
        assert all(np.array_equal(x[key], y[key]) for key in y), name
    metrics = [json.loads((run / "metrics.json").read_text()) for run in (a, b)]
    assert metrics[0]["components"] == metrics[1]["components"] == [[0, 1]]
    assert metrics[0]["coordinator"]["ba_runs"] == metrics[1]["coordinator"]["ba_runs"] >= 1
    assert metrics[0]["map_points"] == metrics[1]["map_points"]


@pytest.mark.slow
def test_paging_everything_out_changes_no_output(scene, tmp_path) -> None:
    paged, resident = _run(scene, tmp_path / "paged", 0), _run(scene, tmp_path / "resident", 1000)
    _same_outputs(paged, resident)


@pytest.mark.slow
def test_the_team_bound_changes_no_output(scene, tmp_path) -> None:
    """Issue 41: 4 resident keyframes per agent, at most 3 across the team (the bound pages
    out keyframes the agents' working sets hold), writes what no bound writes."""
    bounded = _run(scene, tmp_path / "bounded", 4, team=3)
    _same_outputs(bounded, _run(scene, tmp_path / "unbounded", 4))


def test_a_session_read_paged_reads_nothing_until_its_store_serves_it(tmp_path) -> None:
    config = Config()
    coordinator = Coordinator(None, config, None, 2)
    gen = torch.Generator().manual_seed(1)
    with SessionStore.create(tmp_path / STORE_NAME, config, coordinator) as store:
        for step in range(6):
            coordinator.graph.add_keyframe(_packet(step % 2, step // 2, gen))
            coordinator.stats.keyframes += 1
            store.record(coordinator, [])
    eager = read_session(tmp_path / STORE_NAME)
    paged = read_session(tmp_path / STORE_NAME, paged=True)
    assert all(
        isinstance(kf, PagedKeyframe)
        and not kf.resident("pointmaps")
        and not kf.resident("encoding")
        for kf in paged.graph.keyframes
    )
    assert [type(link.link) for link in paged.graph.links] == [PagedLink] * 4
    with pytest.raises(StoreError, match="before its store"):
        paged.graph.links[0].link.ij.idx  # noqa: B018 (a property read back from the store)
    resumed = Coordinator(None, config, None, 2)
    resumed.restore(paged.graph, paged.gauges, [], CoordinatorStats(keyframes=6), [], (0, []))
    with SessionStore.reopen(tmp_path / STORE_NAME, resumed) as store:
        for want, kf in zip(eager.graph.keyframes, resumed.graph.keyframes, strict=True):
            assert torch.equal(kf.X_hat, want.X_hat) and torch.equal(kf.C_init, want.C_init)
            assert np.array_equal(kf.colors, want.colors)
        for want, link in zip(eager.graph.links, resumed.graph.links, strict=True):
            assert torch.equal(link.link.ji.q, want.link.ji.q)
        resumed.graph.keyframes[0].X_hat = resumed.graph.keyframes[0].X_hat * 2
        store.record(resumed, [])
    assert torch.equal(
        read_session(tmp_path / STORE_NAME).graph.keyframes[0].X_hat,
        2 * eager.graph.keyframes[0].X_hat,
    )


def _refined_coordinator(tmp_path: Path, resident: int) -> tuple[Coordinator, Path]:
    """Two agents of 8 keyframes each, joined by an inter-agent link, in one store: the
    terminal cleanup runs pose passes and depth steps (per-pixel parameters: these 6x8
    pointmaps are too small for segments)."""
    # the settings are the point: the working set, and a refinement with parameters
    config = apply_overrides(
        Config(),
        [
            f"session.resident_keyframes={resident}",
            "depth.variant=pixel",
            "depth.alternation_rounds=2",
            f"session.spill_dir={tmp_path / 'spill'}",
        ],
    )
    coordinator = Coordinator(None, config, None, 2)
    gen = torch.Generator().manual_seed(2)
    tmp_path.mkdir(exist_ok=True)
    store = SessionStore.create(tmp_path / STORE_NAME, config, coordinator)
    for step in range(16):
        packet = _packet(step % 2, step // 2, gen)
        pose = torch.cat([0.1 * torch.rand(3, generator=gen), torch.tensor([0, 0, 0, 1, 1.0])])
        coordinator.graph.add_keyframe(replace(packet, T_WC=pose))
        coordinator.stats.keyframes += 1
        store.record(coordinator, [])
    first, second = (coordinator.graph.global_index(a, 3) for a in (0, 1))
    link = coordinator.graph.links[0].link
    coordinator.graph.add_inter_link(first, second, link, 0.5)
    coordinator.gauges.union(0, 1)
    store.record(coordinator, [])
    return coordinator, tmp_path / STORE_NAME


@pytest.mark.slow
def test_the_terminal_refinement_keeps_the_working_set_and_pages_the_rest(
    tmp_path, monkeypatch
) -> None:
    """While the terminal cleanup's depth steps run, no keyframe outside the working set
    holds its pointmaps in memory whenever the store is read (its own residency counters);
    a pose pass, which solves over every pointmap, lets go of them after it; what the
    cleanup changed is parked, then stored at its end."""
    coordinator, path = _refined_coordinator(tmp_path, 2)
    graph = coordinator.graph
    kept = {g for own in graph.local_to_global.values() for g in own[-2:]}
    in_memory: list[set[int]] = []  # at every store read outside a pose solve
    solving = []
    load, optimize = SessionStore.load_keyframe, graph.optimize

    def spy(store: SessionStore, g: int, group: str) -> dict:
        if not solving:
            in_memory.append(
                {
                    k
                    for k, kf in enumerate(graph.keyframes)
                    if not isinstance(kf, PagedKeyframe) or kf.resident("pointmaps")
                }
            )
        return load(store, g, group)

    def solve(*args, **kwargs):
        solving.append(True)
        try:
            return optimize(*args, **kwargs)
        finally:
            solving.pop()

    spills: list[Path | None] = []  # where each depth step spills its chunk problems
    spill_init = ProblemSpill.__init__

    def spill(self, parent=None) -> None:
        spills.append(parent)
        spill_init(self, parent)

    monkeypatch.setattr(SessionStore, "load_keyframe", spy)
    monkeypatch.setattr(graph, "optimize", solve)
    monkeypatch.setattr(ProblemSpill, "__init__", spill)
    coordinator.finish()
    monkeypatch.undo()
    assert spills and all(parent == tmp_path / "spill" for parent in spills)
    alternation = coordinator.alternation[0]
    assert alternation["rounds"] >= 1 and alternation["cleanup_passes"] >= 1
    assert alternation["depth_parameters"] > 0
    assert len(in_memory) > 16 and all(resident <= kept for resident in in_memory)
    assert all(
        isinstance(kf, PagedKeyframe) and kf.served_by(coordinator.journal)
        for g, kf in enumerate(graph.keyframes)
        if g not in kept
    )
    refined = [(kf.X_hat, kf.X_init) for kf in graph.keyframes]
    coordinator.journal.close()
    for kf, (X_hat, X_init) in zip(read_session(path).graph.keyframes, refined, strict=True):
        assert torch.equal(kf.X_hat, X_hat) and torch.equal(kf.X_init, X_init)


@pytest.mark.slow
def test_a_paged_terminal_refinement_equals_an_unpaged_one(tmp_path) -> None:
    paged, _ = _refined_coordinator(tmp_path / "paged", 2)
    unpaged, _ = _refined_coordinator(tmp_path / "unpaged", 10**9)
    assert not any(isinstance(kf, PagedKeyframe) for kf in unpaged.graph.keyframes)
    cleanups = [c.finish() for c in (paged, unpaged)]
    changed = 0
    for a, b in zip(paged.graph.keyframes, unpaged.graph.keyframes, strict=True):
        assert torch.equal(a.T_WC, b.T_WC)
        assert torch.equal(a.X_hat, b.X_hat) and torch.equal(a.X_init, b.X_init)
        changed += not torch.equal(a.X_hat, a.X_init)
    assert changed > 0  # the refinement moved pointmaps
    reports = [c.alternation[0] for c in (paged, unpaged)]
    for key in (
        "rounds",
        "round_max_depth_change",
        "cleanup_max_translation",
        "depth_matches",
        "depth_parameters",
    ):
        assert reports[0][key] == reports[1][key], key
    for a, b in zip(*(list(c.pointmaps) for c in cleanups), strict=True):
        assert a.agent == b.agent and torch.equal(a.X_hat, b.X_hat)
    for agent in (0, 1):
        for a, b in zip(paged.pre_refinement[agent], unpaged.pre_refinement[agent], strict=True):
            assert torch.equal(a.X_hat, b.X_hat) and torch.equal(a.C_hat, b.C_hat)
            assert np.array_equal(a.colors, b.colors) and torch.equal(a.T_WC, b.T_WC)
    for c in (paged, unpaged):
        c.journal.close()
