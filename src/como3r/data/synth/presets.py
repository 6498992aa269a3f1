"""The scene presets of ``como3r synth``: layouts, camera paths and where agents meet.

``default``
    A walled ring of N rooms around a central tower. The camera loop is a flower with one
    petal per room; its waists pass through doors in the walls between rooms. Agents
    share the stretches around the doors (:mod:`.trajectories`), walls taller than
    anything else keep the rest of each room private.
``aliasing``
    The same, but the walls between rooms and the ring wall around them are rows of
    identical buildings (same size, same texture ids and parameterisation), so different
    agents see identical façades at different places.
``no-meeting``
    One sealed walled compound per agent, each agent on a closed loop inside its own:
    no two agents ever see the same surface. ``overlap`` is ignored.
``forward``
    Driving: a stadium-shaped ring road lined with buildings, cameras looking straight
    ahead at 12 m/s, little parallax.

Each preset lays its loop out for the agents' paths, so a short path is a small, tight
loop (one agent turns 360 degrees over its frames). ``loop_frames`` makes the loop at least
that many frames of motion long instead: the agents then ride the start of a bigger loop,
with the turn per frame of a path of ``loop_frames`` frames, and neighbours still meet
(all but the last and the first).

The motion and appearance families built on these (``rotation``, ``fast``, ``low-texture``,
``covered``, ``revisit``) are in :mod:`.families`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from como3r.data.synth.layout import MAX_CLUTTER_HEIGHT, ModuleStyle, SceneBuilder
from como3r.data.synth.primitives import Cylinder, StadiumRoad
from como3r.data.synth.render import Scene
from como3r.data.synth.textures import Kind
from como3r.data.synth.trajectories import (
    AgentPath,
    CameraMotion,
    LoopCurve,
    RingPlan,
    fit_flower_bulge,
    flower_loop,
    plan_ring,
    ride,
    stadium_loop,
)

#: the presets of this module; :data:`.families.PRESETS` lists every preset
BASE_PRESETS = ("default", "aliasing", "no-meeting", "forward")

#: Minimal horizontal distance between a camera and any solid.
CLEARANCE = 1.2
#: Walls are taller than any clutter (see layout.MAX_CLUTTER_HEIGHT).
WALL_HEIGHTS = (8.0, 11.0)


@dataclass(frozen=True)
class Meeting:
    """A stretch driven by two agents: agent ``agents[0]`` ends on it, ``agents[1]``
    starts on it; ``frames`` are each agent's first and last frame on the stretch."""

    agents: tuple[int, int]
    junction: tuple[float, float]
    length: float
    frames: tuple[tuple[int, int], tuple[int, int]]


@dataclass(frozen=True)
class SceneSpec:
    """A generated scene with its agents' ground-truth paths.

    Attributes:
        loop: the loop the agents ride, when they ride one.
        covered: first and last frame (inclusive) of every agent during which the lens is
            covered (the ``covered`` preset): written black, without depth or keys.
    """

    scene: Scene
    paths: list[AgentPath]
    meetings: list[Meeting]
    motion: CameraMotion
    info: dict = field(default_factory=dict)
    loop: LoopCurve | None = None
    covered: tuple[int, int] | None = None


def _loop_radius(length: float, petals: int) -> tuple[float, float]:
    """Waist radius and bulge of a flower loop of ``length``: a circle while it is small,
    otherwise petals grow outwards from a waist of at least 5 m."""
    circle = length / (2.0 * math.pi)
    if circle <= 5.0:
        return circle, 0.0
    radius = max(5.0, 0.45 * circle)
    return radius, fit_flower_bulge(length, radius, petals)


def _plan(
    agents: int, frames: int, overlap: float, motion: CameraMotion, loop_frames: int | None
) -> RingPlan:
    """The ring plan of agents riding ``frames`` at ``motion.speed``, on a loop at least
    ``loop_frames`` frames of motion long."""
    return plan_ring(
        agents,
        motion.speed * (frames - 1),
        overlap,
        motion.speed,
        motion.speed * (loop_frames or 0),
    )


def _ring_paths(
    curve: LoopCurve,
    plan: RingPlan,
    frames: int,
    motion: CameraMotion,
    lateral: list[float],
    rng: np.random.Generator,
) -> tuple[list[AgentPath], list[Meeting], float]:
    """Every agent's path on ``curve`` as ``plan`` places it, the meetings of neighbours
    (not of the last and the first on an open plan) and the shared stretch length."""
    agents = len(plan.starts)
    path_length = motion.speed * (frames - 1)
    paths = [
        ride(curve, float(plan.starts[a]), frames, motion, lateral[a], rng.uniform(0, 2 * np.pi, 4))
        for a in range(agents)
    ]
    meetings = []
    if agents > 1:
        eps = 1e-9 + 1e-6 * motion.speed
        for a in range(agents if plan.closed else agents - 1):
            b = (a + 1) % agents
            tail = np.nonzero(paths[a].arc >= plan.starts[a] + path_length - plan.shared - eps)[0]
            head = np.nonzero(paths[b].arc <= plan.starts[b] + plan.shared + eps)[0]
            junction, _ = curve.at(np.array([plan.junctions[b]]))
            meetings.append(
                Meeting(
                    agents=(a, b),
                    junction=(float(junction[0, 0]), float(junction[0, 1])),
                    length=float(plan.shared),
                    frames=((int(tail[0]), int(tail[-1])), (int(head[0]), int(head[-1]))),
                )
            )
    return paths, meetings, float(plan.shared)


def _lateral_offsets(agents: int, amplitude: float) -> list[float]:
    return [amplitude * (1 if a % 2 == 0 else -1) for a in range(agents)]


def _door_walls(
    builder: SceneBuilder,
    theta: float,
    radius: float,
    tower: float,
    outer: float,
    style: ModuleStyle,
) -> None:
    """The wall between two rooms along the ray at angle ``theta``, with a door where the
    loop's waist crosses it: an outer row of buildings from the door to the ring wall and
    an inner one from the tower to the door, each reaching as close to the waist as the
    clearance to the camera paths allows."""
    module, thickness = 4.0, 1.2
    u = np.array([math.cos(theta), math.sin(theta)])
    far = outer + 2.0
    for start in np.arange(radius + builder.clearance, far - module, 0.25):
        if builder.box_clear(
            0.5 * (start + far) * u, (0.5 * (far - start), 0.5 * thickness), theta
        ):
            builder.wall(tuple(start * u), tuple(far * u), thickness, WALL_HEIGHTS, module, style)
            break
    for end in np.arange(radius - builder.clearance, tower + 0.5, -0.25):
        if builder.box_clear(
            0.5 * (tower + end) * u, (0.5 * (end - tower), 0.5 * thickness), theta
        ):
            builder.wall(tuple(tower * u), tuple(end * u), thickness, WALL_HEIGHTS, end - tower)
            break


def rooms(
    agents: int,
    frames: int,
    overlap: float,
    rng: np.random.Generator,
    aliasing: bool,
    motion: CameraMotion = CameraMotion(),
    plain: bool = False,
    loop_frames: int | None = None,
) -> SceneSpec:
    """The ``default`` and ``aliasing`` presets (module docstring); with another camera
    ``motion`` or ``plain`` textures (:class:`SceneBuilder`), the rooms of the families in
    :mod:`.families`. The loop is at least ``loop_frames`` frames of motion long."""
    plan = _plan(agents, frames, overlap, motion, loop_frames)
    radius, bulge = _loop_radius(plan.loop_length, agents)
    phase = float(rng.uniform(0, 2 * np.pi))
    curve = flower_loop((0.0, 0.0), radius, bulge, agents, phase)
    offset = min(0.2, 0.1 * radius)
    paths, meetings, shared = _ring_paths(
        curve, plan, frames, motion, _lateral_offsets(agents, offset), rng
    )
    builder = SceneBuilder(rng, curve.points, CLEARANCE + offset, plain=plain)
    outer = max(radius + bulge + 7.0, 10.0)

    style = ring_style = ModuleStyle()
    if aliasing:
        style = ModuleStyle(builder.texture(Kind.FACADE), builder.texture(Kind.FACADE))
        ring_style = ModuleStyle(builder.texture(Kind.FACADE), builder.texture(Kind.FACADE))
    aliased = [i for st in (style, ring_style) for i in (st.left_id, st.right_id) if i is not None]
    tower = radius - builder.clearance - 0.3
    if tower >= 0.4:
        builder.primitives.append(
            Cylinder(
                (0.0, 0.0),
                tower,
                0.0,
                WALL_HEIGHTS[0],
                phase,
                builder.texture(Kind.FACADE),
                builder.texture(Kind.ROOF),
            )
        )
        builder.footprints.append((0.0, 0.0, tower))
    else:
        tower = 0.0
    for k in range(agents):
        _door_walls(builder, phase + 2.0 * math.pi * k / agents, radius, tower, outer, style)
    builder.ring_wall(
        (0.0, 0.0),
        outer,
        WALL_HEIGHTS,
        max(8, math.ceil(2 * math.pi * outer / 8)),
        style=ring_style,
    )

    def sample(g: np.random.Generator) -> tuple[float, float, float]:
        r = outer * math.sqrt(g.uniform())
        a = g.uniform(0, 2 * np.pi)
        return r * math.cos(a), r * math.sin(a), a

    area = math.pi * outer**2
    builder.scatter(sample, int(np.clip(area / 12.0, 8, 300)))
    info = {
        "loop": "flower",
        "loop_length_m": curve.length,
        "waist_radius_m": radius,
        "bulge_m": bulge,
        "shared_length_m": shared,
        "aliased_texture_ids": aliased,
    }
    return SceneSpec(builder.build(), paths, meetings, motion, info, loop=curve)


def _compounds(
    agents: int, frames: int, rng: np.random.Generator, loop_frames: int | None
) -> SceneSpec:
    """The ``no-meeting`` preset: one sealed compound and one closed loop per agent (an
    open part of a loop ``loop_frames`` frames of motion long, if that is longer)."""
    motion = CameraMotion()
    # L plus one step closes the loop; a longer loop_frames leaves it open.
    loop_length = motion.speed * max(frames, loop_frames or 0)
    radius, bulge = _loop_radius(loop_length, 3)
    half = radius + bulge + 6.0
    thickness = 1.0
    pitch = 2.0 * (half + thickness) + 4.0
    curves = [
        flower_loop((a * pitch, 0.0), radius, bulge, 3, float(rng.uniform(0, 2 * np.pi)))
        for a in range(agents)
    ]
    paths = [
        ride(curves[a], 0.0, frames, motion, 0.0, rng.uniform(0, 2 * np.pi, 4))
        for a in range(agents)
    ]
    builder = SceneBuilder(rng, np.vstack([c.points for c in curves]), CLEARANCE)
    for a in range(agents):
        cx = a * pitch
        h, e = half + 0.5 * thickness, half + thickness
        # Counter-clockwise, so the left (+y) façades face into the compound.
        corners = [
            (cx - e, -h),
            (cx + e, -h),
            (cx + h, -e),
            (cx + h, e),
            (cx + e, h),
            (cx - e, h),
            (cx - h, e),
            (cx - h, -e),
        ]
        for i in range(0, 8, 2):
            builder.wall(corners[i], corners[i + 1], thickness, (9.0, 11.0), 2 * e / 3)
        tower = radius - builder.clearance - 0.3
        if tower >= 0.4:
            tex = builder.texture(Kind.CONCRETE)
            builder.primitives.append(
                Cylinder(
                    (cx, 0.0),
                    tower,
                    0.0,
                    MAX_CLUTTER_HEIGHT,
                    0.0,
                    tex,
                    builder.materials.clone(tex),
                )
            )
            builder.footprints.append((cx, 0.0, tower))

    def sample(g: np.random.Generator) -> tuple[float, float, float]:
        a = int(g.integers(agents))
        return a * pitch + g.uniform(-half, half), g.uniform(-half, half), 0.0

    builder.scatter(sample, int(np.clip(agents * (2 * half) ** 2 / 12.0, 8, 300)))
    info = {
        "loop": "flower",
        "loop_length_m": curves[0].length,
        "compound_half_size_m": half,
        "shared_length_m": 0.0,
        "aliased_texture_ids": [],
    }
    return SceneSpec(builder.build(), paths, [], motion, info)


def _road(
    agents: int, frames: int, overlap: float, rng: np.random.Generator, loop_frames: int | None
) -> SceneSpec:
    """The ``forward`` preset: a ring road; agents drive its outer lane (at least
    ``loop_frames`` frames of motion long)."""
    motion = CameraMotion(
        speed=0.4,
        yaw_amplitude=0.5,
        yaw_wavelength=40.0,
        pitch=-2.0,
        pitch_amplitude=0.3,
        roll_amplitude=0.0,
        bob_amplitude=0.01,
    )
    plan = _plan(agents, frames, overlap, motion, loop_frames)
    half_width, lane = 3.5, 1.75
    loop_length = plan.loop_length
    lane_radius = max(0.08 * loop_length, lane + half_width + 0.5)
    straight = 0.5 * (loop_length - 2.0 * math.pi * lane_radius)
    if straight < 0.0:
        lane_radius, straight = loop_length / (2.0 * math.pi), 0.0
    curve = stadium_loop((0.0, 0.0), straight, lane_radius)
    road_radius = lane_radius - lane
    road = None
    builder_clearance = CLEARANCE + 0.3
    paths, meetings, shared = _ring_paths(
        curve, plan, frames, motion, _lateral_offsets(agents, 0.15), rng
    )
    builder = SceneBuilder(rng, curve.points, builder_clearance)
    if road_radius > half_width:
        road = StadiumRoad(
            (0.0, 0.0),
            straight,
            road_radius,
            half_width,
            builder.materials.add(
                Kind.ROAD, (0.22, 0.22, 0.23), (0.92, 0.92, 0.88), (half_width, 6.0)
            ),
        )

        def on_road(x: float, y: float, r: float) -> bool:
            _, lateral = road.coordinates(np.array([x]), np.array([y]))
            return bool(abs(lateral[0]) < half_width + 0.5 + r)

        builder.keep_out = on_road
    inner = road_radius - half_width - 2.0
    if inner >= 1.0 and straight >= 4.0:
        builder.wall(
            (-0.5 * straight, 0.0),
            (0.5 * straight, 0.0),
            2 * min(inner, 6.0),
            WALL_HEIGHTS,
            straight / max(1, round(straight / 8.0)),
        )
    outer = 0.5 * straight + lane_radius + half_width + 16.0
    builder.ring_wall((0.0, 0.0), outer, WALL_HEIGHTS, max(8, math.ceil(2 * math.pi * outer / 10)))

    def sample(g: np.random.Generator) -> tuple[float, float, float]:
        xy, tangent = curve.at(np.array([g.uniform(0, curve.length)]))
        side = -1.0 if g.uniform() < 0.7 else 1.0  # mostly outside the loop
        dist = lane + half_width + g.uniform(1.0, 12.0) if side < 0 else g.uniform(2.0, 12.0)
        normal = np.array([-tangent[0, 1], tangent[0, 0]])
        x, y = xy[0] + side * dist * normal
        return float(x), float(y), math.atan2(tangent[0, 1], tangent[0, 0])

    builder.scatter(sample, int(np.clip(curve.length * 0.6, 8, 300)))
    info = {
        "loop": "stadium",
        "loop_length_m": curve.length,
        "lane_radius_m": lane_radius,
        "straight_m": straight,
        "shared_length_m": shared,
        "aliased_texture_ids": [],
    }
    return SceneSpec(builder.build(road), paths, meetings, motion, info, loop=curve)


def build_base_preset(
    preset: str,
    agents: int,
    frames: int,
    overlap: float,
    rng: np.random.Generator,
    loop_frames: int | None = None,
) -> SceneSpec:
    """Generate the scene and agent paths of one of :data:`BASE_PRESETS` (validated by the
    caller) from the scene's random generator; the loop is at least ``loop_frames`` frames
    of motion long (None: as long as the agents' paths make it)."""
    if preset == "default":
        return rooms(agents, frames, overlap, rng, aliasing=False, loop_frames=loop_frames)
    if preset == "aliasing":
        return rooms(agents, frames, overlap, rng, aliasing=True, loop_frames=loop_frames)
    if preset == "no-meeting":
        return _compounds(agents, frames, rng, loop_frames)
    if preset == "forward":
        return _road(agents, frames, overlap, rng, loop_frames)
    raise ValueError(f"unknown preset {preset!r}")
