"""An agent's keyframes outside its working set paged out to its spill folder
(frontend/paging.py; issue 14, bounded memory)."""

from __future__ import annotations

import gc
import os
import socket
import subprocess
import sys
import zipfile
from dataclasses import dataclass

import pytest
import torch

from como3r.config import Config, apply_overrides
from como3r.data.agent import open_agent
from como3r.data.ground_truth import AgentFolderTruth
from como3r.data.synth import synthesize
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.packets import PointmapUpdate, PoseUpdate
from como3r.frontend.paging import (
    SPILL_PREFIX,
    KeyframeParking,
    KeyframeSpill,
    PagedKeyframe,
    PagedMatches,
)
from como3r.geometry.lie import sim3_compose, sim3_exp
from como3r.prior.base import Encoding
from como3r.prior.simulated import SimulatedPrior

WIDTH, HEIGHT, FRAMES = 64, 48, 40  # 13 keyframes, 9 loop edges: 12 are asked for
ARRAYS = ("X_hat", "C_hat", "X_init", "C_init")


@pytest.fixture(scope="module")
def agent(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root,
        agents=1,
        seed=3,
        overlap=0.2,
        frames=FRAMES,
        preset="default",
        width=WIDTH,
        height=HEIGHT,
        progress=None,
    )
    return open_agent(root / "agent_0")


def _run(agent, process_frames, tmp_path, resident: int) -> tuple[AgentFrontend, list]:
    """Every frame through a front-end keeping ``resident`` keyframes whole, with a
    coordinator's pose update (a new focal length) and pointmap update half-way; its
    outcomes and the packets it handed out."""
    config = apply_overrides(
        Config(),
        [
            f"input.long_side={WIDTH}",
            "input.subsample=1",
            f"session.resident_keyframes={resident}",
            f"session.spill_dir={tmp_path}",
        ],
    )
    prior = SimulatedPrior(
        config.simulated_prior, AgentFolderTruth({0: agent}, config.input.long_side)
    )
    frontend = AgentFrontend(prior, config, 0, prior.codebook())
    outcomes = process_frames(frontend, agent, WIDTH, range(FRAMES // 2))
    packets = list(frontend.drain_new_keyframes())
    old = torch.arange(len(frontend.keyframes) - 2)  # all but the newest two
    nudge = sim3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0], dtype=torch.float64))
    frontend.apply_pose_update(
        PoseUpdate(
            agent=0,
            kf_ids=old,
            reason="test",
            T_WC=torch.stack(
                [sim3_compose(nudge, frontend.keyframes[k].T_WC) for k in old.tolist()]
            ),
            focal=float(frontend.keyframes.last.K[0, 0]) * 1.01,
        )
    )
    frontend.apply_pointmap_update(
        PointmapUpdate(
            agent=0, kf_ids=torch.tensor([1]), X_hat=frontend.keyframes[1].X_hat[None] * 1.001
        )
    )
    outcomes += process_frames(frontend, agent, WIDTH, range(FRAMES // 2, FRAMES))
    frontend.settle_camera()
    packets += list(frontend.drain_new_keyframes())
    return frontend, outcomes, packets


@pytest.fixture(scope="module")
def runs(agent, process_frames, tmp_path_factory):
    return {
        resident: _run(agent, process_frames, tmp_path_factory.mktemp(f"spill{resident}"), resident)
        for resident in (0, 1000)
    }


def _same(a, b) -> bool:
    if isinstance(a, torch.Tensor):
        return a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(
            _same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__
        )
    if hasattr(a, "shape"):  # numpy
        return (a == b).all()
    return a == b


@pytest.mark.slow
def test_paging_everything_out_changes_nothing(runs) -> None:
    (paged, paged_outcomes, paged_packets), (whole, outcomes, packets) = runs[0], runs[1000]
    assert paged_outcomes == outcomes
    assert len(whole.keyframes) >= 12 and whole.stats.loop_edges + whole.stats.local_solves > 0
    # the run pages: everything but what the last step read is in the spill only
    assert not any(kf.resident("encoding") for kf in paged.keyframes.keyframes[:-2])
    assert all(isinstance(e.matches, PagedMatches) for e in paged.edges)
    for a, b in zip(
        paged.trajectory() + paged.keyframe_trajectory(),
        whole.trajectory() + whole.keyframe_trajectory(),
    ):
        assert _same(a, b)
    for kf_a, kf_b in zip(paged.keyframes, whole.keyframes, strict=True):
        for name in (*ARRAYS, "colors", "encoding", "T_WC", "K", "fused_frames", "retrieval"):
            assert _same(getattr(kf_a, name), getattr(kf_b, name)), (kf_a.kf_id, name)
    for e_a, e_b in zip(paged.edges, whole.edges, strict=True):
        assert (e_a.i, e_a.j, e_a.kind) == (e_b.i, e_b.j, e_b.kind)
        assert e_a.matches.match_fraction == e_b.matches.match_fraction
        assert all(
            _same(getattr(e_a.matches, f), getattr(e_b.matches, f)) for f in ("idx", "valid", "q")
        )
    assert len(paged_packets) == len(packets) == len(whole.keyframes)
    for a, b in zip(paged_packets, packets):
        assert _same(a, b), a.kf_id
    stats = [
        {
            k: v
            for k, v in vars(f.stats).items()
            if k not in ("stage_seconds", "local_solve_seconds")
        }
        for f in (paged, whole)
    ]
    assert stats[0] == stats[1]


@pytest.mark.slow
def test_at_most_the_resident_keyframes_hold_their_arrays(agent, process_frames, tmp_path) -> None:
    frontend, _, _ = _run(agent, process_frames, tmp_path, 3)
    keyframes = frontend.keyframes.keyframes
    assert len(keyframes) >= 12
    held = [
        kf.kf_id
        for kf in keyframes
        if any(kf.resident(group) for group in ("encoding", "colors", "pointmaps"))
    ]
    assert held == [kf.kf_id for kf in keyframes[-3:]]
    old = len(keyframes) - 3
    for edge in frontend.edges:
        if edge.i < old and edge.j < old:
            assert isinstance(edge.matches, PagedMatches) and not edge.matches.resident()
        else:
            assert not isinstance(edge.matches, PagedMatches)
    # a later read brings a keyframe back until the next page-out
    assert keyframes[0].X_hat.shape == (HEIGHT, WIDTH, 3) and keyframes[0].resident("pointmaps")
    frontend.page_out()
    assert not keyframes[0].resident("pointmaps")
    (folder,) = tmp_path.iterdir()
    assert any(folder.iterdir())
    del frontend, keyframes, edge
    gc.collect()
    assert not folder.exists()  # the spill goes with its front-end


@dataclass(frozen=True)
class _Encoding(Encoding):
    tokens: torch.Tensor
    scale: float


def test_the_spill_gives_back_what_it_was_given(tmp_path) -> None:
    spill = KeyframeSpill(tmp_path)
    encoding = _Encoding(
        agent=2, index=7, shape=(3, 4), tokens=torch.randn(5, 6).to(torch.bfloat16), scale=0.5
    )
    values = {"encoding": encoding, "X": torch.randn(3, 4, 3, dtype=torch.float64)}
    spill.save_keyframe(4, "mixed", values)
    back = spill.load_keyframe(4, "mixed")
    assert _same(back["encoding"], encoding) and _same(back["X"], values["X"])
    kf = PagedKeyframe(
        kf_id=4,
        frame_index=9,
        timestamp=1.0,
        encoding=encoding,
        T_WC=torch.zeros(8),
        X_hat=values["X"],
        C_hat=torch.ones(3, 4),
        X_init=values["X"],
        C_init=torch.ones(3, 4),
        colors=None,
    )
    assert kf.changed() == ["encoding", "colors", "pointmaps"]
    kf.evict(spill, 4)
    assert kf.changed() == [] and not kf.resident("pointmaps")


class _CountedPages:
    """Pages of one keyframe's pointmaps that count their reads."""

    def __init__(self, values: dict[str, torch.Tensor]) -> None:
        self.values, self.reads = values, 0

    def load_keyframe(self, key: int, group: str) -> dict[str, torch.Tensor]:
        self.reads += 1
        return {name: value.clone() for name, value in self.values.items()}


def test_a_parked_keyframe_reads_its_pages_only_for_fields_not_parked(tmp_path) -> None:
    """Issue 41: the terminal cleanup's focal rescale parks all four pointmaps of a
    paged-out keyframe, so that each solve reads them from the parking (raw files) and not
    the store's coded pointmaps as well. ``X_init`` parked as the very ``X_hat`` comes back as
    one tensor, and keeps its value when ``X_hat`` alone is parked again (a depth step)."""
    gen = torch.Generator().manual_seed(0)
    shapes = {"X_hat": (4, 5, 3), "C_hat": (4, 5), "X_init": (4, 5, 3), "C_init": (4, 5)}
    stored = {name: torch.rand(*shapes[name], generator=gen) for name in ARRAYS}
    pages = _CountedPages(stored)
    kf = PagedKeyframe(
        kf_id=0,
        frame_index=0,
        timestamp=0.0,
        encoding=None,
        T_WC=torch.zeros(8),
        colors=None,
        **{name: value.clone() for name, value in stored.items()},
    )
    kf.evict(pages, 3)
    parking = KeyframeParking(tmp_path)
    parking.park(kf, {"X_hat": stored["X_hat"] + 1.0})  # as a depth step parks
    assert torch.equal(kf.peek("X_hat"), stored["X_hat"] + 1.0) and pages.reads == 1
    assert torch.equal(kf.peek("C_init"), stored["C_init"]) and pages.reads == 2
    rescaled = stored["X_hat"] * 2.0
    parking.park(kf, {"X_hat": rescaled, "C_hat": stored["C_hat"], "X_init": rescaled})
    parking.park(kf, {"C_init": stored["C_init"]})
    X_hat, C_hat, X_init, C_init = kf.peek(*ARRAYS)
    assert pages.reads == 2 and X_init is X_hat and torch.equal(X_hat, rescaled)
    assert torch.equal(C_hat, stored["C_hat"]) and torch.equal(C_init, stored["C_init"])
    parking.park(kf, {"X_hat": rescaled + 1.0})
    X_hat, X_init = kf.peek("X_hat", "X_init")
    assert torch.equal(X_hat, rescaled + 1.0) and torch.equal(X_init, rescaled)
    assert pages.reads == 2 and not kf.resident("pointmaps")
    files = list(tmp_path.glob("*/kf3_*.npz"))
    assert files and all(not zipfile.ZipFile(f).infolist()[0].compress_type for f in files)


def test_a_new_spill_removes_the_folders_of_processes_that_are_gone(tmp_path) -> None:
    """A killed agent's spill stays behind; the next spill in the same folder removes it
    (and keeps those of running processes)."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # its id is free now (a new process may take it: then it is kept)
    host = socket.gethostname()
    orphan = tmp_path / f"{SPILL_PREFIX}{gone.pid}@{host}-abc"
    running = tmp_path / f"{SPILL_PREFIX}{os.getppid()}@{host}-def"
    elsewhere = tmp_path / f"{SPILL_PREFIX}{gone.pid}@another-host-ghi"  # a shared folder
    for folder in (orphan, running, elsewhere):
        folder.mkdir()
        (folder / "kf0_pointmaps.npz").write_bytes(b"x")
    spill = KeyframeSpill(tmp_path)
    assert not orphan.exists() and running.exists() and elsewhere.exists()
    assert spill.folder.name.startswith(f"{SPILL_PREFIX}{os.getpid()}@{host}-")
