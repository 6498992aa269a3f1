"""Exports of a finished run folder (manual: docs/commands/export.md): COLMAP, nerfstudio, g2o
(:mod:`como3r.io.g2o`), per-keyframe depth maps and a ROS 2 bag (:mod:`como3r.io.ros2_bag`).

What is read: ``graph.json`` (keyframes with their final ``T_WC``, graph edges, gauge
components: :mod:`como3r.io.run_graph`), ``map.ply`` (the fused cloud) and the keyframe data of
:mod:`como3r.io.keyframe_data` (pointmap, confidence, intrinsics and image per keyframe).
Nothing of a live run is touched.

**Poses.** A keyframe's ``T_WC = (t, q, s)`` is a Sim(3) camera-to-world pose: a point ``X``
of its pointmap lies at ``s R(q) X + t`` in the world. The scale belongs to the pointmap (a
monocular prior predicts each keyframe's depths up to its own scale; ``s`` brings them to the
world's units); the camera itself is the rigid part ``(R, t)``: it sits at ``t``, looks along
``R``'s third column, and sees the world point ``x`` at ``x_C = R^T (x - t)`` in world units,
which projects to the same pixel as the pointmap's ``X = x_C / s``. Every export writes that
rigid pose with ``t`` in world units (the map's, which are metres only as far as the prior's
scale is metric) and puts the scale into the depths (``s X_z``).

**Pixels.** como3r's intrinsics put pixel centres at integer coordinates (OpenCV). COLMAP and
nerfstudio put them at half-integers, so their ``cx``, ``cy`` and 2-D points are como3r's
plus 0.5.

**Outputs appear whole.** Every requested export is first written to a staging sibling
(``DIR.partial``, ``FILE.partial``) and renamed into place only when all of them are complete
(:func:`~como3r.io.output.atomic_output_dir`, with its marker and ``overwrite`` rules); a
failure or Ctrl-C leaves no export and any earlier one as it was.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from como3r.errors import InputError
from como3r.geometry.lie import quat_to_matrix, se3_inverse
from como3r.io.colmap import ColmapCamera, ColmapImage, Pinhole, write_colmap_text
from como3r.io.g2o import G2O_HEADER, write_g2o
from como3r.io.keyframe_data import KeyframeData, keyframe_arrays_path, read_keyframe_data
from como3r.io.output import atomic_output_dir, check_output_dir
from como3r.io.ply import read_ply, write_ply
from como3r.io.run_graph import (
    RunGraph,
    RunKeyframe,
    keyframe_depth,
    keyframe_intrinsics,
    read_run_graph,
)

#: at most this many points of ``map.ply`` go into ``points3D.txt`` (and nerfstudio's
#: ``sparse_pc.ply``): evenly spaced in the file's order, so the same run gives the same points
DEFAULT_MAX_POINTS = 100_000
#: a map point is observed in a keyframe when its depth there is within this fraction of the
#: keyframe's own depth at the pixel it projects to (COLMAP tracks)
DEPTH_TOLERANCE = 0.05
#: 16-bit depth PNGs hold round(depth x this) per world unit (millimetres when the map's
#: unit is the metre; nerfstudio's default ``depth_unit_scale_factor`` 1e-3 reads them)
DEPTH_PNG_SCALE = 1000.0
#: the OpenCV camera (x right, y down, z forward) in OpenGL axes (x right, y up, z backward)
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class ExportSummary:
    """What :func:`export_run` wrote: one row per export (``export``, ``path``, ``wrote``:
    the counts as text), and notes for the user."""

    rows: list[dict[str, object]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def add(self, export: str, path: Path, counts: dict[str, int]) -> None:
        """One export's row."""
        self.rows.append(
            {
                "export": export,
                "path": str(path),
                "wrote": ", ".join(f"{n} {what}" for what, n in counts.items()),
            }
        )


def depth_png(depth: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint16 ``round(depth x DEPTH_PNG_SCALE)``; 0 (invalid) where the depth is 0 or
    beyond ``65535 / DEPTH_PNG_SCALE`` (65.535 world units)."""
    scaled = np.round(depth.astype(np.float64) * DEPTH_PNG_SCALE)
    return np.where((scaled > 0) & (scaled <= 65535), scaled, 0).astype(np.uint16)


def export_run(
    run: str | Path,
    colmap: str | Path | None = None,
    nerfstudio: str | Path | None = None,
    g2o: str | Path | None = None,
    depth: str | Path | None = None,
    ros2_bag: str | Path | None = None,
    overwrite: bool = False,
    max_points: int = DEFAULT_MAX_POINTS,
    progress: Callable[[int, int], None] | None = None,
) -> ExportSummary:
    """Export a finished run; every output appears only once all of them are complete.

    Args:
        run: the run folder (``como3r run --out``).
        colmap: folder for the COLMAP model (:func:`write_colmap`).
        nerfstudio: folder for nerfstudio's ``transforms.json`` (:func:`write_nerfstudio`).
        g2o: file for the pose graph (:func:`write_g2o`).
        depth: folder for the depth maps (:func:`write_depth`).
        ros2_bag: folder for the ROS 2 bag (:func:`como3r.io.ros2_bag.write_ros2_bag`).
        overwrite: replace earlier exports of como3r (never other files).
        max_points: at most this many map points in the COLMAP and nerfstudio clouds.
        progress: called with ``(done, total)`` keyframe steps, first with ``done = 0``.

    Raises:
        InputError: nothing to export; a run folder that is missing, unfinished, or lacks what
            a requested export needs; an output that may not be replaced.
    """
    folders = {
        name: Path(p)
        for name, p in (
            ("colmap", colmap),
            ("nerfstudio", nerfstudio),
            ("depth", depth),
            ("ros2_bag", ros2_bag),
        )
        if p is not None
    }
    if not folders and g2o is None:
        raise InputError(
            "nothing to export: give at least one of --colmap DIR, --nerfstudio "
            "DIR, --g2o FILE, --depth DIR, --ros2-bag DIR"
        )
    run = Path(run)
    graph = read_run_graph(run)
    _check_inputs(run, graph, folders)
    targets = [*folders.values(), *([Path(g2o)] if g2o is not None else [])]
    if len({t.resolve() for t in targets}) < len(targets):
        raise InputError("the exports must go to different places")
    for target in targets:
        if target.resolve() == run.resolve() or target.resolve() in run.resolve().parents:
            raise InputError(f"{target}: an export may not replace the run folder {run}")
    for target in folders.values():
        check_output_dir(target, overwrite)
    if g2o is not None:
        _check_g2o_target(Path(g2o), overwrite)
    total, done = len(folders) * len(graph.keyframes), [0]

    def step() -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    if progress is not None:
        progress(0, total)
    # imported here: the bag writer builds on this module's graph reading, and rosbags
    # loads only when a bag is asked for
    from como3r.io.ros2_bag import write_ros2_bag

    writers = {
        "colmap": lambda out: write_colmap(run, graph, out, max_points, step),
        "nerfstudio": lambda out: write_nerfstudio(run, graph, out, max_points, step),
        "depth": lambda out: write_depth(run, graph, out, step),
        "ros2_bag": lambda out: write_ros2_bag(run, graph, out, step),
    }
    summary = ExportSummary()
    with contextlib.ExitStack() as stack:  # every staging folder is renamed in at the end
        for name, target in folders.items():
            staging = stack.enter_context(atomic_output_dir(target, overwrite=overwrite))
            summary.add(name, target, writers[name](staging))
        if g2o is not None:
            staging_file = stack.enter_context(_atomic_output_file(Path(g2o), overwrite))
            summary.add("g2o", Path(g2o), write_g2o(graph, staging_file))
    if len(graph.components) > 1:
        summary.notes.append(
            f"the agents form {len(graph.components)} separate gauge components "
            f"{graph.components}: their poses share no world frame"
        )
    return summary


def _check_inputs(run: Path, graph: RunGraph, folders: dict[str, Path]) -> None:
    """What the requested exports read is there, before any is written."""
    if folders.keys() & {"colmap", "nerfstudio", "ros2_bag"} and not (run / "map.ply").is_file():
        raise InputError(
            f"{run}: no map.ply (the COLMAP, nerfstudio and ROS 2 bag exports take "
            f"their points from it)"
        )
    if "ros2_bag" in folders:
        for agent in sorted({k.agent for k in graph.keyframes}):
            if not (run / "trajectories" / f"agent_{agent}.txt").is_file():
                raise InputError(
                    f"{run}: no trajectories/agent_{agent}.txt (the ROS 2 bag's "
                    f"/tf and odometry come from it)"
                )
    if folders:
        missing = [
            k for k in graph.keyframes if not keyframe_arrays_path(run, k.agent, k.kf_id).is_file()
        ]
        if missing:
            raise InputError(
                f"{run}: no keyframe data for {len(missing)} of {len(graph.keyframes)} keyframes "
                f"(first: {keyframe_arrays_path(run, missing[0].agent, missing[0].kf_id)}); "
                f"runs write it since como3r export exists: run the input again, or export "
                f"--g2o only"
            )


def _check_g2o_target(path: Path, overwrite: bool) -> None:
    if path.is_dir():
        raise InputError(f"{path}: is a folder (--g2o takes a file name)")
    if path.exists():
        if not overwrite:
            raise InputError(f"{path}: exists (use --overwrite)")
        with open(path, errors="replace") as f:
            if f.readline().rstrip("\n") != G2O_HEADER:
                raise InputError(f"{path}: not written by como3r; refusing to overwrite it")


@contextlib.contextmanager
def _atomic_output_file(path: Path, overwrite: bool) -> Iterator[Path]:
    """Yield ``path.partial``, renamed to ``path`` only if the block succeeds (checked again
    then, as :func:`~como3r.io.output.atomic_output_dir` does)."""
    staging = path.with_name(path.name + ".partial")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        yield staging
    except BaseException:
        staging.unlink(missing_ok=True)
        raise
    try:
        _check_g2o_target(path, overwrite)
    except InputError:
        staging.unlink(missing_ok=True)
        raise
    os.replace(staging, path)


def _map_points(run: Path, max_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``map.ply`` thinned to at most ``max_points`` evenly spaced points: ``xyz (N, 3)``
    float64, ``rgb (N, 3)`` uint8, ``agent_id (N,)`` int32."""
    cloud = read_ply(run / "map.ply")
    keep = (
        np.arange(len(cloud))
        if len(cloud) <= max_points
        else (np.arange(max_points, dtype=np.int64) * len(cloud) // max_points)
    )
    cloud = cloud[keep]
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    rgb = np.stack([cloud["red"], cloud["green"], cloud["blue"]], axis=1)
    return xyz, rgb, cloud["agent_id"].astype(np.int32)


def _observed(
    xyz: np.ndarray, keyframe: RunKeyframe, data: KeyframeData, camera: Pinhole
) -> tuple[np.ndarray, np.ndarray]:
    """The map points a keyframe sees: in front of it, inside its image, and within
    :data:`DEPTH_TOLERANCE` of its own depth at the pixel they project to.

    Args:
        xyz: ``(N, 3)`` world points.

    Returns:
        ``(indices (P,), uv (P, 2))``: the points and their pixels (como3r's convention).
    """
    R = quat_to_matrix(keyframe.rigid[3:7]).numpy()
    x_C = (xyz - keyframe.T_WC[:3]) @ R  # R^T (x - t), row-wise
    front = np.flatnonzero(x_C[:, 2] > 0)
    uv = camera.project(x_C[front])
    col, row = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    front, uv, col, row = front[inside], uv[inside], col[inside], row[inside]
    own = keyframe_depth(keyframe, data)[row, col]
    agree = (own > 0) & (np.abs(x_C[front, 2] - own) <= DEPTH_TOLERANCE * own)
    return front[agree], uv[agree]


def write_colmap(
    run: Path,
    graph: RunGraph,
    out: Path,
    max_points: int = DEFAULT_MAX_POINTS,
    step: Callable[[], None] = lambda: None,
) -> dict[str, int]:
    """A COLMAP text model: ``out/sparse/0/{cameras,images,points3D}.txt`` and
    ``out/images/<name>.png`` (the layout COLMAP's tools, nerfstudio's ``colmap`` data
    parser and 3D Gaussian Splatting's ``-s out`` read).

    One ``PINHOLE`` camera per distinct keyframe intrinsics (an agent's keyframes share one;
    equal to 1e-6 px); one image per keyframe with its world-to-camera pose ``R^T``,
    ``-R^T t`` (rigid part, world units, see the module docstring); ``points3D.txt`` holds
    ``map.ply`` thinned to ``max_points``, each point observed in every keyframe that sees it
    (:func:`_observed`), its 2-D points the projections there.

    Returns:
        counts: ``images``, ``cameras``, ``points``, ``observations``.
    """
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True)
    (out / "images").mkdir()
    xyz, rgb, _ = _map_points(run, max_points)
    cameras: dict[tuple[int, int, float, float, float, float], ColmapCamera] = {}
    images = []
    for image_id, kf in enumerate(graph.keyframes, start=1):
        data = read_keyframe_data(run, kf.agent, kf.kf_id)
        pin = keyframe_intrinsics(data)
        key = (pin.width, pin.height, *(round(v, 6) for v in (pin.fx, pin.fy, pin.cx, pin.cy)))
        camera = cameras.setdefault(key, ColmapCamera(len(cameras) + 1, pin))
        shutil.copyfile(data.image_path, out / "images" / f"{kf.name}.png")
        T_CW = se3_inverse(kf.rigid).numpy()
        points, uv = _observed(xyz, kf, data, pin)
        images.append(
            ColmapImage(
                image_id, T_CW[3:7], T_CW[:3], camera.camera_id, f"{kf.name}.png", uv, points + 1
            )
        )
        step()
    write_colmap_text(sparse, list(cameras.values()), images, xyz, rgb)
    return {
        "images": len(images),
        "cameras": len(cameras),
        "points": len(xyz),
        "observations": sum(len(im.point3D_ids) for im in images),
    }


def write_nerfstudio(
    run: Path,
    graph: RunGraph,
    out: Path,
    max_points: int = DEFAULT_MAX_POINTS,
    step: Callable[[], None] = lambda: None,
) -> dict[str, int]:
    """nerfstudio's ``out/transforms.json``, ``out/images/<name>.png``,
    ``out/depth/<name>.png`` and ``out/sparse_pc.ply``.

    Per frame: ``file_path``, ``depth_file_path`` (16-bit, :func:`depth_png`),
    ``fl_x, fl_y, cx, cy`` (pixel centres at +0.5), ``w, h``, and ``transform_matrix``: the
    rigid camera-to-world ``[[R, t], [0, 1]]`` with the camera in OpenGL axes (OpenCV's y
    and z negated: ``[R, t] diag(1, -1, -1, 1)``), as nerfstudio expects. ``ply_file_path``
    names ``map.ply`` thinned to ``max_points`` in the same world frame.

    Returns:
        counts: ``images``, ``points``.
    """
    for sub in ("images", "depth"):
        (out / sub).mkdir()
    frames = []
    for kf in graph.keyframes:
        data = read_keyframe_data(run, kf.agent, kf.kf_id)
        pin = keyframe_intrinsics(data)
        shutil.copyfile(data.image_path, out / "images" / f"{kf.name}.png")
        Image.fromarray(depth_png(keyframe_depth(kf, data))).save(out / "depth" / f"{kf.name}.png")
        frames.append(
            {
                "file_path": f"images/{kf.name}.png",
                "depth_file_path": f"depth/{kf.name}.png",
                "fl_x": pin.fx,
                "fl_y": pin.fy,
                "cx": pin.cx + 0.5,
                "cy": pin.cy + 0.5,
                "w": pin.width,
                "h": pin.height,
                "transform_matrix": (kf.camera_to_world() @ OPENCV_TO_OPENGL).tolist(),
            }
        )
        step()
    xyz, rgb, agent_id = _map_points(run, max_points)
    write_ply(out / "sparse_pc.ply", xyz.astype(np.float32), rgb, agent_id)
    document = {"camera_model": "OPENCV", "ply_file_path": "sparse_pc.ply", "frames": frames}
    (out / "transforms.json").write_text(json.dumps(document, indent=2))
    return {"images": len(frames), "points": len(xyz)}


def write_depth(
    run: Path, graph: RunGraph, out: Path, step: Callable[[], None] = lambda: None
) -> dict[str, int]:
    """Per keyframe ``out/<name>.npz`` and ``out/<name>.png``.

    The ``.npz`` holds float32 ``depth (H, W)`` (z in the keyframe's camera in world units,
    ``s X_z``; 0 invalid), float32 ``confidence (H, W)`` (per contributing frame, as the run's
    map threshold ``visualization.map_min_confidence`` reads it), float64 ``K (3, 3)`` (pixel
    centres at integers) and float64 ``T_WC (4, 4)`` (rigid camera-to-world, OpenCV axes).
    The ``.png`` is 16-bit ``round(depth x 1000)`` (:data:`DEPTH_PNG_SCALE`: millimetres for a
    map in metres), 0 where invalid or beyond 65.535 world units.

    Returns:
        counts: ``keyframes``.
    """
    for kf in graph.keyframes:
        data = read_keyframe_data(run, kf.agent, kf.kf_id)
        pin = keyframe_intrinsics(data)
        z = keyframe_depth(kf, data)
        K = np.array([[pin.fx, 0.0, pin.cx], [0.0, pin.fy, pin.cy], [0.0, 0.0, 1.0]])
        np.savez(
            out / f"{kf.name}.npz",
            depth=z,
            confidence=data.C.astype(np.float32),
            K=K,
            T_WC=kf.camera_to_world(),
        )
        Image.fromarray(depth_png(z)).save(out / f"{kf.name}.png")
        step()
    return {"keyframes": len(graph.keyframes)}
