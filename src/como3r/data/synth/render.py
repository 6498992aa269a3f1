"""Exact CPU ray casting of a synthetic scene: colour, z-depth and appearance keys.

One pinhole camera ray per pixel centre (OpenCV: x right, y down, z forward; pixel
centres at integer coordinates). Ray directions have camera-frame z = 1, so the ray
parameter of a hit is its z-depth. Primitives are culled per frame by projecting their
bounding boxes: only the pixels of a primitive's screen rectangle are tested against it,
which keeps a 320x240 frame of a few hundred primitives at tens of milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from como3r.data.synth.primitives import NEAR, Ground, Primitive
from como3r.data.synth.textures import MaterialTable, TextureBank, shade, sky_colour

_SKY = -1
_GROUND = -2
#: Pixels rendered at once (see Renderer.render).
_BAND_PIXELS = 8192


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view."""
        fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def matrix(self) -> np.ndarray:
        """``(3, 3)`` calibration matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def rays(self) -> np.ndarray:
        """``(H, W, 3)`` camera-frame ray directions ``K^-1 (u, v, 1)`` (z = 1)."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)


@dataclass(frozen=True)
class Scene:
    """Everything the renderer needs: solids, the ground and the texture table."""

    primitives: tuple[Primitive, ...]
    ground: Ground
    materials: MaterialTable


@dataclass(frozen=True)
class Frame:
    """One rendered view.

    Attributes:
        rgb: ``(H, W, 3)`` uint8.
        depth: ``(H, W)`` float32 z-depth in metres, 0 for sky.
        surface: ``(H, W, 3)`` float32 appearance keys (texture id, s, t); id -1 for sky.
    """

    rgb: np.ndarray
    depth: np.ndarray
    surface: np.ndarray


class Renderer:
    """Renders a :class:`Scene` from camera poses with fixed intrinsics."""

    def __init__(self, scene: Scene, intrinsics: Intrinsics) -> None:
        self.scene = scene
        self.K = intrinsics
        self._rays = intrinsics.rays()
        self._textures = TextureBank(scene.materials)
        if scene.primitives:
            self._corners = np.stack([p.corners() for p in scene.primitives])
        else:
            self._corners = np.zeros((0, 8, 3))

    def _screen_rects(self, R_WC: np.ndarray, t_WC: np.ndarray) -> list[tuple[int, ...]]:
        """Per visible primitive ``(index, v0, v1, u0, u1)``: the pixel rectangle that
        contains its projected bounding box (the whole image if the box straddles the
        camera plane)."""
        K, W, H = self.K, self.K.width, self.K.height
        cam = (self._corners - t_WC) @ R_WC  # (P, 8, 3) camera-frame corners
        z = cam[..., 2]
        in_front = z > NEAR
        rects = []
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K.fx * cam[..., 0] / z + K.cx
            v = K.fy * cam[..., 1] / z + K.cy
        for k in np.nonzero(in_front.any(axis=1))[0]:
            if not in_front[k].all():
                rects.append((int(k), 0, H, 0, W))
                continue
            u0 = max(0, math.floor(u[k].min()))
            u1 = min(W, math.ceil(u[k].max()) + 1)
            v0 = max(0, math.floor(v[k].min()))
            v1 = min(H, math.ceil(v[k].max()) + 1)
            if u0 < u1 and v0 < v1:
                rects.append((int(k), v0, v1, u0, u1))
        return rects

    def render(self, R_WC: np.ndarray, t_WC: np.ndarray) -> Frame:
        """Render the view of camera ``T_WC = (R_WC, t_WC)``.

        Args:
            R_WC: ``(3, 3)`` camera-to-world rotation (columns: camera x, y, z in world).
            t_WC: ``(3,)`` camera centre in the world frame.
        """
        H, W = self.K.height, self.K.width
        o = np.asarray(t_WC, dtype=np.float64)
        # World ray directions as three contiguous (H, W) planes.
        dirs = np.ascontiguousarray(
            np.einsum("ij,hwj->ihw", np.asarray(R_WC, dtype=np.float64), self._rays)
        )
        rects = self._screen_rects(R_WC, o)
        rgb = np.empty((H, W, 3), dtype=np.uint8)
        depth = np.empty((H, W), dtype=np.float32)
        surface = np.empty((H, W, 3), dtype=np.float32)
        # Bands of rows small enough that every temporary stays in cache (and below the
        # allocator's mmap threshold, whose page faults would dominate otherwise).
        band = max(1, _BAND_PIXELS // W)
        for v0 in range(0, H, band):
            v1 = min(H, v0 + band)
            in_band = [
                (k, max(a, v0) - v0, min(b, v1) - v0, u0, u1)
                for k, a, b, u0, u1 in rects
                if a < v1 and b > v0
            ]
            self._render_band(o, dirs[:, v0:v1], in_band, rgb[v0:v1], depth[v0:v1], surface[v0:v1])
        return Frame(rgb=rgb, depth=depth, surface=surface)

    def _render_band(
        self,
        o: np.ndarray,
        dirs: np.ndarray,
        rects: list[tuple[int, ...]],
        rgb: np.ndarray,
        depth_out: np.ndarray,
        surface: np.ndarray,
    ) -> None:
        """Render rows of the image into the output views ``rgb``, ``depth_out``,
        ``surface``; ``dirs`` ``(3, h, W)`` and ``rects`` are relative to the band."""
        depth, owner = self._cast(o, dirs, rects)
        # Group the band's pixels by owner: every surface then evaluates one contiguous run.
        flat_owner = owner.ravel()
        order = np.argsort(flat_owner, kind="stable")
        runs = np.flatnonzero(np.diff(flat_owner[order])) + 1
        lam = depth.ravel()[order]
        rays = tuple(dirs[i].ravel()[order] for i in range(3))
        lam = np.where(np.isfinite(lam), lam, 0.0)
        points = tuple(o[i] + lam * rays[i] for i in range(3))
        ids = np.full(order.size, _SKY, dtype=np.int64)
        s, t, nz = np.zeros((3, order.size))
        for a, b in zip(np.concatenate([[0], runs]), np.concatenate([runs, [order.size]])):
            k = flat_owner[order[a]]
            if k == _SKY:
                continue
            surface_fn = (
                self.scene.ground.surface if k == _GROUND else self.scene.primitives[k].surface
            )
            ids[a:b], s[a:b], t[a:b], nz[a:b] = surface_fn(tuple(p[a:b] for p in points))

        solid = ids >= 0
        colour = np.empty((order.size, 3))
        colour[solid] = shade(self._textures.albedo(ids[solid], s[solid], t[solid]), nz[solid])
        colour[~solid] = sky_colour(np.stack([r[~solid] for r in rays], axis=1))
        h, w = depth.shape
        unsorted = np.empty((order.size, 7))
        unsorted[order] = np.column_stack(
            [
                np.round(np.clip(colour, 0.0, 1.0) * 255.0),
                lam,
                ids,
                np.where(solid, s, 0.0),
                np.where(solid, t, 0.0),
            ]
        )
        rgb[...] = unsorted[:, :3].reshape(h, w, 3)
        depth_out[...] = unsorted[:, 3].reshape(h, w)
        surface[...] = unsorted[:, 4:].reshape(h, w, 3)

    def _cast(
        self, o: np.ndarray, dirs: np.ndarray, rects: list[tuple[int, ...]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of every ray: z-depth ``(h, W)`` (``inf`` for sky) and its owner
        ``(h, W)`` int32 (primitive index, ``_GROUND`` or ``_SKY``)."""
        depth = self.scene.ground.intersect(o, tuple(dirs))
        owner = np.where(np.isfinite(depth), _GROUND, _SKY).astype(np.int32)
        for k, v0, v1, u0, u1 in rects:
            lam = self.scene.primitives[k].intersect(o, tuple(dirs[:, v0:v1, u0:u1]))
            depth_rect = depth[v0:v1, u0:u1]
            closer = lam < depth_rect
            depth_rect[closer] = lam[closer]
            owner[v0:v1, u0:u1][closer] = k
        return depth, owner
