"""Scene primitives with exact ray intersection and surface-local appearance keys.

World frame: z up, ground plane z = 0, metres. Each primitive answers two questions for
a bundle of rays from one camera centre ``o``:

* ``intersect(o, d)``: ray parameter ``lam`` of the first hit (``inf`` for a miss).
  Directions ``d`` need not be unit; with camera rays whose camera-frame z component is
  1, ``lam`` is the z-depth directly.
* ``surface(p)``: appearance key (texture id, s, t) and the vertical component of the
  outward normal at world points ``p`` on the primitive (the face is the nearest one).

Surface parameterisations are local to the primitive (metres from a face corner, arc
length around an axis, height above the base), so two primitives of identical size that
share texture ids show identical keys: the aliasing the ``aliasing`` preset relies on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Hits closer than this along the ray are ignored (the camera is never inside a solid).
NEAR = 1e-3

SurfaceKeys = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: Ray directions or points as three component arrays of one common (any) shape; the
#: renderer keeps them as separate contiguous planes, which numpy handles far faster
#: than ``(M, 3)`` rows.
Components = tuple[np.ndarray, np.ndarray, np.ndarray]


def _quadratic_roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both real roots of ``a x^2 + b x + c = 0`` (``nan`` where none), numerically stable.

    Uses ``q = -(b + sign(b) sqrt(disc)) / 2``, roots ``q / a`` and ``c / q``, which stays
    finite when ``a`` vanishes (a ray parallel to a cone's generator).
    """
    disc = b * b - 4.0 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        q = -0.5 * (b + np.copysign(np.sqrt(disc), b))
        return q / a, c / q


def _nearest_valid(
    roots: tuple[np.ndarray, np.ndarray], oz: float, dz: np.ndarray, z_lo: float, z_hi: float
) -> np.ndarray:
    """Smallest root > NEAR whose hit height lies in ``[z_lo, z_hi]`` (``inf`` if none)."""
    lam = np.full(dz.shape, np.inf)
    for root in roots:
        with np.errstate(invalid="ignore"):
            z = oz + root * dz
            ok = (root > NEAR) & (z >= z_lo) & (z <= z_hi)
        lam = np.where(ok, np.fmin(lam, root), lam)
    return lam


def _disc_hit(
    o: np.ndarray, d: Components, center: tuple[float, float], radius: float, z: float
) -> np.ndarray:
    """``lam`` of the horizontal disc of ``radius`` at height ``z`` (``inf`` on a miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (z - o[2]) / d[2]
        inside = (o[0] - center[0] + lam * d[0]) ** 2 + (
            o[1] - center[1] + lam * d[1]
        ) ** 2 <= radius * radius
    return np.where(inside & (lam > NEAR), lam, np.inf)


@dataclass(frozen=True)
class Box:
    """A box rotated about the vertical axis (buildings, walls, crates).

    Attributes:
        center: ``(3,)`` world centre.
        half: ``(3,)`` half extents along the box's local x, y, z.
        yaw: rotation about world z in radians (local x = world (cos yaw, sin yaw, 0)).
        face_ids: texture ids of the faces +x, -x, +y, -y, +z, -z (local axes).
    """

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    face_ids: tuple[int, int, int, int, int, int]

    def corners(self) -> np.ndarray:
        """``(8, 3)`` world corners."""
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return (signs * np.asarray(self.half)) @ rot.T + np.asarray(self.center)

    def _local(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, offset: bool) -> Components:
        """World vectors (``offset=False``) or points into the box frame."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        if offset:
            x, y, z = x - self.center[0], y - self.center[1], z - self.center[2]
        return c * x + s * y, c * y - s * x, z

    def intersect(self, o: np.ndarray, d: Components) -> np.ndarray:
        """Slab test: ``lam`` of the first hit (``inf`` on a miss), shaped like ``d[0]``."""
        o_l = self._local(*o, offset=True)
        d_l = self._local(*d, offset=False)
        t_near = t_far = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for oi, di, hi in zip(o_l, d_l, self.half):
                inv = 1.0 / di
                t1 = (-hi - oi) * inv
                t2 = (hi - oi) * inv
                lo, up = np.fmin(t1, t2), np.fmax(t1, t2)
                t_near = lo if t_near is None else np.fmax(t_near, lo)
                t_far = up if t_far is None else np.fmin(t_far, up)
        return np.where((t_near <= t_far) & (t_near > NEAR), t_near, np.inf)

    def surface(self, p: Components) -> SurfaceKeys:
        """Keys at world points ``p`` on the box surface.

        The face is the one the point lies closest to. Vertical faces: s runs left to
        right as seen from outside, from the face's left edge; t is the height above the
        box bottom. Top/bottom: offsets from a corner.
        """
        hx, hy, hz = self.half
        x, y, z = self._local(*p, offset=True)
        gap = np.stack([hx - np.abs(x), hy - np.abs(y), hz - np.abs(z)])
        axis = np.argmin(gap, axis=0)
        negative = np.choose(axis, [x, y, z]) < 0
        face = 2 * axis + negative
        height = z + hz
        s = np.choose(face, [y + hy, hy - y, hx - x, x + hx, x + hx, x + hx])
        t = np.choose(face, [height, height, height, height, y + hy, hy - y])
        ids = np.asarray(self.face_ids)[face]
        nz = np.choose(face, [0.0, 0.0, 0.0, 0.0, 1.0, -1.0]).astype(np.float64)
        return ids, s, t, nz


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder (pillars, trunks, the central tower).

    Attributes:
        center: ``(2,)`` world x, y of the axis.
        radius: metres.
        z0, z1: bottom and top heights.
        yaw: angle where the side's arc-length coordinate s starts.
        side_id, top_id: texture ids (the bottom shares ``top_id``).
    """

    center: tuple[float, float]
    radius: float
    z0: float
    z1: float
    yaw: float
    side_id: int
    top_id: int

    def corners(self) -> np.ndarray:
        """``(8, 3)`` corners of the world bounding box."""
        cx, cy = self.center
        r = self.radius
        return np.array(
            [
                [cx + x * r, cy + y * r, z]
                for x in (-1, 1)
                for y in (-1, 1)
                for z in (self.z0, self.z1)
            ]
        )

    def intersect(self, o: np.ndarray, d: Components) -> np.ndarray:
        """``lam`` of the first hit on the side or the caps, shaped like ``d[0]``."""
        px, py = o[0] - self.center[0], o[1] - self.center[1]
        dx, dy, dz = d
        a = dx * dx + dy * dy
        b = 2.0 * (px * dx + py * dy)
        c = px * px + py * py - self.radius**2
        lam = _nearest_valid(_quadratic_roots(a, b, c), o[2], dz, self.z0, self.z1)
        for z_cap in (self.z0, self.z1):
            lam = np.fmin(lam, _disc_hit(o, d, self.center, self.radius, z_cap))
        return lam

    def surface(self, p: Components) -> SurfaceKeys:
        """Side: s = arc length from ``yaw``, t = height above z0. Caps: corner offsets."""
        x, y = p[0] - self.center[0], p[1] - self.center[1]
        radial = np.hypot(x, y)
        side = np.abs(radial - self.radius) < np.minimum(
            np.abs(p[2] - self.z0), np.abs(p[2] - self.z1)
        )
        angle = np.mod(np.arctan2(y, x) - self.yaw, 2.0 * np.pi)
        s = np.where(side, self.radius * angle, x + self.radius)
        t = np.where(side, p[2] - self.z0, y + self.radius)
        ids = np.where(side, self.side_id, self.top_id)
        top = np.abs(p[2] - self.z1) < np.abs(p[2] - self.z0)
        nz = np.where(side, 0.0, np.where(top, 1.0, -1.0))
        return ids, s, t, nz


@dataclass(frozen=True)
class Cone:
    """A vertical cone, apex up (shrubs, tree crowns).

    Attributes:
        center: ``(2,)`` world x, y of the axis.
        radius: base radius; z_base: base height; height: apex above the base.
        yaw: angle where the side's arc-length coordinate starts.
        side_id, base_id: texture ids.
    """

    center: tuple[float, float]
    radius: float
    z_base: float
    height: float
    yaw: float
    side_id: int
    base_id: int

    def corners(self) -> np.ndarray:
        """``(8, 3)`` corners of the world bounding box."""
        cx, cy = self.center
        r = self.radius
        return np.array(
            [
                [cx + x * r, cy + y * r, z]
                for x in (-1, 1)
                for y in (-1, 1)
                for z in (self.z_base, self.z_base + self.height)
            ]
        )

    def intersect(self, o: np.ndarray, d: Components) -> np.ndarray:
        """``lam`` of the first hit on the side or the base disc, shaped like ``d[0]``."""
        k2 = (self.radius / self.height) ** 2
        apex = self.z_base + self.height
        px, py, pz = o[0] - self.center[0], o[1] - self.center[1], apex - o[2]
        dx, dy, dz = d
        # (px + l dx)^2 + (py + l dy)^2 = k^2 (pz - l dz)^2, below the apex.
        a = dx * dx + dy * dy - k2 * dz * dz
        b = 2.0 * (px * dx + py * dy + k2 * pz * dz)
        c = px * px + py * py - k2 * pz * pz
        lam = _nearest_valid(_quadratic_roots(a, b, c), o[2], dz, self.z_base, apex)
        return np.fmin(lam, _disc_hit(o, d, self.center, self.radius, self.z_base))

    def surface(self, p: Components) -> SurfaceKeys:
        """Side: s = arc length at the base radius, t = height. Base: corner offsets."""
        x, y = p[0] - self.center[0], p[1] - self.center[1]
        radial = np.hypot(x, y)
        apex = self.z_base + self.height
        slant = np.hypot(self.radius, self.height)
        side_gap = np.abs(radial - self.radius * (apex - p[2]) / self.height) * self.height / slant
        side = side_gap < np.abs(p[2] - self.z_base)
        angle = np.mod(np.arctan2(y, x) - self.yaw, 2.0 * np.pi)
        s = np.where(side, self.radius * angle, x + self.radius)
        t = np.where(side, p[2] - self.z_base, y + self.radius)
        ids = np.where(side, self.side_id, self.base_id)
        nz = np.where(side, self.radius / slant, -1.0)
        return ids, s, t, nz


Primitive = Box | Cylinder | Cone


@dataclass(frozen=True)
class StadiumRoad:
    """A closed road: points within ``half_width`` of a stadium centre line (two straights
    of length ``straight`` joined by half circles of radius ``radius``, centred at
    ``center``, straights parallel to world x).

    Its surface keys are (arc length along the centre line, signed lateral offset), so
    lane markings follow the road.
    """

    center: tuple[float, float]
    straight: float
    radius: float
    half_width: float
    texture_id: int

    @property
    def length(self) -> float:
        """Length of the centre line."""
        return 2.0 * self.straight + 2.0 * np.pi * self.radius

    def coordinates(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Arc length (from the start of the lower straight, counter-clockwise) and lateral
        offset (positive outwards) of ground points ``(M,)``."""
        half = 0.5 * self.straight
        u = x - self.center[0]
        v = y - self.center[1]
        clamped = np.clip(u, -half, half)
        dist = np.hypot(u - clamped, v)
        lateral = dist - self.radius
        on_straight = np.abs(u) <= half
        arc_low = clamped + half
        arc_high = self.straight + np.pi * self.radius + (half - clamped)
        # On the end caps the arc length follows the angle around the cap centre.
        ang_right = np.arctan2(v, u - half) + 0.5 * np.pi
        ang_left = np.arctan2(-v, -(u + half)) + 0.5 * np.pi
        arc_right = self.straight + self.radius * ang_right
        arc_left = 2.0 * self.straight + np.pi * self.radius + self.radius * ang_left
        arc = np.where(
            on_straight, np.where(v < 0, arc_low, arc_high), np.where(u > 0, arc_right, arc_left)
        )
        return np.mod(arc, self.length), lateral


@dataclass(frozen=True)
class Ground:
    """The ground plane z = 0: paving keyed by world (x, y), optionally a road on top."""

    texture_id: int
    road: StadiumRoad | None = None

    def intersect(self, o: np.ndarray, d: Components) -> np.ndarray:
        """``lam`` of the plane z = 0 (``inf`` for rays that do not descend)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -o[2] / d[2]
        return np.where((d[2] < 0) & (lam > NEAR), lam, np.inf)

    def surface(self, p: Components) -> SurfaceKeys:
        """Keys at ground points: (id, x, y) off-road, (road id, arc length, lateral
        offset) on the road."""
        x, y = p[0], p[1]
        ids = np.full(x.shape, self.texture_id, dtype=np.int64)
        s, t = x.copy(), y.copy()
        if self.road is not None:
            arc, lateral = self.road.coordinates(x, y)
            on_road = np.abs(lateral) < self.road.half_width
            ids[on_road] = self.road.texture_id
            s[on_road] = arc[on_road]
            t[on_road] = lateral[on_road]
        return ids, s, t, np.ones_like(x)
