"""A run stops before its disk is full (runtime/disk_guard.py): one warning when the input
left would not fit, a resumable stop under the reserve (as on a full disk), and a resume
with more space that finishes; on a tmpfs of fixed size where root may mount one."""

from __future__ import annotations

import errno
import json
import logging
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.progress import AgentProgress
from como3r.runtime import disk_guard
from como3r.runtime.disk_guard import MB, DiskGuard
from como3r.runtime.interrupts import checkpoint, interrupts_are_checkpoints
from como3r.store.reader import read_session
from como3r.store.schema import STORE_NAME

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")


class _Store:
    """What the guard reads of a session store: its path, keyframes and file bytes."""

    def __init__(self, path: Path) -> None:
        self.path, self.keyframes, self.on_commit = path, 0, None

    def written_metrics(self) -> dict:
        return {"keyframes": self.keyframes, "file_bytes": 2 * MB}


def test_the_guard_warns_once_then_stops_the_run_at_a_checkpoint(
    tmp_path, monkeypatch, caplog
) -> None:
    free = [100 * MB]
    monkeypatch.setattr(disk_guard, "free_bytes", lambda folder: free[0])
    seen: list = []
    guard = DiskGuard(reserve_mb=20.0, progress=seen.append)
    store = _Store(tmp_path / STORE_NAME)
    with interrupts_are_checkpoints(), caplog.at_level(logging.WARNING):
        guard.watch(store)
        event = AgentProgress(
            0, frames_done=10, frames_total=110, keyframes=5, lost=0, relocalized=0
        )
        guard.progress(event)
        assert seen == [event]  # forwarded
        for k in range(1, 4):  # 10 MB per keyframe: 50 keyframes left need 500 MB
            free[0] -= 10 * MB
            store.keyframes = k
            store.on_commit(store)
            checkpoint()  # over the reserve: the run goes on
        assert guard.per_keyframe == 10 * MB
        assert caplog.text.count("disk: at 10.0 MB per keyframe") == 1
        assert "about 50 keyframes" in caplog.text and "need 520.0 MB" in caplog.text
        free[0] = 15 * MB  # under the reserve: the next checkpoint stops the run
        store.keyframes = 4
        store.on_commit(store)
        with pytest.raises(OSError) as stop:
            checkpoint()
    assert stop.value.errno == errno.ENOSPC
    assert "15.0 MB free, under the reserve of 20.0 MB" in stop.value.strerror
    assert guard.to_json()["warned"] is True


def test_the_automatic_reserve_keeps_keyframes_and_the_outputs(tmp_path, monkeypatch) -> None:
    guard = DiskGuard(reserve_mb=0.0, progress=None)
    assert guard.reserve(store_bytes=0) == disk_guard.RESERVE_FLOOR_BYTES
    guard.per_keyframe = 3 * MB
    assert guard.reserve(store_bytes=100 * MB) == (8 * 3 + 100) * MB


@pytest.fixture
def small_disk(tmp_path):
    """A tmpfs of 16 MB at ``tmp_path / "disk"`` (root only), unmounted at the end."""
    disk = tmp_path / "disk"
    disk.mkdir()
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(disk)],
        capture_output=True,
        text=True,
    )
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (root only): {made.stderr.strip()}")
    yield disk
    subprocess.run(["umount", str(disk)], check=False)


@pytest.mark.slow
def test_a_run_on_a_small_disk_stops_resumably_and_resumes_with_more_space(
    tiny_scene, small_disk, monkeypatch
) -> None:
    """One agent of 8 frames at 64x48 (about 1 MB of disk per keyframe, the store's
    write-ahead log included) on 16 MB with a reserve of 13 MB: it warns, stops with the
    store kept, and resumes to the end once the disk is grown to 64 MB."""
    scene = tiny_scene(frames=8, seed=1, overlap=0.2)
    out = small_disk / "run"
    args = [
        "run",
        "--agent",
        str(scene / "agent_0"),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--set",
        "input.long_side=64",
        "--set",
        "session.disk_reserve_mb=13",
        "--single-process",
        "-q",
    ]
    monkeypatch.setattr("sys.argv", ["como3r", *args])
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    [line] = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert "under the reserve of 13.0 MB" in line and "MB more free space to finish" in line
    assert line.endswith(
        "free some space and continue with: " + " ".join(["como3r", *args, "--resume"])
    )
    partial = small_disk / "run.partial"
    stored = len(read_session(partial / STORE_NAME).graph)
    assert stored > 0 and not out.exists()

    grown = subprocess.run(["mount", "-o", "remount,size=64m", str(small_disk)], check=False)
    assert grown.returncode == 0
    result = CliRunner().invoke(app, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coordinator"]["keyframes"] > stored
    assert metrics["store"]["disk"]["reserve_mb"] == 13.0
    assert (out / "map.ply").is_file() and not partial.exists()
