"""Tests of ``como3r.data.synth``: files, formats, geometry, meetings, presets, determinism.

Scenes are tiny (64x48, a dozen frames) so the whole module runs in seconds; the geometric
checks go through the written files exactly as a consumer of an agent folder would.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from como3r.data.synth import PRESETS, build_preset, synthesize
from como3r.errors import InputError
from como3r.io.packed_arrays import read_packed
from como3r.io.tum import read_tum

W, H = 64, 48
FRAMES = 12


def _synth(out: Path, **overrides) -> tuple[Path, int]:
    """Synthesize into ``out``; returns the folder and how often progress was called."""
    args = dict(agents=2, seed=3, overlap=0.5, frames=FRAMES, preset="default", width=W, height=H)
    args.update(overrides)
    out.mkdir(parents=True)
    calls = []
    synthesize(out, progress=lambda: calls.append(1), **args)
    return out, len(calls)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, tuple[Path, int]]:
    root = tmp_path_factory.mktemp("synth")
    return {
        "default": _synth(root / "default"),
        "aliasing": _synth(root / "aliasing", preset="aliasing", frames=40),
        "no-meeting": _synth(root / "no-meeting", preset="no-meeting", frames=8),
        "forward": _synth(root / "forward", preset="forward", frames=8, agents=3),
        **{
            preset: _synth(root / preset, preset=preset, frames=10)
            for preset in ("rotation", "fast", "low-texture", "covered", "revisit")
        },
    }


class AgentData:
    """One agent folder read back from disk."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.fx, self.fy, self.cx, self.cy = map(float, (folder / "calib.txt").read_text().split())
        self.trajectory = read_tum(folder / "groundtruth.txt")
        self.stems = sorted(p.stem for p in (folder / "rgb").glob("*.png"))

    def depth(self, i: int) -> np.ndarray:
        return read_packed(self.folder / "depth" / f"{self.stems[i]}.c3z")["depth"]

    def surface(self, i: int) -> np.ndarray:
        return read_packed(self.folder / "surface" / f"{self.stems[i]}.c3z")["surface"]

    def pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        T = self.trajectory.T_WC[i].numpy()
        return Rotation.from_quat(T[3:7]).as_matrix(), T[:3]

    def world_points(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """World points ``(H, W, 3)`` of frame i and the mask of pixels with depth."""
        depth = self.depth(i)
        v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]]
        X_C = np.stack(
            [(u - self.cx) / self.fx * depth, (v - self.cy) / self.fy * depth, depth], axis=-1
        )
        R, t = self.pose(i)
        return X_C @ R.T + t, depth > 0

    def project(self, X_W: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel (u, v) rounded and z-depth of world points in frame j."""
        R, t = self.pose(j)
        X_C = (X_W - t) @ R
        z = X_C[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(self.fx * X_C[..., 0] / z + self.cx)
            v = np.round(self.fy * X_C[..., 1] / z + self.cy)
        return u, v, z


def _agent(scenes, preset: str, a: int) -> AgentData:
    return AgentData(scenes[preset][0] / f"agent_{a}")


def _keys_match(k1: np.ndarray, k2: np.ndarray, tol: float) -> np.ndarray:
    return (k1[..., 0] == k2[..., 0]) & np.all(np.abs(k1[..., 1:] - k2[..., 1:]) < tol, axis=-1)


def test_files_and_formats(scenes):
    folder, _ = scenes["default"]
    meta = json.loads((folder / "scene.json").read_text())
    assert meta["preset"] == "default" and meta["seed"] == 3 and meta["agents"] == 2
    assert [a["frames"] for a in meta["agents_info"]] == [FRAMES, FRAMES]
    assert sorted(p.name for p in folder.iterdir()) == ["agent_0", "agent_1", "scene.json"]
    for a in range(2):
        agent = AgentData(folder / f"agent_{a}")
        assert agent.stems == [f"{i:06d}" for i in range(FRAMES)]
        assert (agent.fx, agent.fy, agent.cx, agent.cy) == pytest.approx(
            (
                meta["camera"]["fx"],
                meta["camera"]["fy"],
                meta["camera"]["cx"],
                meta["camera"]["cy"],
            ),
            abs=1e-5,
        )
        stamps = np.loadtxt(agent.folder / "timestamps.txt")
        np.testing.assert_allclose(stamps, np.arange(FRAMES) / 30.0, atol=1e-6)
        np.testing.assert_allclose(agent.trajectory.timestamps, stamps, atol=1e-9)
        for sub in ("depth", "surface"):
            assert sorted(p.stem for p in (agent.folder / sub).iterdir()) == agent.stems
        with Image.open(agent.folder / "rgb" / "000003.png") as img:
            assert img.mode == "RGB" and img.size == (W, H)
        depth, surface = agent.depth(3), agent.surface(3)
        assert depth.dtype == np.float32 and depth.shape == (H, W)
        assert surface.dtype == np.float32 and surface.shape == (H, W, 3)
        assert np.all(np.isfinite(depth)) and np.all(depth >= 0)
        np.testing.assert_array_equal(depth == 0, surface[..., 0] < 0)
        np.testing.assert_array_equal(surface[..., 0], np.round(surface[..., 0]))


def test_progress_called_once_per_frame(scenes):
    assert scenes["default"][1] == 2 * FRAMES
    assert scenes["forward"][1] == 3 * 8


@pytest.mark.parametrize("preset", PRESETS)
def test_ground_depth_is_metric(scenes, preset):
    """Ground pixels (texture id 0, off-road) unproject onto the plane z = 0, and every
    point lies on or above the ground: depth, intrinsics and pose agree in metres."""
    agent = _agent(scenes, preset, 0)
    for i in (0, len(agent.stems) - 1):
        X_W, valid = agent.world_points(i)
        ground = valid & (agent.surface(i)[..., 0] == 0)
        assert ground.sum() > 0.02 * H * W
        np.testing.assert_allclose(X_W[ground][:, 2], 0.0, atol=2e-3)
        np.testing.assert_allclose(X_W[ground][:, :2], agent.surface(i)[ground][:, 1:], atol=2e-3)
        assert X_W[valid][:, 2].min() > -2e-3
        # The camera keeps its distance from every solid.
        assert agent.depth(i)[valid].min() > 0.5


@pytest.mark.parametrize(
    "preset,pairs", [("default", [(0, 2), (5, 6), (9, 11)]), ("forward", [(1, 2), (5, 6)])]
)
def test_reprojection_lands_on_the_same_surface_point(scenes, preset, pairs):
    """Unproject frame i with depth, K and the GT pose and project into frame j: where the
    point is visible in j, the landing pixel shows the same texture, and its key differs
    by no more than the metric distance between the two pixels' world points (s, t are
    metres along the surface)."""
    agent = _agent(scenes, preset, 1)
    for i, j in pairs:
        X_W, valid = agent.world_points(i)
        u, v, z = agent.project(X_W, j)
        inside = valid & (z > 0.1) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        uu, vv = u[inside].astype(int), v[inside].astype(int)
        visible = np.abs(agent.depth(j)[vv, uu] - z[inside]) < 0.03 * z[inside] + 0.02
        assert visible.sum() > 0.3 * H * W
        key_i = agent.surface(i)[inside][visible]
        key_j = agent.surface(j)[vv, uu][visible]
        X_j, _ = agent.world_points(j)
        gap = np.linalg.norm(X_W[inside][visible] - X_j[vv, uu][visible], axis=1)
        key_gap = np.linalg.norm(key_i[:, 1:] - key_j[:, 1:], axis=1)
        # Rounding to the landing pixel moves by at most about one pixel footprint.
        assert np.median(gap / z[inside][visible]) < 1.0 / agent.fx
        consistent = (key_i[:, 0] == key_j[:, 0]) & (key_gap <= 1.1 * gap + 0.05)
        assert consistent.mean() > 0.95


def _common_key_points(a: AgentData, i: int, b: AgentData, j: int, tol: float) -> tuple:
    """World points of both frames at pixels whose appearance keys coincide."""
    Xa, va = a.world_points(i)
    Xb, vb = b.world_points(j)
    ka, kb = a.surface(i)[va], b.surface(j)[vb]
    Xa, Xb = Xa[va], Xb[vb]
    pa, pb = [], []
    for tid in np.intersect1d(ka[:, 0], kb[:, 0]):
        sa, sb = ka[:, 0] == tid, kb[:, 0] == tid
        dist, nearest = cKDTree(kb[sb][:, 1:]).query(ka[sa][:, 1:])
        close = dist < tol
        pa.append(Xa[sa][close])
        pb.append(Xb[sb][nearest[close]])
    if not pa:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pa), np.concatenate(pb)


def test_meeting_region_is_seen_by_both_agents(scenes):
    folder, _ = scenes["default"]
    meetings = json.loads((folder / "scene.json").read_text())["meetings"]
    assert {tuple(m["agents"]) for m in meetings} == {(0, 1), (1, 0)}
    for m in meetings:
        a, b = m["agents"]
        fa, fb = m["frames"][str(a)], m["frames"][str(b)]
        assert fa[1] == FRAMES - 1 and fb[0] == 0  # a ends on the stretch, b starts on it
        # a's first frame on the stretch and b's first frame are at the same place.
        pa, pb = _common_key_points(
            _agent(scenes, "default", a), fa[0], _agent(scenes, "default", b), fb[0], tol=0.03
        )
        assert len(pa) > 0.05 * H * W
        # Same key means same place: both agents' ground truth agrees on the world point.
        assert np.median(np.linalg.norm(pa - pb, axis=1)) < 0.05


def test_no_meeting_agents_never_see_the_same_place(scenes):
    points = []
    for a in range(2):
        agent = _agent(scenes, "no-meeting", a)
        cloud = [agent.world_points(i) for i in range(len(agent.stems))]
        points.append(np.concatenate([X[valid] for X, valid in cloud]))
    dist, _ = cKDTree(points[1]).query(points[0])
    # Sealed compounds with 1 m walls and a 4 m street between them.
    assert dist.min() > 1.0
    assert json.loads((scenes["no-meeting"][0] / "scene.json").read_text())["meetings"] == []


def test_aliasing_shows_identical_keys_at_distinct_places(scenes):
    folder, _ = scenes["aliasing"]
    aliased = json.loads((folder / "scene.json").read_text())["layout"]["aliased_texture_ids"]
    assert len(aliased) == 4
    agents = [_agent(scenes, "aliasing", a) for a in range(2)]
    far = 0
    for i in range(0, 40, 8):
        for j in range(0, 40, 8):
            pa, pb = _common_key_points(agents[0], i, agents[1], j, tol=0.03)
            far += int(np.sum(np.linalg.norm(pa - pb, axis=1) > 2.0))
    assert far > 0.1 * H * W
    # The scene itself repeats the same façade (id and size) at distinct places.
    spec = build_preset("aliasing", 2, 40, 0.5, 3)
    boxes = [p for p in spec.scene.primitives if aliased[0] in getattr(p, "face_ids", ())]
    assert len({p.half for p in boxes}) == 1
    centres = np.array([p.center[:2] for p in boxes])
    assert len(boxes) >= 2 and np.ptp(centres, axis=0).max() > 4.0


def test_default_scene_keys_are_unique(scenes):
    """Without aliasing, equal keys in two agents' views are the same world point."""
    agents = [_agent(scenes, "default", a) for a in range(2)]
    gaps = []
    for i in range(0, FRAMES, 3):
        for j in range(0, FRAMES, 3):
            pa, pb = _common_key_points(agents[0], i, agents[1], j, tol=0.01)
            gaps.append(np.linalg.norm(pa - pb, axis=1))
    gaps = np.concatenate(gaps)
    assert gaps.size > 0.05 * H * W  # the agents do share views (at their meetings)
    assert gaps.max() < 0.1


def test_deterministic(tmp_path):
    args = dict(agents=2, seed=11, overlap=0.3, frames=3, preset="aliasing", width=32, height=24)
    first, _ = _synth(tmp_path / "a", **args)
    second, _ = _synth(tmp_path / "b", **args)
    other, _ = _synth(tmp_path / "c", **{**args, "seed": 12})
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(second) for p in second.rglob("*") if p.is_file())
    for rel in files:
        assert (first / rel).read_bytes() == (second / rel).read_bytes(), rel
    assert (first / "agent_0/rgb/000000.png").read_bytes() != (
        other / "agent_0/rgb/000000.png"
    ).read_bytes()


def test_unknown_preset_lists_valid_ones(tmp_path):
    with pytest.raises(InputError, match="no-meeting") as info:
        synthesize(
            tmp_path,
            agents=2,
            seed=0,
            overlap=0.2,
            frames=4,
            preset="urban",
            width=32,
            height=24,
            progress=None,
        )
    assert "urban" in str(info.value) and all(p in str(info.value) for p in PRESETS)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "bad",
    [
        dict(agents=0),
        dict(frames=1),
        dict(overlap=1.5),
        dict(overlap=float("nan")),
        dict(width=2),
        dict(agents=2.5),
    ],
)
def test_impossible_arguments(tmp_path, bad):
    args = dict(agents=2, seed=0, overlap=0.2, frames=4, preset="default", width=32, height=24)
    with pytest.raises(InputError):
        synthesize(tmp_path, progress=None, **{**args, **bad})


def test_missing_output_folder(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        synthesize(
            tmp_path / "nope",
            agents=1,
            seed=0,
            overlap=0.0,
            frames=2,
            preset="default",
            width=32,
            height=24,
        )


def _densify(points: np.ndarray, factor: int) -> np.ndarray:
    steps = np.linspace(0.0, 1.0, factor, endpoint=False)[:, None, None]
    between = points[:-1] + steps * (points[1:] - points[:-1])
    return np.vstack([between.reshape(-1, points.shape[1]), points[-1:]])


@pytest.mark.parametrize("preset", ["default", "aliasing", "forward"])
@pytest.mark.parametrize("agents,overlap", [(2, 0.2), (3, 0.5), (5, 1.0)])
def test_overlap_is_the_shared_fraction_of_each_path(preset, agents, overlap):
    """Each agent spends ``overlap`` of its path within reach of another agent's path,
    and consecutive agents (a, a+1 mod N) meet."""
    frames = 240
    spec = build_preset(preset, agents, frames, overlap, 5)
    reach = 0.5 if preset != "forward" else 0.35
    for a, path in enumerate(spec.paths):
        # Other paths densified to 1/8 of a step, so distances are to the polylines.
        others = np.concatenate(
            [_densify(p.positions[:, :2], 8) for b, p in enumerate(spec.paths) if b != a]
        )
        near = cKDTree(others).query(path.positions[:, :2])[0] < reach
        # Sampling of the other paths and the lateral offsets blur the stretch ends.
        assert abs(near.mean() - overlap) < 0.06
    assert [m.agents for m in spec.meetings] == [(a, (a + 1) % agents) for a in range(agents)]


def test_no_meeting_paths_are_far_apart():
    spec = build_preset("no-meeting", 4, 200, 0.5, 2)
    for a in range(4):
        for b in range(a + 1, 4):
            d = cKDTree(spec.paths[b].positions).query(spec.paths[a].positions)[0]
            assert d.min() > 10.0


def test_single_agent_closes_a_loop():
    spec = build_preset("default", 1, 100, 0.7, 0)
    path = spec.paths[0]
    step = np.linalg.norm(np.diff(path.positions[:, :2], axis=0), axis=1)
    assert spec.meetings == []
    assert np.linalg.norm(path.positions[-1, :2] - path.positions[0, :2]) < 2.0 * step.max()


def test_cli_synth(tmp_path):
    from typer.testing import CliRunner

    from como3r.cli import app

    out = tmp_path / "scene"
    result = CliRunner().invoke(
        app,
        [
            "synth",
            "--out",
            str(out),
            "--agents",
            "3",
            "--frames",
            "2",
            "--width",
            "32",
            "--height",
            "24",
            "--preset",
            "forward",
        ],
    )
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == [
        ".como3r-run",
        "agent_0",
        "agent_1",
        "agent_2",
        "scene.json",
    ]
    result = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "bad"), "--preset", "city"])
    assert result.exit_code == 2 and not (tmp_path / "bad").exists()
