"""Tiny dataset folders in the published layouts, written by the tests themselves."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from como3r.errors import InputError

WIDTH, HEIGHT = 32, 24
SEVEN_SCENES_REAL = Path("/work/shared/data/7scenes_redkitchen_tsdf50")


def pixels(i: int) -> np.ndarray:
    """A distinct deterministic ``(H, W, 3)`` uint8 image per index."""
    return np.random.default_rng(i).integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)


def depth_metres(i: int) -> np.ndarray:
    """``(H, W)`` float metres ``1 + 0.1 i + 0.01 u`` (u the column)."""
    u = np.arange(WIDTH)[None, :].repeat(HEIGHT, 0)
    return 1.0 + 0.1 * i + 0.01 * u


def rigid(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4, 4)`` random rigid camera-to-world matrices."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return T


def write_tum(root: Path, n: int = 5, *, depth: bool = True, groundtruth: bool = True,
              drop_depth: tuple[int, ...] = (), depth_offset: float = 0.004,
              extra_depth: bool = False) -> dict:
    """A TUM RGB-D sequence folder of ``n`` frames at 30 Hz (rgb from t = 1305031102.0).

    Depth images are stamped ``depth_offset`` after their rgb image; those of the frames in
    ``drop_depth`` are missing from ``depth.txt`` (the Kinect dropped them). ``extra_depth``
    adds a depth image 0.012 s before frame 1's (a worse candidate that must lose). Depth of
    frame i is :func:`depth_metres` at 5000 per metre with pixel (0, 0) invalid (0).
    Ground truth: 100 Hz from 0.05 s before the first frame to 0.05 s after the last.

    Returns:
        ``rgb`` stamps, ``gt`` (stamps, (M, 7) rows).
    """
    root.mkdir(parents=True)
    (root / "rgb").mkdir()
    stamps = 1305031102.0 + np.arange(n) / 30.0
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_test.bag'", "# timestamp filename"]
    for i, t in enumerate(stamps):
        Image.fromarray(pixels(i)).save(root / "rgb" / f"{t:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    if depth:
        (root / "depth").mkdir()
        entries = []
        for i, t in enumerate(stamps):
            if i in drop_depth:
                continue
            units = np.round(depth_metres(i) * 5000).astype(np.uint16)
            units[0, 0] = 0
            entries.append((t + depth_offset, units))
            if extra_depth and i == 1:
                entries.append((t - 0.012, np.full_like(units, 1234)))
        entries.sort(key=lambda e: e[0])
        lines = ["# depth maps", "# file: 'rgbd_dataset_test.bag'", "# timestamp filename"]
        for t, units in entries:
            Image.fromarray(units).save(root / "depth" / f"{t:.6f}.png")
            lines.append(f"{t:.6f} depth/{t:.6f}.png")
        (root / "depth.txt").write_text("\n".join(lines) + "\n")
    gt_stamps = np.arange(stamps[0] - 0.05, stamps[-1] + 0.05, 0.01)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(len(gt_stamps), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows = np.concatenate([rng.normal(size=(len(gt_stamps), 3)), q], axis=1)
    if groundtruth:
        lines = ["# ground truth trajectory", "# file: 'rgbd_dataset_test.bag'",
                 "# timestamp tx ty tz qx qy qz qw"]
        lines += [f"{t:.4f} " + " ".join(f"{v:.6f}" for v in row)
                  for t, row in zip(gt_stamps, rows)]
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return {"rgb": stamps, "gt": (gt_stamps, rows)}


def write_pose(path: Path, T: np.ndarray) -> None:
    """A 7-Scenes ``.pose.txt``: four rows of four numbers, tab-separated as released."""
    path.write_text("".join("\t".join(f"{v: .7e}" for v in row) + "\t\n" for row in T))


def write_7scenes(folder: Path, n: int = 4, *, start: int = 0, invalid: int = 65535,
                  colour: str = "png", depth: bool = True, poses: bool = True) -> np.ndarray:
    """A 7-Scenes frames folder ``frame-{start..start+n-1}``; returns the ``(n, 4, 4)``
    poses. Depth of frame i is :func:`depth_metres` in millimetres, with pixel (0, 0) 0 and
    pixel (0, 1) ``invalid``."""
    folder.mkdir(parents=True)
    T = rigid(n, seed=start)
    for k in range(n):
        stem = folder / f"frame-{start + k:06d}"
        Image.fromarray(pixels(k)).save(f"{stem}.color.{colour}")
        if depth:
            mm = np.round(depth_metres(k) * 1000).astype(np.uint16)
            mm[0, 0], mm[0, 1] = 0, invalid
            Image.fromarray(mm).save(f"{stem}.depth.png")
        if poses:
            write_pose(Path(f"{stem}.pose.txt"), T[k])
    return T


def link_frames(source: Path, target: Path, count: int) -> Path:
    """A folder of symbolic links to the first ``count`` frames of a 7-Scenes folder (no
    data is copied)."""
    target.mkdir(parents=True)
    stems = sorted(p.name.split(".")[0] for p in source.glob("frame-*.color.*"))[:count]
    for stem in stems:
        for path in source.glob(f"{stem}.*"):
            os.symlink(path, target / path.name)
    return target


def input_error(match: str, func, *args, **kwargs) -> str:
    """Call ``func``; it must raise one-line :class:`InputError` containing ``match``."""
    with pytest.raises(InputError) as info:
        func(*args, **kwargs)
    message = str(info.value)
    assert match in message, message
    assert "\n" not in message
    return message
