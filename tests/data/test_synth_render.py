"""Unit tests of the synthetic renderer: primitives, culling, textures, paths, cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from como3r.data.synth import Intrinsics, Renderer, Scene, build_preset
from como3r.data.synth.primitives import Box, Cone, Cylinder, Ground, StadiumRoad
from como3r.data.synth.textures import (
    Kind,
    MaterialTable,
    TextureBank,
    fbm,
    random_material,
    shade,
    value_noise,
)
from como3r.data.synth.trajectories import camera_rotations, plan_ring, stadium_loop


def _rays(*dirs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.asarray(dirs, dtype=np.float64)
    return d[:, 0], d[:, 1], d[:, 2]


def test_box_hits_and_face_keys():
    box = Box(center=(5.0, 0.0, 2.0), half=(1.0, 2.0, 2.0), yaw=0.0, face_ids=(1, 2, 3, 4, 5, 6))
    o = np.array([0.0, 0.5, 1.5])
    d = np.array([[1.0, 0.0, 0.0], [1.0, 0.3, 0.5], [1.0, 0.9, 0.0], [-1.0, 0.0, 0.0]])
    lam = box.intersect(o, tuple(d.T))
    # The -x face x = 4 (y = 0.5 + 1.2 and z = 1.5 + 2 inside), y = 4.1 misses, behind.
    np.testing.assert_allclose(lam, [4.0, 4.0, np.inf, np.inf])
    ids, s, t, nz = box.surface(tuple((o + lam[:2, None] * d[:2]).T))
    # Seen from outside the -x face runs left to right along -y, from its edge y = 2.
    np.testing.assert_array_equal(ids, [2, 2])
    np.testing.assert_allclose(s, [2.0 - 0.5, 2.0 - 1.7])
    np.testing.assert_allclose(t, [1.5, 3.5])
    np.testing.assert_array_equal(nz, [0.0, 0.0])
    top = np.array([5.5, 1.0, 6.0])
    lam = box.intersect(top, _rays((0, 0, -1)))
    ids, s, t, nz = box.surface(tuple((top + lam[0] * np.array([0, 0, -1.0]))[:, None]))
    assert lam[0] == pytest.approx(2.0)
    assert (ids[0], s[0], t[0], nz[0]) == (5, pytest.approx(1.5), pytest.approx(3.0), 1.0)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.0])
def test_identical_boxes_have_identical_keys(yaw):
    """Same size and ids at another place and heading: corresponding points, same keys."""
    ids = (1, 2, 3, 4, 5, 6)
    a = Box((0.0, 0.0, 1.0), (1.5, 0.7, 1.0), 0.0, ids)
    b = Box((10.0, -3.0, 1.0), (1.5, 0.7, 1.0), yaw, ids)
    rng = np.random.default_rng(0)
    half = np.array([1.5, 0.7, 1.0])
    local = rng.uniform(-1, 1, (50, 3)) * half
    rows, axis = np.arange(50), rng.integers(0, 3, 50)
    local[rows, axis] = np.sign(local[rows, axis]) * half[axis]  # push onto a face
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pa = local + np.array(a.center)
    pb = local @ R.T + np.array(b.center)
    for key_a, key_b in zip(a.surface(tuple(pa.T)), b.surface(tuple(pb.T))):
        np.testing.assert_allclose(key_a, key_b, atol=1e-9)


def test_cylinder_and_cone_hits():
    cyl = Cylinder((4.0, 0.0), 1.0, 0.0, 3.0, 0.0, side_id=7, top_id=8)
    o = np.array([0.0, 0.0, 1.5])
    lam = cyl.intersect(o, _rays((1, 0, 0), (1, 0, 0.5), (1, 0, 1), (0, 1, 0)))
    # Side at x = 3; the rim (x = 3, z = 3); passing above; passing beside.
    np.testing.assert_allclose(lam, [3.0, 3.0, np.inf, np.inf])
    ids, s, t, nz = cyl.surface(tuple((o + lam[0] * np.array([1.0, 0, 0]))[:, None]))
    assert ids[0] == 7 and s[0] == pytest.approx(math.pi) and t[0] == pytest.approx(1.5)
    above = np.array([4.2, 0.0, 5.0])
    lam = cyl.intersect(above, _rays((0, 0, -1)))
    ids, *_ = cyl.surface(tuple((above + lam[0] * np.array([0, 0, -1.0]))[:, None]))
    assert lam[0] == pytest.approx(2.0) and ids[0] == 8

    cone = Cone((4.0, 0.0), 1.0, 0.0, 2.0, 0.0, side_id=9, base_id=10)
    lam = cone.intersect(o, _rays((1, 0, 0), (1, 0, -0.1), (0, 0, 1)))
    # At z = 1.5 the cone's radius is 0.25: x = 3.75; descending, 4 - x = (2 - z) / 2.
    np.testing.assert_allclose(lam, [3.75, 3.75 / 1.05, np.inf])
    ids, s, t, nz = cone.surface(tuple((o + lam[0] * np.array([1.0, 0, 0]))[:, None]))
    assert ids[0] == 9 and t[0] == pytest.approx(1.5) and nz[0] == pytest.approx(1 / 5**0.5)


def test_cap_seen_from_below_is_the_base():
    cone = Cone((0.0, 0.0), 1.0, 2.0, 2.0, 0.0, side_id=9, base_id=10)
    o = np.array([0.2, 0.0, 1.0])
    lam = cone.intersect(o, _rays((0, 0, 1)))
    ids, s, t, nz = cone.surface(tuple((o + lam[0] * np.array([0, 0, 1.0]))[:, None]))
    assert lam[0] == pytest.approx(1.0) and ids[0] == 10 and nz[0] == -1.0


def _naive_depth(scene: Scene, K: Intrinsics, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Every primitive against every ray, no culling."""
    d = np.einsum("ij,hwj->ihw", R, K.rays())
    depth = scene.ground.intersect(t, tuple(d))
    for prim in scene.primitives:
        depth = np.minimum(depth, prim.intersect(t, tuple(d)))
    return np.where(np.isfinite(depth), depth, 0.0)


@pytest.mark.parametrize("preset", ["default", "forward"])
def test_culling_changes_nothing(preset):
    spec = build_preset(preset, 2, 30, 0.3, 1)
    K = Intrinsics.from_hfov(48, 36, 75.0)
    renderer = Renderer(spec.scene, K)
    for i in (0, 17, 29):
        path = spec.paths[1]
        frame = renderer.render(path.rotations[i], path.positions[i])
        expected = _naive_depth(spec.scene, K, path.rotations[i], path.positions[i])
        np.testing.assert_allclose(frame.depth, expected, rtol=1e-6)


def test_colour_is_a_function_of_the_key():
    """The colour of a pixel is recomputed from its stored key alone (façades: vertical,
    ground: horizontal), whatever the view: nothing depends on the viewing direction."""
    spec = build_preset("default", 1, 40, 0.0, 4)
    renderer = Renderer(spec.scene, Intrinsics.from_hfov(96, 72, 75.0))
    bank = TextureBank(spec.scene.materials)
    kinds = np.asarray(spec.scene.materials.kind)
    path = spec.paths[0]
    checked = 0
    for i in (3, 20):
        frame = renderer.render(path.rotations[i], path.positions[i])
        keys = frame.surface.reshape(-1, 3)
        rgb = frame.rgb.reshape(-1, 3).astype(int)
        ids = keys[:, 0].astype(int)
        for kind, normal_z in ((Kind.FACADE, 0.0), (Kind.PAVING, 1.0)):
            sel = np.nonzero((ids >= 0) & (kinds[np.maximum(ids, 0)] == kind))[0]
            expected = shade(
                bank.albedo(ids[sel], keys[sel, 1], keys[sel, 2]), np.full(sel.size, normal_z)
            )
            np.testing.assert_allclose(rgb[sel], np.round(expected * 255), atol=1)
            checked += sel.size
    assert checked > 96 * 72


def test_textures_are_rich_and_deterministic():
    table = MaterialTable()
    rng = np.random.default_rng(0)
    ids = [random_material(table, k, rng) for k in Kind if k not in (Kind.ROAD, Kind.PLAIN)]
    ids.append(table.add(Kind.ROAD, (0.22, 0.22, 0.23), (0.92, 0.92, 0.88), (3.5, 6.0)))
    bank = TextureBank(table)
    s, t = np.meshgrid(np.linspace(0, 4, 80), np.linspace(0, 3, 60))
    for tid in ids:
        rgb = bank.albedo(np.full(s.size, tid), s.ravel(), t.ravel()).reshape(60, 80, 3)
        again = TextureBank(table).albedo(np.full(s.size, tid), s.ravel(), t.ravel())
        np.testing.assert_array_equal(rgb.reshape(-1, 3), again)
        grey = rgb.mean(axis=2)
        # Texture at every scale: every 10x10 patch (0.5 m) has visible contrast.
        patches = grey[:60, :80].reshape(6, 10, 8, 10).std(axis=(1, 3))
        assert patches.min() > 0.01, Kind(table.kind[tid]).name
    other = bank.albedo(np.full(s.size, ids[0]), s.ravel() + 7.3, t.ravel())
    assert np.abs(other - bank.albedo(np.full(s.size, ids[0]), s.ravel(), t.ravel())).mean() > 0.02


def test_plain_texture_is_flat_with_sparse_marks():
    """The ``low-texture`` paint: almost every 0.5 m patch is flat, a few hold a mark."""
    table = MaterialTable()
    tid = random_material(table, Kind.PLAIN, np.random.default_rng(0))
    s, t = np.meshgrid(np.linspace(0, 20, 800), np.linspace(0, 20, 800))
    grey = TextureBank(table).albedo(np.full(s.size, tid), s.ravel(), t.ravel()).mean(axis=1)
    patches = grey.reshape(40, 20, 40, 20).std(axis=(1, 3))
    assert 0.0 < np.mean(patches > 0.01) < 0.15
    assert np.median(patches) < 0.003


def test_value_noise_is_smooth_and_bounded():
    s = np.linspace(-3.0, 3.0, 6001)
    v = value_noise(s, np.full_like(s, 0.25), 5)
    assert v.min() >= 0.0 and v.max() <= 1.0 and v.std() > 0.05
    assert np.abs(np.diff(v)).max() < 0.01  # continuous at lattice lines
    f = fbm(s, np.zeros_like(s), 3, 1.0, 4)
    assert abs(f.mean()) < 0.2 and np.abs(f).max() <= 1.0


def test_stadium_road_coordinates_follow_the_loop():
    road = StadiumRoad((1.0, -2.0), straight=12.0, radius=5.0, half_width=3.0, texture_id=1)
    loop = stadium_loop((1.0, -2.0), 12.0, 5.0)
    arc = np.linspace(0.0, loop.length, 400, endpoint=False)
    xy, tangent = loop.at(arc)
    s, lateral = road.coordinates(xy[:, 0], xy[:, 1])
    np.testing.assert_allclose(lateral, 0.0, atol=1e-3)
    np.testing.assert_allclose(np.mod(s - arc + 1.0, road.length) - 1.0, 0.0, atol=1e-3)
    outward = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # right of counter-clockwise
    _, lateral = road.coordinates(*(xy + 0.7 * outward).T)
    np.testing.assert_allclose(lateral, 0.7, atol=1e-3)


def test_camera_rotations_follow_opencv():
    yaw = np.array([0.0, 1.0, -2.5])
    R = camera_rotations(yaw, np.array([0.0, 0.2, -0.1]), np.array([0.0, 0.05, 0.0]))
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    # Level camera heading along +x: z forward = +x, x right = -y, y down = -z.
    np.testing.assert_allclose(R[0], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(np.arctan2(R[1, 1, 2], R[1, 0, 2]), 1.0)
    assert R[1, 2, 2] == pytest.approx(math.sin(0.2))  # pitched up


@pytest.mark.parametrize("agents,overlap", [(2, 0.0), (2, 0.3), (4, 0.6), (6, 1.0)])
def test_ring_plan_shares_the_requested_fraction(agents, overlap):
    length = 10.0
    plan = plan_ring(agents, length, overlap, 0.1)
    arc = np.linspace(0.0, plan.loop_length, 20000, endpoint=False)
    cover = np.zeros((agents, arc.size), dtype=bool)
    for a, start in enumerate(plan.starts):
        cover[a] = np.mod(arc - start, plan.loop_length) <= length
    counts = cover.sum(axis=0)
    for a in range(agents):
        shared = np.mean(counts[cover[a]] > 1)
        assert shared == pytest.approx(overlap, abs=2e-3)


def test_intrinsics_from_fov():
    K = Intrinsics.from_hfov(320, 240, 75.0)
    assert 2.0 * math.degrees(math.atan(160.0 / K.fx)) == pytest.approx(75.0)
    assert (K.cx, K.cy, K.fy) == (159.5, 119.5, K.fx)
    rays = K.rays()
    assert rays.shape == (240, 320, 3) and np.all(rays[..., 2] == 1.0)
    # Rays are K^-1 (u, v, 1) of the pixel centres.
    pixels = rays @ K.matrix().T
    np.testing.assert_allclose(pixels[17, 203], [203.0, 17.0, 1.0], atol=1e-9)


def test_empty_scene_is_ground_and_sky():
    table = MaterialTable()
    ground = table.add(Kind.PAVING, (0.5, 0.5, 0.5), (0.3, 0.5, 0.2), (0.5,))
    renderer = Renderer(Scene((), Ground(ground), table), Intrinsics.from_hfov(32, 24, 75.0))
    R = camera_rotations(np.array([0.3]), np.array([0.0]), np.array([0.0]))[0]
    frame = renderer.render(R, np.array([0.0, 0.0, 1.5]))
    below = frame.surface[:, :, 0] == ground
    assert below[-1].all() and (frame.surface[0, :, 0] == -1).all()
    # Level camera: a ground pixel in row v sits at z-depth 1.5 fy / (v - cy).
    K = renderer.K
    v = np.arange(24)[:, None] * np.ones((1, 32))
    expected = np.where(v > K.cy, 1.5 * K.fy / np.maximum(v - K.cy, 1e-9), 0.0)
    np.testing.assert_allclose(frame.depth, expected, rtol=1e-5)
