"""Procedural textures: colour as a pure function of an appearance key (id, s, t).

Every surface of a synthetic scene carries a texture id and surface-local coordinates
``(s, t)`` in metres (manual: docs/api/index.md). The colour of a surface point is a
deterministic function of that key alone, so the same point has the same colour in every
view and two surfaces that share an id and a parameterisation look exactly alike (the
aliasing a learned matcher falls for). Shading only depends on the surface normal's
vertical component, which is the same for every vertical face, so it never breaks that
rule either.

Textures are multi-scale (lattice value noise from ~4 m down to ~5 cm wavelength) plus
structure (windows, blocks, tiles, lane markings), so dense matching has texture at every
scale a 320x240 camera resolves between 1 and 30 m.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

_M32 = 0xFFFFFFFF


class Kind(IntEnum):
    """Texture families; each has its own procedural colour function."""

    PAVING = 0
    ROAD = 1
    FACADE = 2
    STONE = 3
    CONCRETE = 4
    FOLIAGE = 5
    BARK = 6
    ROOF = 7
    PAINT = 8
    PLAIN = 9


def _as_u32(x: np.ndarray | int) -> np.ndarray:
    """Integers (possibly negative) wrapped modulo 2^32."""
    x = np.asarray(x)
    if x.dtype == np.uint32:
        return x
    return (x.astype(np.int64) & _M32).astype(np.uint32)


def _fmix(h: np.ndarray) -> np.ndarray:
    """MurmurHash3's 32-bit finaliser (full avalanche)."""
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> np.uint32(13))
    h = h * np.uint32(0xC2B2AE35)
    return h ^ (h >> np.uint32(16))


def _lattice_mix(h: np.ndarray) -> np.ndarray:
    """One multiply-xorshift round: enough for lattice values of pre-mixed inputs."""
    h = h ^ (h >> np.uint32(15))
    h = h * np.uint32(0x2C1B3C6D)
    return h ^ (h >> np.uint32(12))


def hash_u32(*keys: np.ndarray | int) -> np.ndarray:
    """Integer hash of one or more integer arrays (broadcast), uniform in ``[0, 2^32)``.

    Negative integers wrap modulo 2^32, so the hash is defined on the whole lattice.
    """
    h = np.zeros(np.broadcast_shapes(*(np.shape(k) for k in keys)), dtype=np.uint32)
    with np.errstate(over="ignore"):  # 0-d inputs become numpy scalars, which would warn
        for key in keys:
            h = _fmix(h ^ (_as_u32(key) + np.uint32(0x9E3779B9)))
    return np.asarray(h, dtype=np.uint32)


def hash_unit(*keys: np.ndarray | int) -> np.ndarray:
    """:func:`hash_u32` mapped to float32 in ``[0, 1)``."""
    return hash_u32(*keys).astype(np.float32) * np.float32(1.0 / 4294967296.0)


_PRIME_S = np.uint32(0x8DA6B343)
_PRIME_T = np.uint32(0xD8163841)
_TO_UNIT = 1.0 / 4294967296.0


def value_noise(s: np.ndarray, t: np.ndarray, seed: np.ndarray | int) -> np.ndarray:
    """Smooth lattice value noise in ``[0, 1]`` at unit lattice spacing.

    Args:
        s, t: coordinates in lattice units (any common shape, |coordinate| < 2^31).
        seed: integer seed(s) broadcastable to ``s`` (different seeds give independent
            fields).
    """
    i0 = np.floor(s)
    j0 = np.floor(t)
    fs = s - i0
    ft = t - j0
    fs = fs * fs * (3.0 - 2.0 * fs)
    ft = ft * ft * (3.0 - 2.0 * ft)
    # Lattice hash mix(i P ^ j Q ^ seed); the products are shared by the four corners, and
    # the odd-constant products already spread every input bit, so one multiply-xorshift
    # round (not a full finaliser) decorrelates neighbouring cells.
    seed = _as_u32(seed)
    si0 = i0.astype(np.int32).view(np.uint32) * _PRIME_S
    si1 = si0 + _PRIME_S
    tq = j0.astype(np.int32).view(np.uint32) * _PRIME_T
    tj0 = tq ^ seed
    tj1 = (tq + _PRIME_T) ^ seed
    to_unit = np.asarray(_TO_UNIT, dtype=fs.dtype)
    v00 = _lattice_mix(si0 ^ tj0).astype(fs.dtype) * to_unit
    v10 = _lattice_mix(si1 ^ tj0).astype(fs.dtype) * to_unit
    v01 = _lattice_mix(si0 ^ tj1).astype(fs.dtype) * to_unit
    v11 = _lattice_mix(si1 ^ tj1).astype(fs.dtype) * to_unit
    a = v00 + (v10 - v00) * fs
    b = v01 + (v11 - v01) * fs
    return a + (b - a) * ft


def fbm(
    s: np.ndarray,
    t: np.ndarray,
    seed: np.ndarray | int,
    wavelength: float,
    octaves: int,
    gain: float = 0.6,
) -> np.ndarray:
    """Fractal sum of value noise, zero mean, roughly in ``[-1, 1]``.

    Args:
        s, t: ``(M,)`` surface coordinates in metres.
        seed: ``(M,)`` or scalar integer seed.
        wavelength: coarsest wavelength in metres; each octave halves it.
        octaves: number of octaves.
        gain: amplitude ratio between consecutive octaves (< 1 = smoother).
    """
    k = np.arange(octaves)
    freq = (2.0**k / wavelength)[:, None].astype(s.dtype)
    amplitude = gain**k
    amplitude = (amplitude * (2.0 / amplitude.sum())).astype(s.dtype)
    # All octaves in one call; the offsets decorrelate lattices that would align at 0.
    seeds = _as_u32(seed)[None] + (101 * k).astype(np.uint32)[:, None]
    shift = (0.37 * k[:, None]).astype(s.dtype)
    noise = value_noise(s[None] * freq + shift, t[None] * freq, seeds)
    return amplitude @ (noise - 0.5)


def _band(x: np.ndarray, lo: float | np.ndarray, hi: float | np.ndarray) -> np.ndarray:
    """1.0 where ``lo <= x < hi`` else 0.0."""
    return ((x >= lo) & (x < hi)).astype(x.dtype)


@dataclass
class MaterialTable:
    """Parameters of every texture id of a scene; the id indexes these lists.

    ``color_a``/``color_b`` are RGB in [0, 1]; ``params`` are four kind-specific numbers
    (documented at each colour function).
    """

    kind: list[int] = field(default_factory=list)
    color_a: list[tuple[float, float, float]] = field(default_factory=list)
    color_b: list[tuple[float, float, float]] = field(default_factory=list)
    params: list[tuple[float, float, float, float]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.kind)

    def add(
        self,
        kind: Kind,
        color_a: tuple[float, float, float],
        color_b: tuple[float, float, float],
        params: tuple[float, ...] = (),
    ) -> int:
        """Register a texture and return its id."""
        padded = tuple(float(p) for p in params) + (0.0,) * (4 - len(params))
        self.kind.append(int(kind))
        self.color_a.append(tuple(float(c) for c in color_a))  # type: ignore[arg-type]
        self.color_b.append(tuple(float(c) for c in color_b))  # type: ignore[arg-type]
        self.params.append(padded)  # type: ignore[arg-type]
        return len(self.kind) - 1

    def clone(self, texture_id: int) -> int:
        """A new id with the same kind, colours and proportions (but its own noise): for
        the faces of one object, which must not share keys with each other."""
        return self.add(
            Kind(self.kind[texture_id]),
            self.color_a[texture_id],
            self.color_b[texture_id],
            self.params[texture_id],
        )

    def kinds_of(self) -> dict[int, str]:
        """Texture id -> kind name, for scene.json."""
        return {i: Kind(k).name.lower() for i, k in enumerate(self.kind)}


def _jitter(rng: np.random.Generator, rgb: tuple[float, float, float], amount: float) -> tuple:
    return tuple(float(np.clip(c + rng.uniform(-amount, amount), 0.02, 0.98)) for c in rgb)


_WALL_COLOURS = [
    (0.80, 0.72, 0.60),
    (0.70, 0.45, 0.35),
    (0.85, 0.82, 0.74),
    (0.55, 0.60, 0.65),
    (0.78, 0.62, 0.42),
    (0.60, 0.55, 0.50),
    (0.88, 0.78, 0.62),
    (0.50, 0.42, 0.40),
]
_PAINT_COLOURS = [
    (0.75, 0.20, 0.15),
    (0.15, 0.35, 0.70),
    (0.85, 0.65, 0.10),
    (0.20, 0.55, 0.30),
    (0.55, 0.55, 0.58),
    (0.90, 0.45, 0.10),
]


def random_material(table: MaterialTable, kind: Kind, rng: np.random.Generator) -> int:
    """Add a texture of ``kind`` with seeded random colours and proportions; return its id."""
    u = rng.uniform
    if kind == Kind.FACADE:
        wall = _jitter(rng, _WALL_COLOURS[rng.integers(len(_WALL_COLOURS))], 0.06)
        glass = _jitter(rng, (0.25, 0.32, 0.40), 0.06)
        return table.add(kind, wall, glass, (u(2.8, 3.4), u(2.0, 3.0), u(0.9, 1.4), u(1.2, 1.7)))
    if kind == Kind.STONE:
        stone = _jitter(rng, _WALL_COLOURS[rng.integers(len(_WALL_COLOURS))], 0.08)
        return table.add(kind, stone, (0.35, 0.33, 0.30), (u(0.28, 0.45), u(0.55, 0.95)))
    if kind == Kind.CONCRETE:
        grey = u(0.50, 0.72)
        return table.add(
            kind,
            _jitter(rng, (grey, grey, grey * 0.97), 0.03),
            (0.3, 0.3, 0.3),
            (u(1.0, 1.6), u(0.5, 0.9)),
        )
    if kind == Kind.FOLIAGE:
        return table.add(
            kind, _jitter(rng, (0.12, 0.30, 0.10), 0.04), _jitter(rng, (0.40, 0.62, 0.22), 0.06)
        )
    if kind == Kind.BARK:
        return table.add(kind, _jitter(rng, (0.30, 0.22, 0.15), 0.04), (0.15, 0.11, 0.08))
    if kind == Kind.ROOF:
        return table.add(kind, _jitter(rng, (0.42, 0.38, 0.35), 0.06), (0.25, 0.24, 0.23))
    if kind == Kind.PAINT:
        base = _jitter(rng, _PAINT_COLOURS[rng.integers(len(_PAINT_COLOURS))], 0.05)
        stripe = _jitter(rng, _PAINT_COLOURS[rng.integers(len(_PAINT_COLOURS))], 0.05)
        return table.add(kind, base, stripe, (u(0.15, 0.4),))
    if kind == Kind.PAVING:
        return table.add(
            kind,
            _jitter(rng, (0.62, 0.58, 0.52), 0.05),
            _jitter(rng, (0.30, 0.45, 0.18), 0.04),
            (u(0.45, 0.75),),
        )
    if kind == Kind.PLAIN:
        base = _jitter(rng, _WALL_COLOURS[rng.integers(len(_WALL_COLOURS))], 0.08)
        return table.add(
            kind, base, tuple(0.45 * c for c in base), (u(0.8, 1.2), u(0.03, 0.06), u(0.06, 0.1))
        )
    raise ValueError(f"no random material for {kind!r}")


def _paving(seed, s, t, ca, cb, p) -> np.ndarray:
    """Ground: square tiles (side p0) with grout, patches of grass, multi-scale noise."""
    large = fbm(s, t, seed + 3, 9.0, 3)
    patch = np.clip(2.5 * large + 0.5, 0.0, 1.0)
    out = np.zeros_like(ca)
    # Stones and grass are evaluated only where they show (most pixels show one of them).
    stone = np.flatnonzero(patch < 1.0)
    if stone.size:
        sd, ss, st, tile = seed[stone], s[stone], t[stone], p[stone, 0]
        i, j = np.floor(ss / tile), np.floor(st / tile)
        fs, ft = ss / tile - i, st / tile - j
        grout = np.minimum(np.minimum(fs, 1 - fs), np.minimum(ft, 1 - ft)) * tile < 0.025
        jitter = 0.8 + 0.4 * hash_unit(i.astype(np.int64), j.astype(np.int64), sd)
        stones = ca[stone] * (jitter * (1.0 + 0.25 * fbm(ss, st, sd + 7, 0.4, 3)))[:, None]
        stones[grout] *= 0.55
        out[stone] = stones * (1 - patch[stone, None])
    green = np.flatnonzero(patch > 0.0)
    if green.size:
        sd, ss, st = seed[green], s[green], t[green]
        blades = 0.6 * fbm(ss, st, sd + 11, 0.4, 4, 0.9)
        out[green] += cb[green] * ((1.0 + blades) * patch[green])[:, None]
    return out * (1.0 + 0.3 * large)[:, None]


def _road(seed, s, t, ca, cb, p) -> np.ndarray:
    """Road in (arc length s, lateral offset t): asphalt, edge lines, dashed centre line.

    p0 is the half width of the carriageway, p1 the dash period.
    """
    half, period = p[:, 0], p[:, 1]
    grain = 1.0 + 0.5 * fbm(s, t, seed, 0.4, 4, 0.8) + 0.35 * fbm(s, t, seed + 1, 6.0, 3)
    out = ca * grain[:, None]
    edge = _band(np.abs(t), half - 0.45, half - 0.3)
    dash = _band(np.abs(t), 0.0, 0.08) * (np.mod(s, period) < 0.5 * period)
    paint = np.clip(edge + dash, 0.0, 1.0)[:, None]
    return out * (1 - paint) + cb * (0.85 + 0.15 * grain[:, None]) * paint


def _facade(seed, s, t, ca, cb, p) -> np.ndarray:
    """Façade: plaster wall with a grid of framed windows (p: floor height, window
    spacing, window width, window height); every window has its own glass tone."""
    floor_h, spacing, win_w, win_h = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    col = np.floor(s / spacing)
    row = np.floor(t / floor_h)
    u = s - (col + 0.5) * spacing
    v = t - row * floor_h
    sill = 0.9
    in_frame = (np.abs(u) < 0.5 * win_w + 0.08) & (v > sill - 0.08) & (v < sill + win_h + 0.08)
    in_glass = (np.abs(u) < 0.5 * win_w) & (v > sill) & (v < sill + win_h)
    plaster = 0.25 * fbm(s, t, seed, 2.0, 3, 0.6) + 0.3 * fbm(s, t, seed + 4, 0.25, 2, 0.8)
    wall = ca * (1.0 + plaster)[:, None]
    cornice = _band(v, 0.0, 0.18)[:, None]
    wall = wall * (1 - 0.25 * cornice)
    cell = hash_unit(col.astype(np.int64), row.astype(np.int64), seed)
    tone = 0.6 + 0.8 * cell
    frame = np.full_like(wall, 0.92) * (0.9 + 0.1 * cell[:, None])
    out = np.where(in_frame[:, None], frame, wall)
    g = np.flatnonzero(in_glass)
    gradient = 0.8 + 0.4 * (v[g] - sill) / win_h[g]
    reflection = 1.0 + 0.5 * fbm(s[g] + 0.5 * t[g], t[g], seed[g] + 9, 0.6, 3, 0.8)
    glass = cb[g] * (tone[g] * gradient * reflection)[:, None]
    curtain = (cell[g] > 0.6) & (v[g] - sill > 0.55 * win_h[g])
    glass[curtain] = (0.75 * ca[g][curtain] + 0.2) * (0.8 + 0.4 * cell[g][curtain, None])
    out[g] = glass
    return out


def _stone(seed, s, t, ca, cb, p) -> np.ndarray:
    """Running-bond stone blocks (p: block height, block length) with mortar."""
    bh, bl = p[:, 0], p[:, 1]
    row = np.floor(t / bh)
    shifted = s + 0.5 * bl * np.mod(row, 2)
    col = np.floor(shifted / bl)
    fu, fv = shifted / bl - col, t / bh - row
    mortar = (np.minimum(fu, 1 - fu) * bl < 0.02) | (np.minimum(fv, 1 - fv) * bh < 0.02)
    jitter = 0.7 + 0.6 * hash_unit(row.astype(np.int64), col.astype(np.int64), seed)
    out = ca * (jitter * (1.0 + 0.2 * fbm(s, t, seed + 1, 0.6, 4)))[:, None]
    out[mortar] = cb[mortar]
    return out * (1.0 + 0.15 * fbm(s, t, seed + 2, 3.0, 2))[:, None]


def _concrete(seed, s, t, ca, cb, p) -> np.ndarray:
    """Cast concrete: form-work panels (p: width, height) with seams, tie holes, stains."""
    pw, ph = p[:, 0], p[:, 1]
    i, j = np.floor(s / pw), np.floor(t / ph)
    fu, fv = s / pw - i, t / ph - j
    seam = (np.minimum(fu, 1 - fu) * pw < 0.015) | (np.minimum(fv, 1 - fv) * ph < 0.015)
    hole = (np.hypot((fu - 0.25) * pw, (fv - 0.5) * ph) < 0.03) | (
        np.hypot((fu - 0.75) * pw, (fv - 0.5) * ph) < 0.03
    )
    jitter = 0.85 + 0.3 * hash_unit(i.astype(np.int64), j.astype(np.int64), seed)
    stain = 1.0 + 0.25 * fbm(s, t, seed + 1, 2.5, 3, 0.6) + 0.25 * fbm(s, t, seed + 2, 0.3, 2)
    out = ca * (jitter * stain)[:, None]
    out[seam | hole] *= 0.5
    return out


def _foliage(seed, s, t, ca, cb, p) -> np.ndarray:
    """Leaves: high-contrast clumps of two greens."""
    mix = np.clip(1.6 * fbm(s, t, seed, 0.35, 4, 0.75) + 0.5, 0.0, 1.0)[:, None]
    return (ca * (1 - mix) + cb * mix) * (1.0 + 0.3 * fbm(s, t, seed + 1, 0.08, 2))[:, None]


def _bark(seed, s, t, ca, cb, p) -> np.ndarray:
    """Bark: vertical streaks (noise stretched along t)."""
    streak = fbm(s * 6.0, t * 0.7, seed, 0.5, 4, 0.7)
    mix = np.clip(streak + 0.5, 0.0, 1.0)[:, None]
    return ca * (1 - mix) + cb * mix


def _roof(seed, s, t, ca, cb, p) -> np.ndarray:
    """Gravel roof."""
    mix = np.clip(fbm(s, t, seed, 0.2, 4, 0.8) + 0.5, 0.0, 1.0)[:, None]
    return ca * (1 - mix) + cb * mix


def _paint(seed, s, t, ca, cb, p) -> np.ndarray:
    """Painted metal: horizontal stripes (p0 period), labels, rust noise."""
    stripe = np.mod(t, 2 * p[:, 0]) < p[:, 0]
    label = (np.mod(s, 0.9) < 0.4) & (np.mod(t + 0.1, 0.7) < 0.25)
    out = np.where(stripe[:, None], ca, cb)
    out = np.where(label[:, None], 1.0 - 0.7 * out, out)
    return out * (1.0 + 0.3 * fbm(s, t, seed, 0.5, 4, 0.7))[:, None]


def _plain(seed, s, t, ca, cb, p) -> np.ndarray:
    """Flat paint (the ``low-texture`` preset): colour ``ca`` with a faint 2 m shading and
    sparse dark marks of colour ``cb``: on a grid of cells of side p0 metres, a fraction p1
    of the cells holds one round mark of radius p2 metres at a random place."""
    cell, share, radius = p[:, 0], p[:, 1], p[:, 2]
    i, j = np.floor(s / cell).astype(np.int64), np.floor(t / cell).astype(np.int64)
    marked = hash_unit(i, j, seed) < share
    cs = (i + 0.2 + 0.6 * hash_unit(i, j, seed + 1)) * cell
    ct = (j + 0.2 + 0.6 * hash_unit(i, j, seed + 2)) * cell
    mark = marked & (np.hypot(s - cs, t - ct) < radius)
    out = ca * (1.0 + 0.03 * fbm(s, t, seed + 3, 2.0, 2))[:, None]
    return np.where(mark[:, None], cb, out)


_KIND_FUNCTIONS = {
    Kind.PAVING: _paving,
    Kind.ROAD: _road,
    Kind.FACADE: _facade,
    Kind.STONE: _stone,
    Kind.CONCRETE: _concrete,
    Kind.FOLIAGE: _foliage,
    Kind.BARK: _bark,
    Kind.ROOF: _roof,
    Kind.PAINT: _paint,
    Kind.PLAIN: _plain,
}


class TextureBank:
    """Vectorised colour lookup of a :class:`MaterialTable` (arrays indexed by id)."""

    def __init__(self, table: MaterialTable) -> None:
        self.kind = np.asarray(table.kind, dtype=np.int64)
        self.color_a = np.asarray(table.color_a, dtype=np.float32).reshape(-1, 3)
        self.color_b = np.asarray(table.color_b, dtype=np.float32).reshape(-1, 3)
        self.params = np.asarray(table.params, dtype=np.float32).reshape(-1, 4)
        self.seed = hash_u32(np.arange(len(table.kind)), 0x5EED)

    def albedo(self, ids: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Colour of surface points.

        Args:
            ids: ``(M,)`` integer texture ids (all >= 0).
            s, t: ``(M,)`` surface coordinates in metres.

        Returns:
            ``(M, 3)`` RGB in [0, 1].
        """
        out = np.zeros((ids.shape[0], 3), dtype=np.float32)
        kinds = self.kind[ids]
        # float32 is ample for colours (coordinates stay below ~1e4 m, resolved to 1 mm)
        # and halves the memory traffic of the noise.
        s = s.astype(np.float32)
        t = t.astype(np.float32)
        for kind in np.unique(kinds):
            sel = np.nonzero(kinds == kind)[0]
            tid = ids[sel]
            out[sel] = _KIND_FUNCTIONS[Kind(int(kind))](
                self.seed[tid],
                s[sel],
                t[sel],
                self.color_a[tid],
                self.color_b[tid],
                self.params[tid],
            )
        return np.clip(out, 0.0, 1.0)


def shade(albedo: np.ndarray, normal_z: np.ndarray) -> np.ndarray:
    """View-independent shading: light from above, so every vertical face gets the same
    factor and identical keys keep identical colours whatever the face orientation.

    Args:
        albedo: ``(M, 3)``; normal_z: ``(M,)`` vertical component of the unit normal.
    """
    return albedo * (0.78 + 0.22 * normal_z)[:, None]


def sky_colour(directions: np.ndarray) -> np.ndarray:
    """Sky as a function of the world viewing direction only (it is at infinity).

    Args:
        directions: ``(M, 3)`` world ray directions (any length), z up.

    Returns:
        ``(M, 3)`` RGB in [0, 1]: horizon haze to zenith blue, with clouds.
    """
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    elevation = np.clip(d[:, 2], 0.0, 1.0)
    horizon = np.array([0.78, 0.84, 0.90])
    zenith = np.array([0.30, 0.50, 0.85])
    out = horizon + (zenith - horizon) * np.sqrt(elevation)[:, None]
    # Clouds on a virtual plane 1 km up: a fixed pattern for every camera position.
    lift = np.maximum(d[:, 2], 0.05)
    cx, cy = 1000.0 * d[:, 0] / lift, 1000.0 * d[:, 1] / lift
    cloud = np.clip(1.8 * fbm(cx, cy, 4242, 900.0, 4, 0.55), 0.0, 1.0)
    cloud *= np.clip(d[:, 2] * 8.0, 0.0, 1.0)
    return out * (1 - cloud[:, None]) + 0.95 * cloud[:, None]
