"""The bytes ``como3r synth`` and a run write: the agent folders' compressed maps read as the
``.npy`` ones of before, bit for bit, and a small synth + run stays under a bound of bytes per
frame (issue 39: the demo's output was 452 MB)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from como3r.data.agent import open_agent
from como3r.data.synth import synthesize
from como3r.io.packed_arrays import read_packed

#: bytes per input frame of the tiny run below (64x48, 2 agents x 12 frames), about twice
#: what was measured: its scene (rgb, depth, surface: 22.8 kB, 56 kB with .npy maps)
SCENE_BYTES_PER_FRAME = 46_000
#: its run's keyframes/ and map.ply (42.5 kB measured)
KEYFRAMES_AND_MAP_BYTES_PER_FRAME = 85_000
#: scene and run together (199 kB measured; at this size the run's session.db, 2.1 MB, and
#: report.html, 1.0 MB, hardly depend on the frames)
TOTAL_BYTES_PER_FRAME = 400_000


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def test_old_npy_maps_read_as_the_compressed_ones(tmp_path) -> None:
    """A synth folder of before (depth and surface as .npy) gives the very frames the
    .c3z layout gives, and its maps take several times the bytes."""
    new = tmp_path / "new"
    new.mkdir()
    synthesize(
        new, agents=1, seed=3, overlap=0.0, frames=3, preset="default", width=160, height=120
    )
    agent = new / "agent_0"
    old = tmp_path / "old"
    shutil.copytree(agent, old)
    for kind in ("depth", "surface"):
        for packed in sorted((old / kind).glob("*.c3z")):
            np.save(packed.with_suffix(".npy"), read_packed(packed)[kind])
            packed.unlink()
    assert _bytes(old / "surface") > 5 * _bytes(agent / "surface")
    assert _bytes(old / "depth") > 3 * _bytes(agent / "depth")
    a, b = open_agent(agent), open_agent(old)
    assert a.has_depth and a.has_surface and b.has_depth and b.has_surface
    assert {p.suffix for p in a.depth_paths + a.surface_paths} == {".c3z"}
    assert {p.suffix for p in b.depth_paths + b.surface_paths} == {".npy"}
    for i in range(3):
        fa, fb = a.load_frame(i), b.load_frame(i)
        for x, y in ((fa.depth, fb.depth), (fa.surface, fb.surface)):
            assert x.dtype == y.dtype == np.float32 and x.shape == y.shape
            assert np.array_equal(x.view(np.uint32), y.view(np.uint32))
        assert (fa.depth > 0).mean() > 0.3


def test_a_small_synth_and_run_stay_under_their_bytes_per_frame(tiny_run_dir) -> None:
    """The tiny run of the export tests (2 agents x 12 frames at 64x48): its scene and run
    folders stay within about twice their measured bytes per frame."""
    scene, run = tiny_run_dir.parent / "scene", tiny_run_dir
    frames = 24
    sizes = {p.name: _bytes(p) if p.is_dir() else p.stat().st_size for p in run.iterdir()}
    assert _bytes(scene) / frames < SCENE_BYTES_PER_FRAME
    assert (sizes["keyframes"] + sizes["map.ply"]) / frames < KEYFRAMES_AND_MAP_BYTES_PER_FRAME
    assert (_bytes(scene) + _bytes(run)) / frames < TOTAL_BYTES_PER_FRAME, sizes
