"""``como3r coordinator`` and two ``como3r agent`` processes in network namespaces of their
own, on veth links capped at 5 Mbit/s, agent 0's cut mid-run for longer than the Zenoh lease
(the short variant of ``benchmarks/links.py``): nothing lost, the loopback run's merged ATE;
and the pieces a large message travels in."""

from __future__ import annotations

import importlib.util
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from como3r.data.synth import synthesize
from como3r.transport.zenoh_protocol import PIECE, STREAM, Pieces

pytest.importorskip("zenoh")

ROOT = Path(__file__).resolve().parents[2]
SIDE = 128
#: the lease every process of the cut team announces (Zenoh's default is 10 s) and the cut:
#: past the lease both ends drop the link, so the agent sees the coordinator go and re-sends
LEASE_S, CUT_S = 2.0, 5.0


def _links():
    spec = importlib.util.spec_from_file_location("links", ROOT / "benchmarks" / "links.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["links"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


links = _links()
UNAVAILABLE = links.namespaces_unavailable()


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """Two agents that meet, 12 frames each (6 processed) at 128x96: at 64x48 the merged
    ATE depends on the order in which the agents' keyframes arrive (17 % apart when one
    agent's come after the other's), which a cut changes."""
    root = tmp_path_factory.mktemp("links_scene")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.5,
        frames=12,
        preset="default",
        width=SIDE,
        height=SIDE * 3 // 4,
        progress=None,
    )
    return root


def test_pieces_join_in_order_and_a_broken_message_is_dropped() -> None:
    def piece(incarnation: int, seq: int, index: int, count: int, queued: int = 0) -> bytes:
        return PIECE.pack(incarnation, seq, index, count, queued, 125e3)

    def whole(incarnation: int, seq: int, queued: int = 0) -> bytes:
        return STREAM.pack(incarnation, seq, queued, 125e3)

    pieces = Pieces(max_bytes=100)
    one = [piece(7, 3, i, 3, queued=30 - 10 * i) for i in range(3)]
    assert pieces.add("0", one[0], b"ab") is None
    assert pieces.add("1", piece(9, 0, 0, 2), b"xy") is None  # agents apart
    assert pieces.add("0", one[1], b"cd") is None
    # the whole message carries the backlog its sender had after the last piece
    assert pieces.add("0", one[2], b"e") == (whole(7, 3, queued=10), b"abcde")
    # a link lost mid-message: its pieces then the message again, whole, from its start
    assert pieces.add("0", piece(7, 4, 0, 2), b"fg") is None
    assert pieces.add("0", piece(7, 5, 1, 2), b"zz") is None  # out of order: dropped
    assert pieces.add("0", piece(7, 4, 1, 2), b"hi") is None  # its message is gone
    assert pieces.add("0", piece(7, 4, 0, 2), b"fg") is None
    assert pieces.add("0", piece(7, 4, 1, 2), b"hi") == (whole(7, 4), b"fghi")
    assert pieces.add("1", piece(9, 0, 1, 2), b"zw") == (whole(9, 0), b"xyzw")
    # over the cap: rejected once, the rest of it dropped
    big = [piece(7, 6, i, 3) for i in range(3)]
    assert pieces.add("0", big[0], b"x" * 60) is None
    assert "exceeds the cap of 100 bytes" in pieces.add("0", big[1], b"x" * 60)
    assert pieces.add("0", big[2], b"x") is None


def test_why_namespaces_cannot_be_made_is_said(monkeypatch) -> None:
    monkeypatch.setattr(links.os, "geteuid", lambda: 1000)
    assert links.namespaces_unavailable() == "network namespaces need root"
    monkeypatch.setattr(links.os, "geteuid", lambda: 0)
    monkeypatch.setattr(links.shutil, "which", lambda tool: None if tool == "ip" else tool)
    assert links.namespaces_unavailable() == "no `ip` command"


@pytest.mark.slow
@pytest.mark.skipif(UNAVAILABLE is not None, reason=f"no network namespaces here: {UNAVAILABLE}")
def test_a_capped_link_cut_past_the_lease_loses_nothing(scene, tmp_path) -> None:
    # the same team on loopback (keyframes travel in half precision either way), run beside
    # the cut one: the cut team's coordinator mostly waits out the cut
    with ThreadPoolExecutor(1) as pool:
        reference = pool.submit(
            links.run_team,
            "loopback",
            scene,
            tmp_path,
            SIDE,
            2,
            cap_mbit=None,
            cut_s=None,
            loopback=True,
        )
        run = links.run_team(
            "cut",
            scene,
            tmp_path,
            SIDE,
            2,
            cap_mbit=5.0,
            cut_s=CUT_S,
            loopback=False,
            lease_s=LEASE_S,
        )
        loopback = links.summarize(reference.result(), 2)
    assert run.cut_at is not None and run.up_at is not None  # the link was cut, mid-run
    row = links.summarize(run, 2)
    metrics = json.loads((run.out / "metrics.json").read_text())
    print(
        f"cut {CUT_S:g} s (lease {LEASE_S:g} s) at 5 Mbit/s: up {row.up_kb} kB, stall {row.stall_s} s, caught up "
        f"{row.caught_up_s} s after link-up, longest acknowledgement {row.ack_ms:.0f} ms "
        f"({row.acks} seen), merged ATE {row.ate_mm:.2f} mm"
    )
    assert row.lost_frames == 0 and row.lost_keyframes == 0
    for a, entry in enumerate(metrics["runtime"]["agents"]):
        assert entry["status"] == "finished", entry
        assert entry["frames_done"] == entry["frames_expected"] == 6
        assert entry["keyframes_received"] == metrics["agents"][a]["keyframes"] >= 2
        # the messages crossed the link (not Zenoh's shared memory beside it)
        assert row.up_kb[a] * 1e3 >= sum(entry["bytes_from_agent"].values())
    assert metrics["components"] == [[0, 1]]
    agent0 = "\n".join(line for _, line in run.processes["agent0"].lines)
    if "the coordinator is gone" in agent0:  # unless it had left before the cut: it re-sent
        assert "caught up" in agent0, agent0
        assert row.caught_up_s is not None and row.caught_up_s >= 0
    assert row.acks >= 2  # acknowledgements reached both ends' probes
    assert abs(row.ate_mm - loopback.ate_mm) <= 0.1 * loopback.ate_mm, (row, loopback)
