"""Tests of the scene families of ``como3r synth``: ``scale`` and the presets ``rotation``,
``fast``, ``low-texture``, ``covered`` and ``revisit`` each have their documented property.

Renders are tiny (64x48, a few frames); path properties are checked on :func:`build_preset`
without rendering.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from como3r.data.synth import build_preset, synthesize
from como3r.data.synth.families import FAMILY_PRESETS, MIN_FRAMES
from como3r.decentralized.odometry_sim import add_odometry
from como3r.errors import InputError
from como3r.io.packed_arrays import read_packed
from como3r.io.tum import read_tum

W, H = 64, 48


def _synth(out: Path, **overrides) -> Path:
    args = dict(agents=1, seed=4, overlap=0.2, frames=4, preset="default", width=W, height=H)
    args.update(overrides)
    out.mkdir(parents=True)
    synthesize(out, **args)
    return out


def _steps(positions: np.ndarray) -> np.ndarray:
    """``(K - 1,)`` distances between consecutive camera centres."""
    return np.linalg.norm(np.diff(positions, axis=0), axis=1)


def _turns_deg(rotations: np.ndarray) -> np.ndarray:
    """``(K - 1,)`` rotation angles between consecutive cameras, degrees."""
    relative = Rotation.from_matrix(rotations[:-1]).inv() * Rotation.from_matrix(rotations[1:])
    return np.degrees(relative.magnitude())


def _grey(folder: Path, stem: str) -> np.ndarray:
    with Image.open(folder / "rgb" / f"{stem}.png") as img:
        return np.asarray(img, dtype=np.float64).mean(axis=2)


def test_scale_multiplies_every_length_and_keeps_the_images(tmp_path):
    one = _synth(tmp_path / "one") / "agent_0"
    tenth = _synth(tmp_path / "tenth", scale=0.1) / "agent_0"
    for i in range(4):
        stem = f"{i:06d}"
        assert (one / "rgb" / f"{stem}.png").read_bytes() == (
            tenth / "rgb" / f"{stem}.png"
        ).read_bytes()
        depth = read_packed(one / "depth" / f"{stem}.c3z")["depth"]
        assert (depth > 0).mean() > 0.5
        np.testing.assert_allclose(
            read_packed(tenth / "depth" / f"{stem}.c3z")["depth"], 0.1 * depth, rtol=1e-6
        )
        keys, keys_tenth = (
            read_packed(f / "surface" / f"{stem}.c3z")["surface"] for f in (one, tenth)
        )
        np.testing.assert_array_equal(keys_tenth[..., 0], keys[..., 0])
        assert np.abs(keys[..., 1:]).max() > 1.0
        np.testing.assert_allclose(keys_tenth[..., 1:], 0.1 * keys[..., 1:], rtol=1e-6, atol=1e-6)
    gt, gt_tenth = read_tum(one / "groundtruth.txt"), read_tum(tenth / "groundtruth.txt")
    assert np.ptp(gt.T_WC[:, :3].numpy(), axis=0).max() > 0.05
    np.testing.assert_allclose(gt_tenth.T_WC[:, :3], 0.1 * gt.T_WC[:, :3], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(gt_tenth.T_WC[:, 3:], gt.T_WC[:, 3:], atol=1e-9)
    meta, meta_tenth = (json.loads((f.parent / "scene.json").read_text()) for f in (one, tenth))
    assert (meta["scale"], meta_tenth["scale"]) == (1.0, 0.1)
    for get in (
        lambda m: m["speed_m_per_frame"],
        lambda m: m["camera"]["height_m"],
        lambda m: m["agents_info"][0]["path_length_m"],
        lambda m: m["layout"]["loop_length_m"],
    ):
        assert get(meta_tenth) == pytest.approx(0.1 * get(meta), rel=1e-5)
    # The odometry's noise is relative to the scene depth: the same odometry, scaled.
    odometry = [read_tum(add_odometry(f, seed=7)).T_WC for f in (one, tenth)]
    np.testing.assert_allclose(odometry[1][:, :3], 0.1 * odometry[0][:, :3], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan"), float("inf"), "2", True])
def test_scale_must_be_a_finite_positive_number(tmp_path, scale):
    with pytest.raises(InputError, match="--scale"):
        synthesize(
            tmp_path,
            agents=1,
            seed=0,
            overlap=0.2,
            frames=2,
            preset="default",
            width=32,
            height=24,
            scale=scale,
        )
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("preset", sorted(MIN_FRAMES))
def test_presets_that_need_more_frames_say_so(tmp_path, preset):
    with pytest.raises(InputError, match=f"\\[{MIN_FRAMES[preset]}, .*{preset}"):
        synthesize(
            tmp_path,
            agents=1,
            seed=0,
            overlap=0.2,
            frames=MIN_FRAMES[preset] - 1,
            preset=preset,
            width=32,
            height=24,
        )


@pytest.mark.parametrize("preset", FAMILY_PRESETS)
def test_families_are_deterministic_in_the_seed(preset):
    first, again, other = (build_preset(preset, 2, 12, 0.3, seed) for seed in (5, 5, 6))
    for a in range(2):
        np.testing.assert_array_equal(first.paths[a].positions, again.paths[a].positions)
        np.testing.assert_array_equal(first.paths[a].rotations, again.paths[a].rotations)
        assert not np.allclose(first.paths[a].positions, other.paths[a].positions)
    assert len(first.scene.primitives) == len(again.scene.primitives)


def test_rotation_turns_in_place():
    default = build_preset("default", 2, 20, 0.2, 1)
    spec = build_preset("rotation", 2, 20, 0.2, 1)
    default_step = np.median(_steps(default.paths[0].positions))
    for path in spec.paths:
        # The centre stays on a few-centimetre circle: no parallax worth the name ...
        assert np.linalg.norm(path.positions - path.positions.mean(axis=0), axis=1).max() < 0.05
        assert _steps(path.positions).max() < 0.05 * default_step
        # ... while the camera pans through more than 45 degrees.
        turned = Rotation.from_matrix(path.rotations[0]).inv() * Rotation.from_matrix(
            path.rotations[-1]
        )
        assert np.degrees(turned.magnitude()) > 45.0
    # The agents stand at different places and share part of their headings.
    assert np.linalg.norm(spec.paths[0].positions[0] - spec.paths[1].positions[0]) > 1.0


@pytest.mark.parametrize("agents,frames", [(1, 20), (3, 100)])
def test_fast_moves_several_times_further_per_frame(agents, frames):
    default = build_preset("default", agents, frames, 0.2, 2).paths[0]
    fast = build_preset("fast", agents, frames, 0.2, 2).paths[0]
    assert np.median(_steps(fast.positions)) > 3.5 * np.median(_steps(default.positions))
    # The hand-held wobble turns it as much faster; the loop's own turn (once round the
    # loop per path) is the same per frame, and dominates short single-agent paths.
    turns = np.mean(_turns_deg(fast.rotations)) / np.mean(_turns_deg(default.rotations))
    assert turns > (2.5 if agents == 3 else 0.9)


def test_low_texture_has_far_less_image_gradient(tmp_path):
    def gradient_energy(folder: Path) -> float:
        energy = []
        for i in range(3):
            grey = _grey(folder / "agent_0", f"{i:06d}")
            energy.append(np.mean(np.diff(grey, axis=0) ** 2) + np.mean(np.diff(grey, axis=1) ** 2))
        return float(np.mean(energy))

    default = gradient_energy(_synth(tmp_path / "default", frames=3, width=128, height=96))
    plain = gradient_energy(
        _synth(tmp_path / "plain", frames=3, width=128, height=96, preset="low-texture")
    )
    assert plain < 0.3 * default


def test_covered_frames_are_dark_and_show_nothing(tmp_path):
    folder = _synth(tmp_path / "covered", preset="covered", frames=12, agents=2)
    first, last = json.loads((folder / "scene.json").read_text())["covered_frames"]
    assert 0 < first and last < 11 and last - first + 1 >= 3
    for a in range(2):
        agent = folder / f"agent_{a}"
        for i in range(12):
            stem = f"{i:06d}"
            depth, keys = (
                read_packed(agent / "depth" / f"{stem}.c3z")["depth"],
                read_packed(agent / "surface" / f"{stem}.c3z")["surface"],
            )
            if first <= i <= last:
                assert _grey(agent, stem).max() < 10.0
                assert not np.any(depth > 0) and np.all(keys[..., 0] == -1)
            else:
                assert _grey(agent, stem).mean() > 60.0 and (depth > 0).mean() > 0.5
        # Ground truth goes on through the covered stretch at the usual pace.
        steps = _steps(read_tum(agent / "groundtruth.txt").T_WC[:, :3].numpy())
        assert len(steps) == 11 and steps.max() < 1.2 * np.median(steps)


def test_revisit_jumps_back_to_a_mapped_place():
    spec = build_preset("revisit", 2, 30, 0.2, 3)
    for path in spec.paths:
        (jump,) = path.jumps
        steps = _steps(path.positions)
        usual = np.median(steps)
        assert steps[jump - 1] > 5.0 * usual
        assert np.all(np.delete(steps, jump - 1) < 1.5 * usual)
        # The camera lands next to a pose it held well before the jump, looking the same way.
        earlier = np.linalg.norm(path.positions[: jump - 5] - path.positions[jump], axis=1)
        k = int(np.argmin(earlier))
        assert earlier[k] < 0.3
        turned = Rotation.from_matrix(path.rotations[k]).inv() * Rotation.from_matrix(
            path.rotations[jump]
        )
        assert np.degrees(turned.magnitude()) < 25.0
        # The teleport is not distance travelled.
        assert path.length() == pytest.approx(np.delete(steps, jump - 1).sum(), rel=0.08)
        assert path.length() < steps.sum() - 0.5 * steps[jump - 1]


@pytest.mark.parametrize("preset", ["default", "forward", "fast", "revisit"])
def test_loop_frames_makes_a_short_path_turn_like_a_long_one(preset):
    short = build_preset(preset, 1, 12, 0.2, 1).paths[0]
    long = build_preset(preset, 1, 100, 0.2, 1).paths[0]
    opened = build_preset(preset, 1, 12, 0.2, 1, loop_frames=100).paths[0]
    usual = np.mean(_turns_deg(long.rotations))
    assert np.mean(_turns_deg(short.rotations)) > 2.0 * usual  # a tight 12-frame loop
    assert np.mean(_turns_deg(opened.rotations)) < 1.5 * usual
    np.testing.assert_allclose(
        np.median(_steps(opened.positions)), np.median(_steps(long.positions)), rtol=0.1
    )


def test_loop_frames_opens_the_ring_of_meetings():
    closed = build_preset("default", 3, 20, 0.4, 2)
    opened = build_preset("default", 3, 20, 0.4, 2, loop_frames=100)
    assert [m.agents for m in closed.meetings] == [(0, 1), (1, 2), (2, 0)]
    assert [m.agents for m in opened.meetings] == [(0, 1), (1, 2)]
    for m in opened.meetings:
        (a, b), ((a0, _), (b0, _)) = m.agents, m.frames
        # The first frames of both agents on the stretch are at the same place.
        gap = opened.paths[a].positions[a0, :2] - opened.paths[b].positions[b0, :2]
        assert np.linalg.norm(gap) < 0.5


def test_loop_frames_is_validated_and_recorded(tmp_path):
    with pytest.raises(InputError, match="--loop-frames"):
        synthesize(
            tmp_path,
            agents=1,
            seed=0,
            overlap=0.2,
            frames=4,
            preset="default",
            width=32,
            height=24,
            loop_frames=1,
        )
    folder = _synth(tmp_path / "scene", loop_frames=50)
    assert json.loads((folder / "scene.json").read_text())["loop_frames"] == 50
