"""Building blocks of synthetic scenes: walls of façade modules and scattered clutter.

A :class:`SceneBuilder` collects primitives and keeps what it needs to place new ones
safely: the footprints already taken, the wall segments, and a k-d tree of the camera
paths so that nothing is ever placed closer than a clearance to any camera.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from como3r.data.synth.primitives import Box, Cone, Cylinder, Ground, Primitive, StadiumRoad
from como3r.data.synth.render import Scene
from como3r.data.synth.textures import Kind, MaterialTable, random_material

#: Objects scattered in the open are lower than this, walls are taller: a camera at 1.5 m
#: never sees anything behind a wall over its top.
MAX_CLUTTER_HEIGHT = 6.0


@dataclass(frozen=True)
class ModuleStyle:
    """Texture ids of a wall module; ``None`` draws fresh ids for every module."""

    left_id: int | None = None
    right_id: int | None = None


@dataclass
class SceneBuilder:
    """Accumulates a scene while keeping placement constraints.

    Attributes:
        rng: the scene's random generator (the only source of randomness).
        path_points: ``(M, 2)`` samples of every camera path (for clearance checks).
        clearance: minimal horizontal distance from a camera path to any solid.
        plain: every texture, ground included, is flat paint with sparse marks
            (:attr:`Kind.PLAIN`; the ``low-texture`` preset) whatever kind is asked for.
    """

    rng: np.random.Generator
    path_points: np.ndarray
    clearance: float
    plain: bool = False
    materials: MaterialTable = field(default_factory=MaterialTable)
    primitives: list[Primitive] = field(default_factory=list)
    footprints: list[tuple[float, float, float]] = field(default_factory=list)
    walls: list[tuple[np.ndarray, np.ndarray, float]] = field(default_factory=list)
    keep_out: Callable[[float, float, float], bool] | None = None

    def __post_init__(self) -> None:
        self._path_tree = cKDTree(self.path_points)
        self.ground_id = self.texture(Kind.PAVING)

    def texture(self, kind: Kind) -> int:
        """A fresh texture id of the given kind (of :attr:`Kind.PLAIN` if ``plain``)."""
        return random_material(self.materials, Kind.PLAIN if self.plain else kind, self.rng)

    def family(self, kind: Kind, count: int) -> list[int]:
        """``count`` ids of one look (same colours, own noise): the faces of one object
        must not share keys, or its opposite sides would alias."""
        first = self.texture(kind)
        return [first] + [self.materials.clone(first) for _ in range(count - 1)]

    def path_distance(self, x: float, y: float) -> float:
        """Horizontal distance from (x, y) to the nearest camera path sample."""
        return float(self._path_tree.query([x, y])[0])

    def wall_distance(self, x: float, y: float) -> float:
        """Distance from (x, y) to the surface of the nearest wall segment."""
        if not self.walls:
            return math.inf
        a = np.array([w[0] for w in self.walls])
        b = np.array([w[1] for w in self.walls])
        half_thickness = np.array([w[2] for w in self.walls])
        ab = b - a
        u = np.clip(
            np.einsum("ij,ij->i", np.array([x, y]) - a, ab) / np.einsum("ij,ij->i", ab, ab),
            0.0,
            1.0,
        )
        closest = a + u[:, None] * ab
        return float(np.min(np.hypot(x - closest[:, 0], y - closest[:, 1]) - half_thickness))

    def is_free(self, x: float, y: float, radius: float) -> bool:
        """Whether a footprint of ``radius`` at (x, y) keeps clear of paths, walls, objects
        and the keep-out zone."""
        if self.path_distance(x, y) < self.clearance + radius:
            return False
        if self.keep_out is not None and self.keep_out(x, y, radius):
            return False
        if self.wall_distance(x, y) < radius + 0.2:
            return False
        if not self.footprints:
            return True
        taken = np.asarray(self.footprints)
        gaps = np.hypot(x - taken[:, 0], y - taken[:, 1]) - taken[:, 2] - radius
        return bool(np.all(gaps >= 0.2))

    def box_clear(self, center: np.ndarray, half: tuple[float, float], yaw: float) -> bool:
        """Whether the footprint rectangle (``half`` extents along its local x, y, rotated
        by ``yaw``) keeps the clearance to every camera path."""
        reach = math.hypot(*half) + self.clearance
        near = self._path_tree.query_ball_point(np.asarray(center, float), reach)
        if not near:
            return True
        c, s = math.cos(yaw), math.sin(yaw)
        rel = self.path_points[near] - np.asarray(center)
        local = np.abs(rel @ np.array([[c, -s], [s, c]]))
        outside = np.maximum(local - np.asarray(half), 0.0)
        return bool(np.all(np.hypot(outside[:, 0], outside[:, 1]) >= self.clearance))

    def wall(
        self,
        start: tuple[float, float],
        end: tuple[float, float],
        thickness: float,
        heights: tuple[float, float],
        module_length: float,
        style: ModuleStyle = ModuleStyle(),
    ) -> None:
        """A row of box modules (buildings) from ``start`` towards ``end``.

        The row is made of ``ceil(length / module_length)`` modules of equal length, so it
        may overshoot ``end`` by less than one module (rows end inside other walls). The
        long faces are façades; "left" is the +y side of the row direction. With a fixed
        ``style`` every module is identical (same size, height and texture ids).
        """
        a, b = np.asarray(start, float), np.asarray(end, float)
        length = float(np.linalg.norm(b - a))
        if length <= 0.0:
            return
        direction = (b - a) / length
        yaw = math.atan2(direction[1], direction[0])
        count = max(1, math.ceil(length / module_length - 1e-9))
        identical = style.left_id is not None
        ends = self.family(Kind.STONE, 2 * count)
        roofs = self.family(Kind.ROOF, 2 * count)
        for i in range(count):
            height = heights[0] if identical else float(self.rng.uniform(*heights))
            centre = a + (i + 0.5) * module_length * direction
            left = style.left_id if style.left_id is not None else self.texture(Kind.FACADE)
            right = style.right_id if style.right_id is not None else self.texture(Kind.FACADE)
            self.primitives.append(
                Box(
                    center=(float(centre[0]), float(centre[1]), 0.5 * height),
                    half=(0.5 * module_length, 0.5 * thickness, 0.5 * height),
                    yaw=yaw,
                    face_ids=(
                        ends[2 * i],
                        ends[2 * i + 1],
                        left,
                        right,
                        roofs[2 * i],
                        roofs[2 * i + 1],
                    ),
                )
            )
        self.walls.append((a, a + count * module_length * direction, 0.5 * thickness))

    def ring_wall(
        self,
        center: tuple[float, float],
        radius: float,
        heights: tuple[float, float],
        segments: int,
        thickness: float = 1.5,
        style: ModuleStyle = ModuleStyle(),
    ) -> None:
        """A closed polygon of walls whose inner (left) faces are tangent to the circle
        ``radius`` around ``center``; consecutive segments overlap so it is sealed."""
        outer = radius + 0.5 * thickness
        half_chord = outer * math.tan(math.pi / segments) + thickness
        for k in range(segments):
            ang = 2.0 * math.pi * k / segments
            mid = np.array(center) + outer * np.array([math.cos(ang), math.sin(ang)])
            tangent = np.array([-math.sin(ang), math.cos(ang)])
            self.wall(
                tuple(mid - half_chord * tangent),
                tuple(mid + half_chord * tangent),
                thickness,
                heights,
                2.0 * half_chord,
                style,
            )

    def add_tree(self, x: float, y: float) -> None:
        """A trunk with a conical crown (footprint radius <= 1.5 m)."""
        u = self.rng.uniform
        base, yaw = float(u(1.7, 2.2)), float(u(0, 2 * np.pi))
        bark, leaves = self.family(Kind.BARK, 2), self.family(Kind.FOLIAGE, 2)
        self.primitives.append(Cylinder((x, y), float(u(0.12, 0.2)), 0.0, base + 0.5, yaw, *bark))
        self.primitives.append(
            Cone((x, y), float(u(0.8, 1.5)), base, float(u(2.0, 3.5)), yaw, *leaves)
        )

    def add_building(self, x: float, y: float, half: tuple[float, float], yaw: float) -> None:
        """A low building with façades and stone sides."""
        height = float(self.rng.uniform(3.0, MAX_CLUTTER_HEIGHT))
        faces = [self.texture(Kind.FACADE if i % 2 == 0 else Kind.STONE) for i in range(4)]
        self.primitives.append(
            Box(
                (x, y, 0.5 * height),
                (*half, 0.5 * height),
                yaw,
                (*faces, *self.family(Kind.ROOF, 2)),
            )
        )

    def add_small_object(self, kind: str, x: float, y: float) -> None:
        """A pillar, shrub, crate or bollard."""
        u = self.rng.uniform
        yaw = float(u(0, 2 * np.pi))
        if kind == "pillar":
            self.primitives.append(
                Cylinder(
                    (x, y),
                    float(u(0.2, 0.5)),
                    0.0,
                    float(u(2.5, 5.0)),
                    yaw,
                    *self.family(Kind.CONCRETE, 2),
                )
            )
        elif kind == "shrub":
            self.primitives.append(
                Cone(
                    (x, y),
                    float(u(0.4, 0.8)),
                    0.0,
                    float(u(0.8, 1.6)),
                    yaw,
                    *self.family(Kind.FOLIAGE, 2),
                )
            )
        elif kind == "crate":
            h = float(u(0.4, 1.2))
            half = (float(u(0.2, 0.6)), float(u(0.2, 0.6)), 0.5 * h)
            self.primitives.append(
                Box((x, y, 0.5 * h), half, yaw, tuple(self.family(Kind.PAINT, 6)))
            )
        else:
            self.primitives.append(
                Cylinder((x, y), 0.1, 0.0, 0.9, yaw, *self.family(Kind.PAINT, 2))
            )

    _SMALL_RADIUS = {"tree": 1.5, "pillar": 0.5, "shrub": 0.8, "crate": 0.9, "bollard": 0.15}

    def add_random_object(self, x: float, y: float, facing: float) -> bool:
        """One random object at (x, y) if it fits; returns whether it was placed.

        ``facing`` is the preferred yaw of buildings (so they line up with the paths).
        """
        kind = str(
            self.rng.choice(
                ["building", "tree", "pillar", "shrub", "crate", "bollard"],
                p=[0.25, 0.2, 0.15, 0.15, 0.15, 0.1],
            )
        )
        if kind == "building":
            half = (float(self.rng.uniform(1.5, 4.0)), float(self.rng.uniform(1.5, 4.0)))
            radius = math.hypot(*half)
        else:
            radius = self._SMALL_RADIUS[kind]
        if not self.is_free(x, y, radius):
            return False
        if kind == "building":
            self.add_building(x, y, half, facing + float(self.rng.uniform(-0.15, 0.15)))
        elif kind == "tree":
            self.add_tree(x, y)
        else:
            self.add_small_object(kind, x, y)
        self.footprints.append((x, y, radius))
        return True

    def scatter(
        self,
        sample: Callable[[np.random.Generator], tuple[float, float, float]],
        count: int,
        attempts_per_object: int = 20,
    ) -> int:
        """Try to place ``count`` random objects at positions drawn by ``sample``
        (returns x, y and a preferred building yaw); returns how many were placed."""
        placed = 0
        for _ in range(count * attempts_per_object):
            if placed >= count:
                break
            x, y, facing = sample(self.rng)
            placed += self.add_random_object(x, y, facing)
        return placed

    def build(self, road: StadiumRoad | None = None) -> Scene:
        """The finished scene."""
        ground = Ground(self.ground_id, road)
        return Scene(tuple(self.primitives), ground, self.materials)
