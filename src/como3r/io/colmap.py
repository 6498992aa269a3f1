"""COLMAP text models: ``cameras.txt``, ``images.txt``, ``points3D.txt``.

The format of COLMAP's documentation ("Output format", text): one ``PINHOLE`` camera line
``CAMERA_ID PINHOLE WIDTH HEIGHT fx fy cx cy``; two lines per image, ``IMAGE_ID QW QX QY QZ
TX TY TZ CAMERA_ID NAME`` (the world-to-camera rotation as a unit quaternion and the
world-to-camera translation, ``x_C = R x_W + t``) and its 2-D points ``X Y POINT3D_ID ...``;
one line per 3-D point ``POINT3D_ID X Y Z R G B ERROR IMAGE_ID POINT2D_IDX ...``. Ids start at
1. COLMAP puts pixel centres at half-integer coordinates (the image's top-left corner is
``(0, 0)``); como3r puts them at integers (:mod:`como3r.geometry.camera`): the writer takes
como3r's principal points and pixels and adds 0.5.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Pinhole:
    """Intrinsics of a ``width x height`` image, pixel centres at integers (como3r's)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def project(self, x_C: np.ndarray) -> np.ndarray:
        """``(N, 2)`` pixels ``(u, v)`` of camera-frame points ``x_C (N, 3)`` (z > 0)."""
        return np.stack(
            [self.fx * x_C[:, 0] / x_C[:, 2] + self.cx, self.fy * x_C[:, 1] / x_C[:, 2] + self.cy],
            axis=1,
        )


@dataclass(frozen=True)
class ColmapCamera:
    """A ``PINHOLE`` camera: its id and intrinsics."""

    camera_id: int
    pinhole: Pinhole


@dataclass(frozen=True)
class ColmapImage:
    """One registered image.

    Attributes:
        image_id: >= 1.
        q_CW: ``(4,)`` world-to-camera rotation, unit quaternion ``(x, y, z, w)``.
        t_CW: ``(3,)`` world-to-camera translation.
        camera_id: its :class:`ColmapCamera`.
        name: file name relative to the model's image folder.
        points2D: ``(P, 2)`` pixel coordinates (como3r's convention) of its observations.
        point3D_ids: ``(P,)`` the observed 3-D point of each (-1: none).
    """

    image_id: int
    q_CW: np.ndarray
    t_CW: np.ndarray
    camera_id: int
    name: str
    points2D: np.ndarray
    point3D_ids: np.ndarray


def write_colmap_text(
    folder: str | Path,
    cameras: Sequence[ColmapCamera],
    images: Sequence[ColmapImage],
    xyz: np.ndarray,
    rgb: np.ndarray,
) -> None:
    """Write ``cameras.txt``, ``images.txt`` and ``points3D.txt`` into ``folder``.

    3-D point ``i`` gets id ``i + 1``; its track is every image observation whose
    ``point3D_ids`` entry is ``i + 1``. ``ERROR`` is written as 0: the observations are the
    points' projections.

    Args:
        folder: an existing folder.
        cameras: the cameras.
        images: the images, their observations referring to point ids ``1 .. N``.
        xyz: ``(N, 3)`` world points.
        rgb: ``(N, 3)`` uint8 colours.
    """
    folder = Path(folder)
    with open(folder / "cameras.txt", "w") as f:
        f.write(
            "# Camera list with one line of data per camera:\n"
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
            f"# Number of cameras: {len(cameras)}\n"
        )
        for c in cameras:
            pin = c.pinhole
            f.write(
                f"{c.camera_id} PINHOLE {pin.width} {pin.height} {pin.fx!r} {pin.fy!r} "
                f"{pin.cx + 0.5!r} {pin.cy + 0.5!r}\n"
            )
    observations = sum(int((im.point3D_ids > 0).sum()) for im in images)
    with open(folder / "images.txt", "w") as f:
        f.write(
            "# Image list with two lines of data per image:\n"
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
            "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
            f"# Number of images: {len(images)}, mean observations per image: "
            f"{observations / max(len(images), 1):.6g}\n"
        )
        for im in images:
            x, y, z, w = (float(v) + 0.0 for v in im.q_CW)  # + 0.0: no "-0.0"
            t = " ".join(repr(float(v) + 0.0) for v in im.t_CW)
            f.write(f"{im.image_id} {w!r} {x!r} {y!r} {z!r} {t} {im.camera_id} {im.name}\n")
            f.write(
                " ".join(
                    f"{u + 0.5:.4f} {v + 0.5:.4f} {int(p)}"
                    for (u, v), p in zip(im.points2D, im.point3D_ids)
                )
                + "\n"
            )
    tracks = _tracks(images, len(xyz))
    with open(folder / "points3D.txt", "w") as f:
        f.write(
            "# 3D point list with one line of data per point:\n"
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
            f"# Number of points: {len(xyz)}, mean track length: "
            f"{observations / max(len(xyz), 1):.6g}\n"
        )
        for i, ((x, y, z), (r, g, b), track) in enumerate(zip(xyz, rgb, tracks)):
            f.write(f"{i + 1} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} 0 {track}\n")


def _tracks(images: Sequence[ColmapImage], count: int) -> list[str]:
    """Each 3-D point's track ``IMAGE_ID POINT2D_IDX ...`` as text, in image order."""
    tracks: list[list[str]] = [[] for _ in range(count)]
    for im in images:
        for k, p in enumerate(im.point3D_ids.tolist()):
            if p > 0:
                tracks[p - 1].append(f"{im.image_id} {k}")
    return [" ".join(t) for t in tracks]
