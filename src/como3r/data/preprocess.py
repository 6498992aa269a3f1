"""MASt3R image pre-processing (MAST3R_SPEC.md §2.1) and the matching per-pixel maps.

An image of ``W1 x H1`` pixels is

1. resized so its long side is ``long_side`` (512 for MASt3R), each side
   ``round(x * long_side / max(W1, H1))`` with Python's ``round``; PIL ``LANCZOS`` when
   shrinking (``max(W1, H1) > long_side``), ``BICUBIC`` otherwise;
2. centre-cropped to multiples of 16: ``cx = W // 2``, ``halfw = ((2 * cx) // 16) * 8``
   (same for y); a square resized image becomes 4:3 (``halfh = 3 * halfw / 4``) unless
   ``square_ok``;
3. normalised to ``2 * v / 255 - 1`` in [-1, 1] for the network.

Intrinsics follow the image (C-Sec. B.4: "the per-sequence intrinsic matrix is rescaled to
the same resolution and the principal point is recentred"). Depth and appearance-key maps
follow it with nearest-neighbour sampling so every value stays a value of the input map.

Pixel convention: integer pixel coordinates are pixel centres (OpenCV / TUM ``K``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from como3r.data.agent_input import Frame
from como3r.errors import InputError
from como3r.prior.base import View
from como3r.prior.ground_truth import GroundTruth

PATCH = 16
"""MASt3R patch size: network input sides must be multiples of it (MAST3R_SPEC.md §2.2)."""

KType = TypeVar("KType", np.ndarray, Tensor)


@dataclass(frozen=True)
class ImageTransform:
    """How :func:`resize_crop` maps an original image to the network input.

    Attributes:
        original: ``(W1, H1)`` of the input image.
        resized: ``(W, H)`` after the resize, before the crop.
        output: ``(W_crop, H_crop)`` of the network input, multiples of 16.
        scale_w: ``W1 / W``.
        scale_h: ``H1 / H``.
        half_crop_w: ``(W - W_crop) / 2`` (MAST3R_SPEC.md §2.1 step 7).
        half_crop_h: ``(H - H_crop) / 2``.
        crop_left: first resized column kept; equals ``half_crop_w`` rounded down when
            ``W - W_crop`` is odd, so it is what :meth:`intrinsics` uses.
        crop_top: first resized row kept.
    """

    original: tuple[int, int]
    resized: tuple[int, int]
    output: tuple[int, int]
    scale_w: float
    scale_h: float
    half_crop_w: float
    half_crop_h: float
    crop_left: int
    crop_top: int

    def intrinsics(self, K: KType) -> KType:
        """Intrinsics of the network input from those of the original image.

        Args:
            K: ``(..., 3, 3)`` pinhole intrinsics in original pixels (numpy or torch).

        Returns:
            ``(..., 3, 3)`` intrinsics in output pixels, same type and dtype as ``K``:
            focal lengths divided by the scale, principal point mapped through the resize
            (pixel centres: ``u' = (u + 0.5) / scale - 0.5``) and shifted by the crop.
        """
        A = np.array(
            [
                [1.0 / self.scale_w, 0.0, 0.5 / self.scale_w - 0.5 - self.crop_left],
                [0.0, 1.0 / self.scale_h, 0.5 / self.scale_h - 0.5 - self.crop_top],
                [0.0, 0.0, 1.0],
            ]
        )
        if isinstance(K, Tensor):
            return torch.as_tensor(A, dtype=K.dtype, device=K.device) @ K
        return (A @ K).astype(K.dtype, copy=False)

    def apply_nearest(self, values: np.ndarray) -> np.ndarray:
        """Resize and crop a per-pixel map aligned with the original image.

        Nearest-neighbour sampling: output pixel ``x`` takes input column
        ``floor((x + crop_left + 0.5) * scale_w)``, so depth zeros and appearance keys stay
        exact values of the input.

        Args:
            values: ``(H1, W1)`` or ``(H1, W1, C)`` map, any dtype.

        Returns:
            ``(H_crop, W_crop[, C])`` map of the same dtype.
        """
        width, height = self.original
        if values.shape[:2] != (height, width):
            raise ValueError(f"map of shape {values.shape} does not match a {width}x{height} image")
        cols = _nearest_source(self.output[0], self.crop_left, self.scale_w, width)
        rows = _nearest_source(self.output[1], self.crop_top, self.scale_h, height)
        return values[rows[:, None], cols[None, :]]

    def apply_geometry(
        self, depth: np.ndarray, surface: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Resize and crop a depth map (and its appearance keys) aligned with the image.

        Shrinking samples the nearest input pixel (:meth:`apply_nearest`). Enlarging
        interpolates where the four input pixels around an output pixel lie on one smooth
        surface (all with depth, depths within ``exp(0.1)`` of each other and, with keys,
        one texture id): inverse depth bilinearly (exact on planes) and the keys' (s, t)
        bilinearly; elsewhere it samples the nearest pixel. Nearest sampling alone repeats
        each input value over a block of output pixels, a staircase no camera sees.

        Args:
            depth: ``(H1, W1)`` z-depth, 0 where unknown.
            surface: ``(H1, W1, 3)`` appearance keys (id, s, t), or None.

        Returns:
            ``(H_crop, W_crop)`` depth and ``(H_crop, W_crop, 3)`` keys (or None), float32.
        """
        nearest_depth = self.apply_nearest(depth).astype(np.float32)
        nearest_surface = None if surface is None else self.apply_nearest(surface)
        if self.scale_w >= 1.0 and self.scale_h >= 1.0:
            return nearest_depth, nearest_surface
        width, height = self.original
        c0, c1, a = _linear_source(self.output[0], self.crop_left, self.scale_w, width)
        r0, r1, b = _linear_source(self.output[1], self.crop_top, self.scale_h, height)
        corners = [
            (r0[:, None], c0[None]),
            (r0[:, None], c1[None]),
            (r1[:, None], c0[None]),
            (r1[:, None], c1[None]),
        ]
        weights = [
            (1 - b)[:, None] * (1 - a)[None],
            (1 - b)[:, None] * a[None],
            b[:, None] * (1 - a)[None],
            b[:, None] * a[None],
        ]
        z = np.stack([depth[rc] for rc in corners]).astype(np.float64)
        smooth = (z > 0).all(0) & (z.max(0) < math.exp(0.1) * z.min(0))
        if surface is not None:
            ids = np.stack([surface[rc][..., 0] for rc in corners])
            smooth &= (ids == ids[0]).all(0) & (ids[0] >= 0)
        inverse = sum(w / np.where(z[k] > 0, z[k], 1.0) for k, w in enumerate(weights))
        out_depth = np.where(smooth, 1.0 / inverse, nearest_depth).astype(np.float32)
        if surface is None:
            return out_depth, None
        keys = sum(
            w[..., None] * surface[rc][..., 1:].astype(np.float64)
            for rc, w in zip(corners, weights)
        )
        out_surface = nearest_surface.astype(np.float32, copy=True)
        out_surface[..., 1:] = np.where(smooth[..., None], keys, out_surface[..., 1:])
        return out_depth, out_surface

    @staticmethod
    def to_network(image: np.ndarray) -> Tensor:
        """``(H, W, 3)`` uint8 RGB -> ``(3, H, W)`` float32 ``2 * v / 255 - 1`` in [-1, 1].

        Computed as ``(v / 255 - 0.5) / 0.5``, the order of ``ToTensor`` + ``Normalize``.
        """
        pixels = torch.from_numpy(np.array(image, dtype=np.uint8)).permute(2, 0, 1)
        return (pixels.to(torch.float32) / 255.0 - 0.5) / 0.5


def compute_transform(
    width: int, height: int, long_side: int = 512, square_ok: bool = False
) -> ImageTransform:
    """The :class:`ImageTransform` of a ``width x height`` image (MAST3R_SPEC.md §2.1).

    Raises:
        InputError: the image is so elongated that a side would be cropped to nothing.
    """
    if long_side < PATCH:
        raise ValueError(f"long_side must be at least {PATCH}, got {long_side}")
    longest = max(width, height)
    resized_w = int(round(width * long_side / longest))
    resized_h = int(round(height * long_side / longest))
    cx, cy = resized_w // 2, resized_h // 2
    half_w = ((2 * cx) // PATCH) * (PATCH // 2)
    half_h = ((2 * cy) // PATCH) * (PATCH // 2)
    if resized_w == resized_h and not square_ok:
        # The spec's 4:3 rule (3 * halfw / 4) is a multiple of 8 for long_side = 512; rounding
        # down to a multiple of 8 keeps the height a multiple of 16 for every other long side.
        half_h = (3 * half_w // 4) // (PATCH // 2) * (PATCH // 2)
    if half_w == 0 or half_h == 0:
        raise InputError(
            f"a {width}x{height} image resized to {resized_w}x{resized_h} leaves no "
            f"{PATCH}-pixel patch after the centre crop"
        )
    return ImageTransform(
        original=(width, height),
        resized=(resized_w, resized_h),
        output=(2 * half_w, 2 * half_h),
        scale_w=width / resized_w,
        scale_h=height / resized_h,
        half_crop_w=(resized_w - 2 * half_w) / 2,
        half_crop_h=(resized_h - 2 * half_h) / 2,
        crop_left=cx - half_w,
        crop_top=cy - half_h,
    )


def resize_crop(
    image: np.ndarray, long_side: int = 512, square_ok: bool = False
) -> tuple[np.ndarray, ImageTransform]:
    """Resize and centre-crop an image for MASt3R (MAST3R_SPEC.md §2.1 steps 2-3).

    Args:
        image: ``(H1, W1, 3)`` uint8 RGB.
        long_side: target long side (512 for MASt3R; smaller for fast tests).
        square_ok: keep square images square instead of cropping them to 4:3.

    Returns:
        ``(H_crop, W_crop, 3)`` uint8 RGB and the transform that produced it.
    """
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    transform = compute_transform(image.shape[1], image.shape[0], long_side, square_ok)
    resample = (
        Image.Resampling.LANCZOS
        if max(transform.original) > long_side
        else Image.Resampling.BICUBIC
    )
    resized = Image.fromarray(image).resize(transform.resized, resample)
    left, top = transform.crop_left, transform.crop_top
    width, height = transform.output
    cropped = resized.crop((left, top, left + width, top + height))
    return np.array(cropped), transform


def upsampling(image_size: tuple[int, int], long_side: int) -> float:
    """Network pixels per input pixel of a ``(W, H)`` image resized to ``long_side``
    (> 1: the image is enlarged, so one of its pixels spans several network pixels)."""
    return long_side / max(image_size)


def make_view(
    frame: Frame,
    agent: int,
    long_side: int = 512,
    calib: tuple[float, float, float, float] | None = None,
) -> View:
    """The prior's :class:`View` of a frame at network resolution.

    Args:
        frame: decoded frame (original resolution).
        agent: agent id.
        long_side: long side of the resize (512 for MASt3R).
        calib: ``(fx, fy, cx, cy)`` in original pixels in a calibrated run, else None.

    Returns:
        View with ``image (3, H, W)`` in [-1, 1] and ``K (3, 3)`` float32 when ``calib`` is
        given; never ground truth (:func:`frame_ground_truth` is the simulated prior's).
    """
    image, transform = resize_crop(frame.image, long_side)
    return View(
        image=ImageTransform.to_network(image),
        agent=agent,
        index=frame.index,
        K=None if calib is None else _network_intrinsics(transform, calib),
    )


def frame_ground_truth(
    frame: Frame,
    long_side: int = 512,
    calib: tuple[float, float, float, float] | None = None,
) -> GroundTruth:
    """A frame's ground truth at the resolution :func:`make_view` gives its image.

    Args:
        frame: decoded frame (original resolution).
        long_side: long side of the resize.
        calib: the agent's ``(fx, fy, cx, cy)`` in original pixels, or None.

    Returns:
        ``depth (H, W)`` and ``surface (H, W, 3)`` float32 where the frame has them (resized
        by :meth:`ImageTransform.apply_geometry`), ``K`` from ``calib`` and the frame's
        ground-truth pose.
    """
    height, width = frame.image.shape[:2]
    transform = compute_transform(width, height, long_side)
    depth = surface = None
    if frame.depth is not None:
        depth_map, surface_map = transform.apply_geometry(frame.depth, frame.surface)
        depth = torch.from_numpy(np.ascontiguousarray(depth_map))
        if surface_map is not None:
            surface = torch.from_numpy(np.ascontiguousarray(surface_map))
    elif frame.surface is not None:
        surface = torch.from_numpy(np.ascontiguousarray(transform.apply_nearest(frame.surface)))
    K = None if calib is None else _network_intrinsics(transform, calib)
    return GroundTruth(depth=depth, K=K, surface=surface, T_WC=frame.T_WC_gt)


def _network_intrinsics(
    transform: ImageTransform, calib: tuple[float, float, float, float]
) -> Tensor:
    """``(3, 3)`` float32 intrinsics of the transformed image from ``(fx, fy, cx, cy)``."""
    fx, fy, cx, cy = calib
    K_original = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return torch.from_numpy(transform.intrinsics(K_original)).to(torch.float32)


def _linear_source(
    size: int, offset: int, scale: float, limit: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each of ``size`` output pixels: the two input indices around its centre and the
    weight of the second (pixel-centre convention, clamped at the border)."""
    position = np.clip((np.arange(size) + offset + 0.5) * scale - 0.5, 0.0, limit - 1.0)
    first = np.minimum(np.floor(position).astype(np.int64), max(limit - 2, 0))
    second = np.minimum(first + 1, limit - 1)
    return first, second, position - first


def _nearest_source(size: int, offset: int, scale: float, limit: int) -> np.ndarray:
    """Input index sampled by each of ``size`` output pixels (pixel-centre convention)."""
    centres = (np.arange(size) + offset + 0.5) * scale
    return np.minimum(np.floor(centres).astype(np.int64), limit - 1)
