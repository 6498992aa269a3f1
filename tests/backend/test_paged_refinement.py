"""Tests of como3r.backend.paged_refinement: the depth step summed over working sets equals
the whole problem's (C-Eq. 19-24)."""

from __future__ import annotations

from dataclasses import fields, replace

import pytest
import torch

from como3r.backend import paged_refinement
from como3r.backend.cpu_kernels import MatchStreams
from como3r.backend.depth_problem import build_problem, match_streams
from como3r.backend.depth_refinement import refine_depths
from como3r.backend.paged_refinement import (
    LabelMaps,
    Pointmaps,
    ProblemSpill,
    chunk_edges,
    refine_in_chunks,
)
from como3r.backend.segments import segment_keyframe
from como3r.frontend.graph import Edge
from como3r.frontend.paging import KeyframeParking
from como3r.geometry.lie import sim3_act, sim3_exp, sim3_identity, sim3_inverse

from .test_depth_refinement import CONFIG, SHIFT, FakeKeyframe, W, scene_points, shifted_matches

KEYFRAMES = 6


def chain(dtype: torch.dtype = torch.float32):
    """``KEYFRAMES`` keyframes sliding along one wide scene, each ``X_init`` off by a
    per-segment factor, sequential edges both ways."""
    generator = torch.Generator().manual_seed(3)
    wide = scene_points(W + SHIFT * KEYFRAMES, torch.float64)
    keyframes, poses, labels = [], [], []
    for k in range(KEYFRAMES):
        T_WC = (
            sim3_identity(dtype=torch.float64)
            if k == 0
            else sim3_exp(
                torch.tensor(
                    [0.05 * k, 0.0, 0.01 * k, 0.0, 0.01 * k, 0.0, 0.0], dtype=torch.float64
                )
            )
        )
        X = sim3_act(sim3_inverse(T_WC), wide[:, SHIFT * k : SHIFT * k + W])
        C = torch.full(X.shape[:2], 3.0, dtype=dtype)
        lab = segment_keyframe(X.to(dtype), C, CONFIG)
        errors = 0.1 * (
            2 * torch.rand(int(lab.max()) + 1, generator=generator, dtype=torch.float64) - 1
        )
        X_init = X * torch.where(lab >= 0, errors[lab.clamp_min(0)], 0.0).exp()[..., None]
        keyframes.append(FakeKeyframe(X_init.to(dtype), X_init.to(dtype), C))
        poses.append(T_WC)
        labels.append(lab)
    edges = [
        e
        for k in range(1, KEYFRAMES)
        for e in (
            Edge(k - 1, k, shifted_matches(lambda u: u + SHIFT < W, SHIFT, 2.0)),
            Edge(k, k - 1, shifted_matches(lambda u: u >= SHIFT, -SHIFT, 2.0)),
        )
    ]
    return keyframes, torch.stack(poses).to(dtype), edges, labels


def chunked(keyframes, poses, edges, labels, reads=None, keep=lambda rows: False, budget=None):
    """:func:`refine_in_chunks` over the chain; returns the written pointmaps and report."""
    ends = [(edges[n].i, edges[n].j) for n in range(0, len(edges), 2)]

    def read(r: int) -> Pointmaps:
        if reads is not None:
            reads.append(r)
        return Pointmaps(keyframes[r].X_hat, keyframes[r].X_init)

    written = {}
    report = refine_in_chunks(
        len(keyframes),
        read,
        poses,
        chunk_edges(ends, lambda links: [e for n in links for e in edges[2 * n : 2 * n + 2]]),
        labels.__getitem__,
        CONFIG,
        written.__setitem__,
        pinned=[0],
        keep=keep,
        **({} if budget is None else {"keep_bytes": budget}),
    )
    return written, report


@pytest.mark.parametrize("per_chunk", [2, 100])
def test_chunked_depth_step_equals_the_whole_problem(monkeypatch, per_chunk) -> None:
    monkeypatch.setattr(paged_refinement, "KEYFRAMES_PER_CHUNK", per_chunk)
    keyframes, poses, edges, labels = chain()
    X_whole, _, whole = refine_depths(
        keyframes, poses, edges, list(range(KEYFRAMES)), labels, CONFIG, pinned=[0]
    )
    written, report = chunked(keyframes, poses, edges, labels)
    assert sorted(written) == list(range(1, KEYFRAMES))  # the pinned keyframe is not written
    for k in range(1, KEYFRAMES):
        torch.testing.assert_close(written[k], X_whole[k], rtol=1e-5, atol=1e-6)
    assert whole.max_change > 0.03  # the step did move the depths
    for name in (
        "num_parameters",
        "num_matches",
        "num_boundary_pairs",
        "iterations",
        "clipped_steps",
    ):
        assert getattr(report, name) == getattr(whole, name), name
    assert report.max_change == pytest.approx(whole.max_change, rel=1e-4)
    assert report.cost_history == pytest.approx(whole.cost_history, rel=1e-5)


def test_chunks_group_links_by_their_later_endpoint(monkeypatch) -> None:
    monkeypatch.setattr(paged_refinement, "KEYFRAMES_PER_CHUNK", 2)
    chunks = chunk_edges([(0, 1), (1, 2), (2, 3), (0, 3), (3, 4)], lambda links: list(links))
    assert [c.rows for c in chunks] == [(0, 1), (0, 1, 2, 3), (3, 4)]
    assert [c.edges() for c in chunks] == [[0], [1, 2, 3], [4]]


def test_a_chunk_reads_only_its_keyframes_once_per_step(monkeypatch) -> None:
    """The first pass reads the keyframes chunk by chunk: never more than a chunk's rows
    between two chunks (the working set), whatever the map's size; the later passes read
    the chunks' problems back from the spill, not the keyframes."""
    monkeypatch.setattr(paged_refinement, "KEYFRAMES_PER_CHUNK", 2)
    keyframes, poses, edges, labels = chain()
    reads: list[int] = []
    chunked(keyframes, poses, edges, labels, reads)
    setup, writes = list(range(KEYFRAMES)), list(range(1, KEYFRAMES))
    assert reads == setup + [0, 1, 1, 2, 3, 3, 4, 5] + writes


@pytest.mark.parametrize("kept", [(), (0, 1), (0, 1, 2)])
def test_kept_and_spilled_chunks_give_the_same_result(monkeypatch, kept) -> None:
    """A chunk allowed to keep its problem (its keyframes resident) stays in memory, any
    other is written to the spill once and read back at every later pass: the same
    pointmaps, costs and match counts bit for bit, whichever chunks are kept."""
    monkeypatch.setattr(paged_refinement, "KEYFRAMES_PER_CHUNK", 2)
    keyframes, poses, edges, labels = chain()
    reference, reference_report = chunked(keyframes, poses, edges, labels, keep=lambda rows: True)
    saved, loaded = [], []
    save, load = ProblemSpill.save, ProblemSpill.load
    monkeypatch.setattr(
        ProblemSpill, "save", lambda spill, n, p: (saved.append(n), save(spill, n, p))[1]
    )
    monkeypatch.setattr(
        ProblemSpill, "load", lambda spill, n: (loaded.append(n), load(spill, n))[1]
    )
    rows = [(0, 1), (1, 2, 3), (3, 4, 5)]
    written, report = chunked(
        keyframes, poses, edges, labels, keep=lambda chunk: rows.index(tuple(chunk)) in kept
    )
    spilled = [n for n in range(3) if n not in kept]
    assert saved == spilled and loaded == spilled * CONFIG.inner_iters
    for k in range(1, KEYFRAMES):
        assert torch.equal(written[k], reference[k])
    assert report.cost_history == reference_report.cost_history
    assert report.num_matches == reference_report.num_matches


def test_a_spilled_problem_reads_back_bit_for_bit(tmp_path) -> None:
    """int64 indices go to the file as int32 and come back as int64; one beyond int32 stays
    int64; floats keep their dtype; a CPU chunk's match streams come back as such; the files
    are deleted with the spill."""
    keyframes, poses, edges, labels = chain(torch.float64)
    problem, _, _ = build_problem(
        keyframes, poses, edges, lambda k: k, labels, CONFIG, {0}, data_only=True
    )
    spill = ProblemSpill(tmp_path)
    spill.save(0, problem)
    wide = replace(problem, match_b=problem.match_b + 2**40)
    spill.save(1, wide)
    int32 = sum(
        getattr(problem, f.name).numel()
        for f in fields(problem)
        if getattr(problem, f.name).dtype == torch.int64
    )
    floats = sum(
        getattr(problem, f.name).nbytes
        for f in fields(problem)
        if getattr(problem, f.name).is_floating_point()
    )
    assert spill.bytes == 2 * (4 * int32 + floats) + 4 * problem.match_b.numel()
    for n, want in ((0, problem), (1, wide)):
        back = spill.load(n)
        for f in fields(want):
            a, b = getattr(back, f.name), getattr(want, f.name)
            assert a.dtype == b.dtype and torch.equal(a, b), f.name
    assert problem.match_a.numel() > 100 and int(problem.param.min()) == -1
    streams = match_streams(problem)  # what a CPU chunk spills: comes back as its type
    spill.save(2, streams)
    back = spill.load(2)
    assert isinstance(back, MatchStreams)
    for f in fields(streams):
        a, b = getattr(back, f.name), getattr(streams, f.name)
        assert a.dtype == b.dtype and torch.equal(a, b), f.name
    assert list(tmp_path.glob("*/chunk*.bin"))
    spill.close()
    assert not list(tmp_path.glob("*/chunk*.bin")) and 0 not in spill


def test_label_maps_of_paged_keyframes_live_in_the_parking(tmp_path) -> None:
    parking = KeyframeParking(tmp_path)
    labels = LabelMaps(parking)
    kept, parked = torch.arange(6).reshape(2, 3), torch.arange(6).reshape(2, 3) - 1
    labels.keep(4, kept, parked=False)
    labels.keep(7, parked, parked=True)
    assert list(labels) == [4, 7] and len(labels) == 2
    assert labels[4] is kept
    assert torch.equal(labels[7], parked) and labels[7] is not parked
    assert parking.writes == 1


@pytest.mark.parametrize("budget_chunks", [0, 1, 2])
def test_kept_problems_stay_within_the_byte_budget(monkeypatch, budget_chunks) -> None:
    """Chunks that may keep their problems keep them only while the kept bytes fit
    ``keep_bytes``: the first ones in chunk order, the rest spilled; the result is the same
    bit for bit."""
    monkeypatch.setattr(paged_refinement, "KEYFRAMES_PER_CHUNK", 2)
    keyframes, poses, edges, labels = chain()
    reference, reference_report = chunked(keyframes, poses, edges, labels, keep=lambda rows: True)
    sizes = []
    measure = paged_refinement._problem_bytes
    monkeypatch.setattr(
        paged_refinement, "_problem_bytes", lambda data: (sizes.append(measure(data)), sizes[-1])[1]
    )
    saved = []
    save = ProblemSpill.save
    monkeypatch.setattr(
        ProblemSpill, "save", lambda spill, n, p: (saved.append(n), save(spill, n, p))[1]
    )
    chunked(keyframes, poses, edges, labels, keep=lambda rows: True)  # measure the sizes
    assert len(sizes) == 3 and min(sizes) > 0 and saved == []
    budget, sizes[:] = sum(sizes[:budget_chunks]), []
    written, report = chunked(
        keyframes, poses, edges, labels, keep=lambda rows: True, budget=budget
    )
    assert saved == list(range(budget_chunks, 3))
    for k in range(1, KEYFRAMES):
        assert torch.equal(written[k], reference[k])
    assert report.cost_history == reference_report.cost_history
