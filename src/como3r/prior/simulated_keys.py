"""Appearance keys and the fixed random-feature maps of the simulated prior.

A pixel's *appearance key* is what a learned prior recognises it by: the id of the texture it
shows and where on that texture it lies (manual: docs/api/index.md). Synthetic scenes store
keys as ``surface`` maps ``(texture id, s, t)`` with ``s, t`` in metres; two façades that
share a texture id and its parameterisation are indistinguishable, exactly like repeated
structure for a learned model. Without a surface map the key of a pixel is its world point
(ground-truth pose and depth), which never aliases.

Keys are stored as an integer id ``(H, W)`` (``-1``: no key) and metric coordinates
``(H, W, 3)``: ``(s, t, 0)`` for surface keys, ``(x, y, z)`` world metres for world keys,
whose id is :data:`WORLD_KEY_ID`.

Two views are matched the way a learned matcher would pair them: pixels whose keys fall in
the same key cell (:func:`match_key_cells`), then moved to the exact key with the local key
Jacobians of the surface (:func:`key_jacobians`).

Descriptors come from a fixed random Fourier-feature map of the key: a per-texture random
embedding plus cosines ``cos(omega . k + phi)`` at log-uniformly spread wavelengths. Each
cosine is attenuated by ``exp(-|omega|^2 sigma^2 / 2)``, the exact average of the cosine over
a Gaussian pixel footprint of standard deviation ``sigma``: a pixel cannot resolve texture
finer than the surface patch it integrates, so the descriptor is locally discriminative at
the scale of a pixel, in every view and at every resolution. Texture coarser than the image
is invisible to a descriptor made from it, so each cosine is also attenuated by
``exp(-(lambda / (coarse_footprints * footprint))^2 / 2)``, and the wavelengths repeat in
tiles ``ratio^k`` times the base band (``k`` in ``-tiles..tiles``): every descriptor sees
the same band *relative to its own footprint*. A scene scaled as a whole (geometry and
texture coordinates, so its images are unchanged, as ``como3r synth --scale`` makes them)
therefore gets descriptors as discriminative as at scale 1 (the tiles' random draws
differ, so not the same values), as a network looking at the same images would. With one
band fixed in metres, the 20x aerial family's pixels (about 40 cm) saw no texture coarser
than 25 pixels: the descriptor search moved 45 % of its matches to look-alikes up to 20
pixels away, and 6 of its 12 frames were lost (tests/prior/test_simulated.py).
"""

from __future__ import annotations

import hashlib
import math
import struct
from typing import NamedTuple

import torch
from torch import Tensor

from como3r.geometry.lie import sim3_act

WORLD_KEY_ID = 1 << 40
"""Texture id of keys made of world coordinates; no surface map uses it."""

_HASH_MULTIPLIER = 0x9E3779B97F4A7C15 - (1 << 64)
"""Odd 64-bit multiplier (golden ratio) as a signed int64, for cell hashing."""


def stable_seed(*values: int | str) -> int:
    """A 63-bit seed derived from ``values`` (stable across processes and platforms)."""
    text = "/".join(str(v) for v in values).encode()
    digest = hashlib.blake2b(text, digest_size=8).digest()
    return struct.unpack("<Q", digest)[0] & ((1 << 63) - 1)


def generator(*values: int | str) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded by :func:`stable_seed` of ``values``."""
    return torch.Generator().manual_seed(stable_seed(*values))


def reproducible_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for ``a`` ``(..., M, K)`` and a small ``b`` ``(..., K, N)`` (batch dimensions
    broadcast), bit-identical on every call.

    The simulated prior must give the same prediction for the same pair every time
    (``tests/prior``), but a BLAS product's rounding can depend on its operands' memory
    alignment, so the same decode twice differed by an ulp about once in ten runs. An
    elementwise product summed over ``K`` has one fixed summation order.
    """
    return (a[..., :, None] * b).sum(-2)


def keys_from_surface(surface: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Keys of a surface map.

    Args:
        surface: ``(H, W, 3)`` float (texture id, s, t); id < 0 for sky.
        valid: ``(H, W)`` bool, pixels with depth.

    Returns:
        ids ``(H, W)`` int64 (``-1`` where id < 0 or not ``valid``) and coordinates
        ``(H, W, 3)`` float32 ``(s, t, 0)``.
    """
    ids = torch.round(surface[..., 0]).to(torch.int64)
    ids = torch.where(valid & (ids >= 0), ids, torch.full_like(ids, -1))
    coords = torch.zeros(surface.shape, dtype=torch.float32, device=surface.device)
    coords[..., :2] = surface[..., 1:3].to(torch.float32)
    return ids, coords


def keys_from_world(points_C: Tensor, T_WC: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Keys made of world coordinates, which cannot alias.

    Args:
        points_C: ``(H, W, 3)`` camera-frame points in metres.
        T_WC: ``(8,)`` ground-truth camera pose.
        valid: ``(H, W)`` bool.

    Returns:
        ids ``(H, W)`` int64 (:data:`WORLD_KEY_ID` or ``-1``) and world points ``(H, W, 3)``
        float32 (millimetre resolution up to ~10 km from the world origin).
    """
    world = sim3_act(T_WC.to(torch.float64), points_C.to(torch.float64)).to(torch.float32)
    ids = torch.where(valid, WORLD_KEY_ID, -1).to(torch.int64)
    return ids, torch.where(valid[..., None], world, torch.zeros_like(world))


def _neighbour_differences(
    ids: Tensor, coords: Tensor, values: Tensor | None, pixels: Tensor
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Finite differences of the keys (and ``values``) at ``pixels`` along u and v.

    Along each axis, of the two neighbours sharing the pixel's (valid) id, the one with the
    smaller key step is used, which ignores a jump across an occlusion boundary on one side.

    Args:
        ids: ``(H, W)`` int64 key ids.
        coords: ``(H, W, 3)`` key coordinates.
        values: ``(H, W, C)`` or None.
        pixels: ``(M,)`` int64 flat pixel indices.

    Returns:
        key change per pixel step ``(M, 2, 3)`` along (u, v), value change ``(M, 2, C)``
        (or None) and the key step lengths ``(M, 2)``, ``inf`` where no neighbour shares
        the id.
    """
    H, W = ids.shape
    flat_ids, flat_coords = ids.reshape(-1), coords.reshape(-1, 3)
    u, v = pixels % W, pixels // W
    # neighbours (u + 1, u - 1, v + 1, v - 1) and the sign that makes a difference "per +1"
    inside = torch.stack([u < W - 1, u > 0, v < H - 1, v > 0], dim=-1)
    offsets = torch.tensor([1, -1, W, -W], device=pixels.device)
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0], device=coords.device)[:, None]
    other = torch.where(inside, pixels[:, None] + offsets, pixels[:, None])
    same = inside & (flat_ids[other] == flat_ids[pixels, None]) & (flat_ids[pixels, None] >= 0)
    dk = sign * (flat_coords[other] - flat_coords[pixels, None])
    step = torch.where(same, dk.norm(dim=-1), torch.full_like(dk[..., 0], math.inf))
    # per axis, the side with the smaller step (the next neighbour on ties)
    side = step.view(-1, 2, 2).argmin(dim=-1, keepdim=True)
    best_step = step.view(-1, 2, 2).gather(2, side)[..., 0]
    best_dk = dk.view(-1, 2, 2, 3).gather(2, side[..., None].expand(-1, -1, -1, 3))[:, :, 0]
    if values is None:
        return best_dk, None, best_step
    flat_values = values.reshape(H * W, -1)
    dv = sign * (flat_values[other] - flat_values[pixels, None])
    channels = flat_values.shape[1]
    best_dv = dv.view(-1, 2, 2, channels).gather(2, side[..., None].expand(-1, -1, -1, channels))[
        :, :, 0
    ]
    return best_dk, best_dv, best_step


def key_footprint(ids: Tensor, coords: Tensor, fallback: Tensor, max_ratio: float) -> Tensor:
    """Key-space size of each pixel (metres per pixel).

    Args:
        ids: ``(H, W)`` int64 key ids.
        coords: ``(H, W, 3)`` key coordinates, metres.
        fallback: ``(H, W)`` footprint where no neighbour shares the id (range / focal).
        max_ratio: the footprint is clamped to ``[fallback / max_ratio, fallback * max_ratio]``
            (slanted surfaces legitimately exceed range / focal, outliers should not).

    Returns:
        ``(H, W)`` root-mean-square of the key steps along u and v.
    """
    steps = _neighbour_differences(ids, coords, None, torch.arange(ids.numel(), device=ids.device))[
        2
    ]
    step_u, step_v = steps.unbind(-1)
    finite_u, finite_v = torch.isfinite(step_u), torch.isfinite(step_v)
    step_u, step_v = torch.where(finite_u, step_u, step_v), torch.where(finite_v, step_v, step_u)
    footprint = torch.sqrt(0.5 * (step_u.square() + step_v.square())).view(ids.shape)
    footprint = torch.where(torch.isfinite(footprint), footprint, fallback)
    return torch.minimum(torch.maximum(footprint, fallback / max_ratio), fallback * max_ratio)


def key_jacobians(
    ids: Tensor, coords: Tensor, points: Tensor, pixels: Tensor
) -> tuple[Tensor, Tensor]:
    """Local maps from key offsets to pixel offsets and to camera points at ``pixels``.

    From finite differences with the neighbours on the same surface, with ``dK``, ``dX``
    the ``(3, 2)`` key and point changes per pixel step along u and v:
    ``d (u, v) / d key = pinv(dK)`` and ``d point / d key = dX pinv(dK)``, so that
    ``point(k + dk) ~= point(k) + J dk`` on the surface (exact on planes).

    Args:
        ids: ``(H, W)`` int64 key ids.
        coords: ``(H, W, 3)`` key coordinates, metres.
        points: ``(H, W, 3)`` camera-frame points, metres.
        pixels: ``(M,)`` int64 flat pixel indices.

    Returns:
        ``(M, 2, 3)`` and ``(M, 3, 3)``, zero where undefined (no neighbour on the same
        surface along an axis, or degenerate key steps).
    """
    dk, dx, steps = _neighbour_differences(ids, coords, points, pixels)  # dK^T, dX^T
    dk_u, dk_v = dk.unbind(1)
    # pinv(dK) = (dK^T dK)^-1 dK^T with the 2x2 inverse in closed form.
    a, b, c = (dk_u * dk_u).sum(-1), (dk_u * dk_v).sum(-1), (dk_v * dk_v).sum(-1)
    det = a * c - b * b
    well_posed = torch.isfinite(steps).all(-1) & (det > 1e-4 * a * c)
    inverse = torch.stack([c, -b, -b, a], dim=-1).unflatten(-1, (2, 2))
    inverse = inverse / torch.where(well_posed, det, torch.ones_like(det))[:, None, None]
    key_to_pixel = torch.where(well_posed[:, None, None], inverse @ dk, torch.zeros_like(dk))
    return key_to_pixel, dx.transpose(1, 2) @ key_to_pixel


def cell_hash(ids: Tensor, coords: Tensor, cell: float) -> Tensor:
    """Hash of the key cell ``(id, floor(k / cell))`` of each key, int64.

    Keys in the same cell get equal hashes; different cells collide with probability about
    ``2^-64`` per pair (integer products wrap modulo ``2^64``).

    Args:
        ids: ``(N,)`` int64 key ids.
        coords: ``(N, 3)`` key coordinates in metres.
        cell: cell size in metres.
    """
    cells = torch.floor(coords.to(torch.float64) / cell).to(torch.int64)
    hashed = ids
    for axis in range(3):
        hashed = hashed * _HASH_MULTIPLIER + cells[:, axis]
    return hashed


class KeyMatches(NamedTuple):
    """Key-cell matches of an ordered pair of views (i, j), flat pixel indices."""

    counterpart_i: Tensor  # (H_i * W_i,) bool: the key cell of the pixel of i occurs in j
    counterpart_j: Tensor  # (H_j * W_j,) bool: the key cell of the pixel of j occurs in i
    pixels_i: Tensor  # (M,) int64 a random pixel of i in the cell of ...
    pixels_j: Tensor  # (M,) int64 ... this pixel of j, for every j pixel with a counterpart
    cell: float  # cell size, metres


def match_key_cells(
    ids_i: Tensor,
    coords_i: Tensor,
    ids_j: Tensor,
    coords_j: Tensor,
    cell: float,
    gen: torch.Generator,
) -> KeyMatches:
    """Pixels of two views whose keys fall in the same cell (what a learned matcher pairs).

    Args:
        ids_i, ids_j: ``(H, W)`` int64 key ids of the views, -1 where none.
        coords_i, coords_j: ``(H, W, 3)`` key coordinates, metres.
        cell: key cell size, metres.
        gen: draws which pixel of i a pixel of j is matched to when several share its cell.
    """
    flat_i, flat_j = ids_i.reshape(-1), ids_j.reshape(-1)
    keyed_i, keyed_j = torch.nonzero(flat_i >= 0)[:, 0], torch.nonzero(flat_j >= 0)[:, 0]
    hash_i = cell_hash(flat_i[keyed_i], coords_i.reshape(-1, 3)[keyed_i], cell)
    hash_j = cell_hash(flat_j[keyed_j], coords_j.reshape(-1, 3)[keyed_j], cell)
    # Searching sorted queries in sorted keys is several times faster (memory locality).
    sorted_i, order_i = torch.sort(hash_i)
    sorted_j, order_j = torch.sort(hash_j)
    first = torch.searchsorted(sorted_i, sorted_j)
    count = torch.searchsorted(sorted_i, sorted_j, right=True) - first
    found = torch.nonzero(count > 0)[:, 0]
    # Pixels of i in a cell some pixel of j hit: mark the hit runs [first, first + count)
    # of sorted_i with +1 / -1 and integrate.
    marks = torch.zeros(sorted_i.shape[0] + 1, dtype=torch.int64, device=sorted_i.device)
    ones = torch.ones_like(found)
    marks.index_add_(0, first[found], ones).index_add_(0, first[found] + count[found], -ones)
    counterpart_i = torch.zeros_like(flat_i, dtype=torch.bool)
    counterpart_i[keyed_i[order_i]] = torch.cumsum(marks, 0)[:-1] > 0
    counterpart_j = torch.zeros_like(flat_j, dtype=torch.bool)
    counterpart_j[keyed_j[order_j]] = count > 0
    offset = torch.rand(found.shape[0], generator=gen).to(count.device) * count[found]
    pick = first[found] + torch.minimum(offset.long(), count[found] - 1)
    return KeyMatches(
        counterpart_i, counterpart_j, keyed_i[order_i[pick]], keyed_j[order_j[found]], cell
    )


#: Keys a :class:`RandomFeatureMap` makes features of at a time (issue 41): each of its
#: temporaries is ``(N, dim)``, and a whole 512x384 view's (N = 196608, dim 24: 19 MB each)
#: made a simulated encoding's transient 200 MB, on each thread that re-encodes. A key's
#: features do not depend on its block but for the float32 rounding of its phases (a matrix
#: product's rounding depends on its row count): on 18 views of a 512x384 replay the
#: descriptors came out bit for bit those of a whole-view call.
FEATURE_ROWS = 16384


class RandomFeatureMap:
    """Fixed random Fourier-feature map of appearance keys (module docstring).

    ``features = id_weight * E[id] + sqrt(2 / dim) * sum_k a_k(footprint) * cos(omega_k . k +
    phi_k)`` with ``E[id]`` a random unit vector per texture id (none for world keys, which
    show no texture); feature i of tile k has the wavelength ``lambda_i ratio^k``, ``lambda_i``
    log-uniform in ``[wavelength_min, wavelength_max]`` and ``ratio = wavelength_max /
    wavelength_min``, a random direction (in-plane for surface keys, 3-D for world keys) and
    phase; ``a = exp(-|omega|^2 (blur * footprint)^2 / 2 - (lambda / (coarse_footprints *
    footprint))^2 / 2)``. Tile 0 is the base band, so at footprints where it alone is in band
    the map is the single-band map of its wavelengths.

    Args:
        dim: feature dimension.
        seed: seed of every random draw (features are a fixed function of the key).
        wavelength_min: finest wavelength of the base band, key units (metres).
        wavelength_max: coarsest wavelength of the base band, key units.
        id_weight: norm of the per-texture embedding relative to the cosine part.
        blur: standard deviation of the pixel footprint, in footprints.
        coarse_footprints: wavelength, in footprints, above which texture fades out (the
            extent of the image a feature is made from).
        name: distinguishes independent maps of the same prior.
        tiles: the tiles ``-tiles..tiles`` (``ratio^tiles`` must cover every footprint of
            interest: 4 tiles of the descriptors' 200x band span 13 decades either way).
    """

    def __init__(
        self,
        dim: int,
        seed: int,
        wavelength_min: float,
        wavelength_max: float,
        id_weight: float,
        blur: float,
        coarse_footprints: float,
        name: str,
        tiles: int = 4,
    ) -> None:
        self.dim = dim
        self.seed = seed
        self.id_weight = id_weight
        self.blur = blur
        self.coarse_footprints = coarse_footprints
        self.name = name
        self.ratio = wavelength_max / wavelength_min
        self._base_band = (wavelength_min, wavelength_max)
        gen = generator(seed, name, "frequencies")
        log_lambda = torch.empty(dim, dtype=torch.float64).uniform_(
            math.log(wavelength_min), math.log(wavelength_max), generator=gen
        )
        self._lambda = torch.exp(log_lambda)
        base_angle = torch.empty(dim, dtype=torch.float64).uniform_(
            0.0, 2.0 * math.pi, generator=gen
        )
        base_spatial = torch.randn(dim, 3, dtype=torch.float64, generator=gen)
        base_phase = torch.empty(dim, dtype=torch.float64).uniform_(
            0.0, 2.0 * math.pi, generator=gen
        )
        self._tiles = {
            k: self._tile(k, base_angle, base_spatial, base_phase) for k in range(-tiles, tiles + 1)
        }
        self._embeddings: dict[int, Tensor] = {}

    def _tile(
        self, k: int, angle: Tensor, spatial: Tensor, phase: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(omega_surface (dim, 3), omega_world (dim, 3), phase (dim,), lambda (dim,))`` of
        tile ``k``; tile 0 uses the base draws, the others their own."""
        if k != 0:
            gen = generator(self.seed, self.name, "tile", k)
            angle = torch.empty(self.dim, dtype=torch.float64).uniform_(
                0.0, 2.0 * math.pi, generator=gen
            )
            spatial = torch.randn(self.dim, 3, dtype=torch.float64, generator=gen)
            phase = torch.empty(self.dim, dtype=torch.float64).uniform_(
                0.0, 2.0 * math.pi, generator=gen
            )
        wavelength = self._lambda * self.ratio**k
        magnitude = 2.0 * math.pi / wavelength
        planar = torch.stack([torch.cos(angle), torch.sin(angle), torch.zeros_like(angle)], -1)
        spatial = spatial / spatial.norm(dim=-1, keepdim=True)
        return (
            (planar * magnitude[:, None]).float(),
            (spatial * magnitude[:, None]).float(),
            phase.float(),
            wavelength.float(),
        )

    def _band(self, k: int) -> tuple[float, float]:
        """Shortest and longest wavelength of tile ``k``."""
        return self._base_band[0] * self.ratio**k, self._base_band[1] * self.ratio**k

    def _in_band(self, k: int, footprint: Tensor) -> Tensor:
        """``(N,)`` bool: some wavelength of tile ``k`` keeps 1 % of its amplitude at the
        footprint, i.e. lies between ``1.04 blur`` and ``3.03 coarse_footprints`` footprints."""
        cut = math.sqrt(2.0 * math.log(100.0))
        shortest, longest = self._band(k)
        return (longest >= footprint * (2.0 * math.pi * self.blur / cut)) & (
            shortest <= footprint * (self.coarse_footprints * cut)
        )

    def embedding(self, key_id: int) -> Tensor:
        """``(dim,)`` float32 random unit vector of a texture id (cached)."""
        vector = self._embeddings.get(key_id)
        if vector is None:
            vector = torch.randn(self.dim, generator=generator(self.seed, self.name, key_id))
            vector = vector / vector.norm()
            self._embeddings[key_id] = vector
        return vector

    def embeddings(self, ids: Tensor) -> Tensor:
        """``(N, dim)`` float32 embeddings of ``(N,)`` int64 ids."""
        unique, inverse = torch.unique(ids, return_inverse=True)
        table = torch.stack([self.embedding(int(i)) for i in unique.tolist()])
        return table.to(ids.device)[inverse]

    def _tile_waves(
        self,
        tile: tuple[Tensor, Tensor, Tensor, Tensor],
        coords: Tensor,
        footprint: Tensor,
        is_world: Tensor | None,
    ) -> Tensor:
        """``(N, dim)`` attenuated cosines of one tile at ``(N, 3)`` keys (class docstring);
        ``is_world`` marks world keys (None: none)."""
        omega_surface, omega_world, phi, wavelength = (t.to(coords.device) for t in tile)
        # float32 phases: only wavelengths above ~1 footprint are evaluated, so a phase is
        # below 7 rad per footprint of the key's distance from the key origin (3e-3 rad of
        # rounding 2 km from it at 30 cm per pixel, far below the noise)
        phase = coords @ omega_surface.T
        if is_world is not None:
            phase = torch.where(is_world[:, None], coords @ omega_world.T, phase)
        # both frequency sets share the magnitudes, hence the attenuation
        blur_sq = (self.blur * footprint).square()[:, None]
        coarse = (self.coarse_footprints * footprint)[:, None]
        exponent = blur_sq * omega_surface.square().sum(-1) + (wavelength / coarse).square()
        return torch.exp(-0.5 * exponent) * torch.cos(phase + phi)

    def __call__(self, ids: Tensor, coords: Tensor, footprint: Tensor) -> Tensor:
        """Features of valid keys (not normalised), made :data:`FEATURE_ROWS` keys at a time.

        Args:
            ids: ``(N,)`` int64, all >= 0.
            coords: ``(N, 3)`` key coordinates, metres.
            footprint: ``(N,)`` key-space pixel size, metres.

        Returns:
            ``(N, dim)`` float32.
        """
        if ids.shape[0] <= FEATURE_ROWS:
            return self._features(ids, coords, footprint)
        out = torch.empty(ids.shape[0], self.dim, device=coords.device)
        for start in range(0, ids.shape[0], FEATURE_ROWS):
            rows = slice(start, start + FEATURE_ROWS)
            out[rows] = self._features(ids[rows], coords[rows], footprint[rows])
        return out

    def _features(self, ids: Tensor, coords: Tensor, footprint: Tensor) -> Tensor:
        """:meth:`__call__` of one block of keys."""
        device = coords.device
        coords, footprint = coords.to(torch.float32), footprint.to(torch.float32)
        is_world = ids == WORLD_KEY_ID
        any_world = bool(is_world.any())
        waves = torch.zeros(coords.shape[0], self.dim, device=device)
        for k, tile in self._tiles.items():
            rows = torch.nonzero(self._in_band(k, footprint))[:, 0]
            if rows.numel():
                waves.index_add_(
                    0,
                    rows,
                    self._tile_waves(
                        tile, coords[rows], footprint[rows], is_world[rows] if any_world else None
                    ),
                )
        waves *= math.sqrt(2.0 / self.dim)
        if bool(is_world.all()):
            return waves  # world keys carry no texture: a shared embedding would only blur
        embedding = self.embeddings(ids) * (~is_world)[:, None]
        return waves + self.id_weight * embedding
