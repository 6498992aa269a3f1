"""Tiny dataset folders in the published layouts, written by the tests themselves."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.geometry.lie import quat_to_matrix

from ..shared_data import SHARED_DATA

WIDTH, HEIGHT = 32, 24
SEVEN_SCENES_REAL = SHARED_DATA / "7scenes_redkitchen_tsdf50"


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


def pose_matrices(T_WC: torch.Tensor) -> np.ndarray:
    """``(N, 4, 4)`` float64 matrices of ``(N, 8)`` poses with s = 1."""
    M = np.tile(np.eye(4), (len(T_WC), 1, 1))
    M[:, :3, :3] = quat_to_matrix(T_WC[:, 3:7]).numpy()
    M[:, :3, 3] = T_WC[:, :3].numpy()
    return M


def write_tum(
    root: Path,
    n: int = 5,
    *,
    depth: bool = True,
    groundtruth: bool = True,
    drop_depth: tuple[int, ...] = (),
    depth_offset: float = 0.004,
    extra_depth: bool = False,
) -> dict:
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
        lines = [
            "# ground truth trajectory",
            "# file: 'rgbd_dataset_test.bag'",
            "# timestamp tx ty tz qx qy qz qw",
        ]
        lines += [
            f"{t:.4f} " + " ".join(f"{v:.6f}" for v in row) for t, row in zip(gt_stamps, rows)
        ]
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return {"rgb": stamps, "gt": (gt_stamps, rows)}


def write_pose(path: Path, T: np.ndarray) -> None:
    """A 7-Scenes ``.pose.txt``: four rows of four numbers, tab-separated as released."""
    path.write_text("".join("\t".join(f"{v: .7e}" for v in row) + "\t\n" for row in T))


def write_7scenes(
    folder: Path,
    n: int = 4,
    *,
    start: int = 0,
    invalid: int = 65535,
    colour: str = "png",
    depth: bool = True,
    poses: bool = True,
) -> np.ndarray:
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


#: EuRoC cam0 intrinsics (fu, fv, cu, cv) for the 32x24 test images
EUROC_CALIB = (30.0, 31.0, 15.5, 11.5)
#: the published MH_01_easy cam0 T_BS (camera pose in the body frame), row-major 4x4
EUROC_T_BS = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
EUROC_T0_NS = 1403636579763555584


def euroc_sensor_yaml(
    calib=EUROC_CALIB, distortion=(0.0, 0.0, 0.0, 0.0), T_BS=EUROC_T_BS, resolution=(WIDTH, HEIGHT)
) -> str:
    """A ``cam0/sensor.yaml`` as EuRoC publishes it (comments, flow lists, T_BS mapping)."""
    data = ", ".join(repr(float(v)) for v in np.asarray(T_BS).ravel())
    return (
        "# General sensor definitions.\nsensor_type: camera\n"
        "comment: VI-Sensor cam0 (MT9M034)\n\n"
        "# Sensor extrinsics wrt. the body-frame.\nT_BS:\n  cols: 4\n  rows: 4\n"
        f"  data: [{data}]\n\n"
        "# Camera specific definitions.\nrate_hz: 20\n"
        f"resolution: [{resolution[0]}, {resolution[1]}]\ncamera_model: pinhole\n"
        f"intrinsics: [{', '.join(map(str, calib))}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{', '.join(map(str, distortion))}]\n"
    )


def write_euroc(
    root: Path,
    n: int = 4,
    *,
    images: list[np.ndarray] | None = None,
    groundtruth: bool = True,
    **sensor,
) -> dict:
    """A EuRoC sequence ``root/mav0`` of ``n`` 8-bit grey cam0 frames at 20 Hz (ns stamps
    from :data:`EUROC_T0_NS`), ``sensor`` passed to :func:`euroc_sensor_yaml`; ground truth
    at 200 Hz from 20 ms before the first frame to 20 ms after the last, random body poses.

    Returns:
        ``ns`` (n,) int frame stamps, ``gt_ns`` (M,), ``gt`` (M, 7) rows p xyz, q wxyz.
    """
    cam0 = root / "mav0" / "cam0"
    (cam0 / "data").mkdir(parents=True)
    images = images if images is not None else [pixels(i)[..., 0] for i in range(n)]
    ns = EUROC_T0_NS + 50_000_000 * np.arange(len(images), dtype=np.int64)
    lines = ["#timestamp [ns],filename"]
    for t, image in zip(ns, images):
        Image.fromarray(image).save(cam0 / "data" / f"{t}.png")
        lines.append(f"{t},{t}.png")
    (cam0 / "data.csv").write_text("\n".join(lines) + "\n")
    (cam0 / "sensor.yaml").write_text(euroc_sensor_yaml(**sensor))
    gt_ns = np.arange(ns[0] - 20_000_000, ns[-1] + 20_000_001, 5_000_000, dtype=np.int64)
    rng = np.random.default_rng(5)
    q = rng.normal(size=(len(gt_ns), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows = np.concatenate([rng.normal(size=(len(gt_ns), 3)), q], axis=1)
    if groundtruth:
        folder = root / "mav0" / "state_groundtruth_estimate0"
        folder.mkdir()
        header = (
            "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
            "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], "
            "v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
            "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
            "b_a_RS_S_z [m s^-2]"
        )
        body = [
            f"{t}," + ",".join(f"{v:.9f}" for v in row) + ",0.1,0.2,0.3" + ",0.0" * 6
            for t, row in zip(gt_ns, rows)
        ]
        (folder / "data.csv").write_text("\n".join([header, *body]) + "\n")
    return {"ns": ns, "gt_ns": gt_ns, "gt": rows}


#: KITTI sequence 00's published P2 (left colour camera, rectified), row-major 3x4
KITTI_P2 = np.array(
    [
        [718.856, 0.0, 607.1928, 45.38225],
        [0.0, 718.856, 185.2157, -0.1130887],
        [0.0, 0.0, 1.0, 0.003779761],
    ]
)


def write_kitti(
    root: Path,
    name: str = "05",
    n: int = 4,
    *,
    poses: bool = True,
    frames: tuple[int, ...] | None = None,
    folders: tuple[str, ...] = ("image_2",),
) -> dict:
    """A KITTI odometry dataset root ``root/sequences/<name>`` (in each of ``folders``,
    ``image_2/`` colour PNGs (:func:`pixels`) or ``image_0/`` grey ones (channel 0 of
    :func:`pixels`) of ``frames``, default all ``n``; ``times.txt`` of ``n`` lines at about
    10 Hz; ``calib.txt`` with P0-P3 and Tr) and ``root/poses/<name>.txt`` (``n`` rigid 3x4
    cam0 poses).

    Returns:
        ``sequence`` folder, ``times`` (n,), ``cam0`` (n, 4, 4) poses.
    """
    sequence = root / "sequences" / name
    sequence.mkdir(parents=True)
    for folder in folders:
        (sequence / folder).mkdir()
        for k in range(n) if frames is None else frames:
            image = pixels(k) if folder == "image_2" else pixels(k)[..., 0]
            Image.fromarray(image).save(sequence / folder / f"{k:06d}.png")
    times = np.arange(n) * 0.1036224 + np.arange(n) ** 2 * 1e-4
    (sequence / "times.txt").write_text("".join(f"{t:e}\n" for t in times))
    P0 = KITTI_P2.copy()
    P0[:, 3] = 0.0
    calib = [("P0", P0), ("P1", P0), ("P2", KITTI_P2), ("P3", KITTI_P2), ("Tr", np.eye(4)[:3])]
    (sequence / "calib.txt").write_text(
        "".join(f"{key}: " + " ".join(f"{v:.12e}" for v in M.ravel()) + "\n" for key, M in calib)
    )
    T = rigid(n, seed=7)
    if poses:
        (root / "poses").mkdir(exist_ok=True)
        (root / "poses" / f"{name}.txt").write_text(
            "".join(" ".join(f"{v:e}" for v in M[:3].ravel()) + "\n" for M in T)
        )
    return {"sequence": sequence, "times": times, "cam0": T}


def write_tanks(
    root: Path,
    ids: tuple[int, ...] = (1, 2, 3, 5),
    *,
    suffix: str = "png",
    groundtruth: tuple[int, ...] | None = None,
) -> np.ndarray:
    """A Tanks and Temples folder ``root`` with ``image/<id:06d>.<suffix>`` (image of frame
    id ``i`` is :func:`pixels` ``(i)``) and ``gt_traj.txt`` lines ``id tx ty tz qx qy qz qw``
    for ``groundtruth`` (default: every id; ``()``: no file).

    Returns:
        ``(M, 7)`` ground-truth rows (t, q_xyzw) in file order.
    """
    (root / "image").mkdir(parents=True)
    for i in ids:
        Image.fromarray(pixels(i)).save(root / "image" / f"{i:06d}.{suffix}")
    gt_ids = ids if groundtruth is None else groundtruth
    rng = np.random.default_rng(11)
    q = rng.normal(size=(len(gt_ids), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rows = np.concatenate([rng.normal(size=(len(gt_ids), 3)), q], axis=1)
    if gt_ids:
        (root / "gt_traj.txt").write_text(
            "".join(
                f"{i} " + " ".join(f"{v:.9f}" for v in row) + "\n" for i, row in zip(gt_ids, rows)
            )
        )
    return rows
