"""Motion and appearance families of ``como3r synth``: the scenes our defaults were not
tuned on, for the robustness benchmark (``benchmarks/robustness.py``).

``rotation``
    Every camera turns in place in a walled courtyard full of clutter, panning at
    :data:`ROTATION_DEG_PER_FRAME` with a gentle pitch and roll wobble. The vertical
    rotation axis sits :data:`NODAL_OFFSET` behind the optical centre, as on a tripod head
    or a hand-held camera turned by a person, so the camera centre moves on a circle of
    that radius: the translation is negligible against the scene (parallax well below a
    pixel beyond a few metres) but keeps the ground truth non-degenerate for the Sim(3)
    alignment of the ATE (a single point has no defined scale or rotation). With several
    agents the pivots lie 1.5 m from the courtyard centre and neighbours' headings overlap
    by ``overlap`` of their sweep (as the arc of a ring plan, :func:`~.trajectories.plan_ring`).
``fast``
    The ``default`` rooms driven :data:`FAST_FACTOR` times faster: per frame, the camera
    moves that many times as far and its hand-held wobble (a function of the distance)
    turns it that many times as fast. The loop's own turn per frame stays that of the
    ``default`` preset with as many frames (the loop is as many times longer), which
    dominates short single-agent paths (a small closed loop).
``low-texture``
    The ``default`` rooms with every surface, ground included, in flat paint with faint
    shading and sparse dark marks (:attr:`~.textures.Kind.PLAIN`): large weakly textured walls.
``covered``
    The ``default`` preset with the lens covered for a few consecutive frames in the middle
    of every agent's path (:func:`covered_frames`): the images are near-black sensor noise,
    the depth maps 0 and the surface maps id -1 (nothing valid for the simulated prior to
    see); the ground truth continues.
``revisit``
    The ``default`` rooms; every camera rides its path for the first
    :data:`REVISIT_SHARE` of its frames, then jumps back to the place of its frame
    ``frames // 5`` (half a step further along, on the loop's centre line, a fresh wobble)
    and rides on from there: a discontinuity of the path onto an already mapped place,
    for relocalization. ``overlap`` and the meetings refer to the first part.

Every family is a deterministic function of its arguments and seed; all but ``rotation``
follow ``loop_frames`` (:mod:`.presets`).
"""

from __future__ import annotations

import math

import numpy as np

from como3r.data.synth.layout import SceneBuilder
from como3r.data.synth.presets import (
    BASE_PRESETS,
    CLEARANCE,
    WALL_HEIGHTS,
    SceneSpec,
    build_base_preset,
    rooms,
)
from como3r.data.synth.trajectories import (
    AgentPath,
    CameraMotion,
    camera_rotations,
    plan_ring,
    ride,
)

FAMILY_PRESETS = ("rotation", "fast", "low-texture", "covered", "revisit")
#: every preset of ``como3r synth``
PRESETS = BASE_PRESETS + FAMILY_PRESETS
#: presets that need more than the general minimum of 2 frames per agent
MIN_FRAMES = {"covered": 6, "revisit": 10}

#: ``rotation``: pan rate in degrees per frame
ROTATION_DEG_PER_FRAME = 3.0
#: ``rotation``: metres from the vertical rotation axis to the optical centre
NODAL_OFFSET = 0.03
#: ``rotation``: inner radius of the courtyard wall, metres
COURTYARD_RADIUS = 9.0
#: ``rotation``: distance of the agents' pivots from the courtyard centre, metres
PIVOT_RADIUS = 1.5
#: ``fast``: per-frame motion relative to the ``default`` preset
FAST_FACTOR = 4.0
#: ``revisit``: share of the frames ridden before the jump back
REVISIT_SHARE = 0.6


def covered_frames(frames: int) -> tuple[int, int]:
    """First and last frame (inclusive) of the ``covered`` preset's covered stretch:
    ``frames // 8`` frames, at least 3 and at most 10, centred in the path (>= 6 frames)."""
    count = min(10, max(3, frames // 8))
    first = (frames - count) // 2
    return first, first + count - 1


def _rotation(agents: int, frames: int, overlap: float, rng: np.random.Generator) -> SceneSpec:
    """The ``rotation`` preset (module docstring)."""
    rate = math.radians(ROTATION_DEG_PER_FRAME)
    motion = CameraMotion(speed=NODAL_OFFSET * rate, yaw_amplitude=0.0)
    sweep = rate * (frames - 1)
    plan = plan_ring(agents, sweep, overlap, rate)
    phase = float(rng.uniform(0, 2 * np.pi))
    heading0 = float(rng.uniform(0, 2 * np.pi))
    radius = PIVOT_RADIUS if agents > 1 else 0.0
    paths = []
    for a in range(agents):
        angle = phase + 2.0 * math.pi * a / agents
        pivot = radius * np.array([math.cos(angle), math.sin(angle)])
        turned = rate * np.arange(frames)
        yaw = heading0 + plan.starts[a] + turned
        wobble = rng.uniform(0, 2 * np.pi, 2)
        pitch = np.radians(
            motion.pitch + motion.pitch_amplitude * np.sin(0.21 * np.arange(frames) + wobble[0])
        )
        roll = np.radians(motion.roll_amplitude) * np.sin(0.13 * np.arange(frames) + wobble[1])
        xy = pivot + NODAL_OFFSET * np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
        positions = np.concatenate([xy, np.full((frames, 1), motion.height)], axis=1)
        paths.append(
            AgentPath(
                arc=NODAL_OFFSET * turned,
                positions=positions,
                rotations=camera_rotations(yaw, pitch, roll),
            )
        )
    builder = SceneBuilder(rng, np.vstack([p.positions[:, :2] for p in paths]), CLEARANCE)
    builder.ring_wall(
        (0.0, 0.0), COURTYARD_RADIUS, WALL_HEIGHTS, math.ceil(2 * math.pi * COURTYARD_RADIUS / 8)
    )

    def sample(g: np.random.Generator) -> tuple[float, float, float]:
        r = COURTYARD_RADIUS * math.sqrt(g.uniform())
        a = g.uniform(0, 2 * np.pi)
        return r * math.cos(a), r * math.sin(a), a

    builder.scatter(sample, int(math.pi * COURTYARD_RADIUS**2 / 8.0))
    info = {
        "loop": "none",
        "courtyard_radius_m": COURTYARD_RADIUS,
        "pivot_radius_m": radius,
        "nodal_offset_m": NODAL_OFFSET,
        "rotation_deg_per_frame": ROTATION_DEG_PER_FRAME,
        "shared_sweep_deg": math.degrees(plan.shared),
        "shared_length_m": 0.0,
        "aliased_texture_ids": [],
    }
    return SceneSpec(builder.build(), paths, [], motion, info)


def _revisit(
    agents: int, frames: int, overlap: float, rng: np.random.Generator, loop_frames: int | None
) -> SceneSpec:
    """The ``revisit`` preset (module docstring)."""
    jump = math.ceil(REVISIT_SHARE * frames)
    target = frames // 5
    spec = rooms(agents, jump, overlap, rng, aliasing=False, loop_frames=loop_frames)
    motion = spec.motion
    paths = []
    for first in spec.paths:
        rest = ride(
            spec.loop,
            float(first.arc[target]) + 0.5 * motion.speed,
            frames - jump,
            motion,
            0.0,
            rng.uniform(0, 2 * np.pi, 4),
        )
        paths.append(
            AgentPath(
                arc=np.concatenate([first.arc, rest.arc]),
                positions=np.concatenate([first.positions, rest.positions]),
                rotations=np.concatenate([first.rotations, rest.rotations]),
                jumps=(jump,),
            )
        )
    info = {**spec.info, "revisit_jump_frame": jump, "revisit_target_frame": target}
    return SceneSpec(spec.scene, paths, spec.meetings, motion, info, loop=spec.loop)


def build_preset(
    preset: str, agents: int, frames: int, overlap: float, seed: int, loop_frames: int | None = None
) -> SceneSpec:
    """Generate the scene and agent paths of ``preset`` (validated by the caller: one of
    :data:`PRESETS`, at least :data:`MIN_FRAMES` frames).

    Args:
        preset: the preset name.
        agents: number of agents N >= 1.
        frames: frames per agent.
        overlap: fraction of each agent's path shared with a neighbour.
        seed: random seed of the scene and paths.
        loop_frames: lay the loop out for at least this many frames of motion per agent
            (:mod:`.presets`); None: for ``frames``.

    Raises:
        ValueError: unknown preset or too few frames for it.
    """
    if frames < MIN_FRAMES.get(preset, 2):
        raise ValueError(f"preset {preset!r} needs at least {MIN_FRAMES[preset]} frames")
    rng = np.random.default_rng(seed)
    if preset in BASE_PRESETS:
        return build_base_preset(preset, agents, frames, overlap, rng, loop_frames)
    if preset == "rotation":
        return _rotation(agents, frames, overlap, rng)
    if preset == "fast":
        return rooms(
            agents,
            frames,
            overlap,
            rng,
            aliasing=False,
            loop_frames=loop_frames,
            motion=CameraMotion(speed=FAST_FACTOR * CameraMotion().speed),
        )
    if preset == "low-texture":
        return rooms(
            agents, frames, overlap, rng, aliasing=False, plain=True, loop_frames=loop_frames
        )
    if preset == "covered":
        spec = rooms(agents, frames, overlap, rng, aliasing=False, loop_frames=loop_frames)
        first, last = covered_frames(frames)
        return SceneSpec(
            spec.scene,
            spec.paths,
            spec.meetings,
            spec.motion,
            {**spec.info, "covered_frames": [first, last]},
            loop=spec.loop,
            covered=(first, last),
        )
    if preset == "revisit":
        return _revisit(agents, frames, overlap, rng, loop_frames)
    raise ValueError(f"unknown preset {preset!r}")
