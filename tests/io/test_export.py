"""``como3r export``: COLMAP, nerfstudio, g2o and depth exports of a real (tiny) run."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from typer.testing import CliRunner

from como3r.cli import app
from como3r.errors import InputError
from como3r.geometry.camera import intrinsics_matrix, project, unproject_depth
from como3r.geometry.lie import quat_to_matrix, sim3_act, sim3_inverse
from como3r.io import export as export_module
from como3r.io.export import DEPTH_PNG_SCALE, depth_png, export_run
from como3r.io.g2o import G2O_HEADER
from como3r.io.keyframe_data import KeyframeData, read_keyframe_data
from como3r.io.ply import read_ply
from como3r.io.run_graph import keyframe_intrinsics, read_run_graph

from .tiny_run import HEIGHT, WIDTH


@pytest.fixture(scope="module")
def run_dir(tiny_run_dir) -> Path:
    """A finished two-agent run of the real pipeline on a tiny synthetic scene (the
    session's, which the HTML report's tests read too)."""
    return tiny_run_dir


@pytest.fixture(scope="module")
def exported(run_dir, tmp_path_factory) -> Path:
    """All four exports of the run, through the command line."""
    out = tmp_path_factory.mktemp("exported")
    result = CliRunner().invoke(
        app,
        [
            "export",
            str(run_dir),
            "--colmap",
            str(out / "colmap"),
            "--nerfstudio",
            str(out / "ns"),
            "--g2o",
            str(out / "graph.g2o"),
            "--depth",
            str(out / "depth"),
        ],
        env={"COLUMNS": "120"},
    )
    assert result.exit_code == 0, result.output
    assert "colmap" in result.output and "g2o" in result.output
    return out


def _graph(run_dir: Path) -> dict:
    return json.loads((run_dir / "graph.json").read_text())


def _rigid_matrices(graph: dict) -> list[np.ndarray]:
    """Each keyframe's rigid camera-to-world ``(4, 4)`` from graph.json (scale dropped)."""
    matrices = []
    for kf in graph["keyframes"]:
        T = torch.tensor(kf["T_WC"], dtype=torch.float64)
        M = np.eye(4)
        M[:3, :3] = quat_to_matrix(T[3:7] / T[3:7].norm()).numpy()
        M[:3, 3] = T[:3].numpy()
        matrices.append(M)
    return matrices


def test_the_run_writes_each_keyframes_data(run_dir) -> None:
    graph = _graph(run_dir)
    assert {kf["agent"] for kf in graph["keyframes"]} == {0, 1}
    assert any(e["type"] == "inter" for e in graph["edges"])
    for kf in graph["keyframes"]:
        data = read_keyframe_data(run_dir, kf["agent"], kf["keyframe"])
        assert data.X.shape == (HEIGHT, WIDTH, 3) and data.C.shape == (HEIGHT, WIDTH)
        assert data.K is not None and data.image().shape == (HEIGHT, WIDTH, 3)


def test_colmap_model_reads_back_in_pycolmap(run_dir, exported) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    graph = _graph(run_dir)
    model = pycolmap.Reconstruction(str(exported / "colmap" / "sparse" / "0"))
    assert model.num_images() == len(graph["keyframes"])
    assert model.num_cameras() == 2  # one per agent
    assert model.num_points3D() == min(
        len(read_ply(run_dir / "map.ply")), export_module.DEFAULT_MAX_POINTS
    )
    images = {im.name: im for im in model.images.values()}
    for kf, M in zip(graph["keyframes"], _rigid_matrices(graph)):
        name = f"agent{kf['agent']}_kf{kf['keyframe']:06d}.png"
        assert (exported / "colmap" / "images" / name).is_file()
        image = images[name]
        # pose round trip: COLMAP's world-to-camera, inverted, is the run's rigid T_WC
        cam_from_world = np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]])
        np.testing.assert_allclose(np.linalg.inv(cam_from_world), M, atol=1e-5)
        K = read_keyframe_data(run_dir, kf["agent"], kf["keyframe"]).K
        camera = model.cameras[image.camera_id]
        assert (camera.model_name, camera.width, camera.height) == ("PINHOLE", WIDTH, HEIGHT)
        np.testing.assert_allclose(
            camera.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], rtol=1e-6
        )
        assert image.num_points3D > 0
    # every 2-D point is where COLMAP itself projects its 3-D point (pixel and pose conventions)
    assert model.compute_num_observations() > model.num_points3D()
    model.update_point_3d_errors()
    assert model.compute_mean_reprojection_error() < 1e-3


def test_nerfstudio_matrix_and_intrinsics_project_as_the_run(run_dir, exported) -> None:
    graph = _graph(run_dir)
    document = json.loads((exported / "ns" / "transforms.json").read_text())
    assert document["camera_model"] == "OPENCV" and len(document["frames"]) == len(
        graph["keyframes"]
    )
    cloud = read_ply(exported / "ns" / document["ply_file_path"])
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    for kf, frame in zip(graph["keyframes"], document["frames"]):
        assert (exported / "ns" / frame["file_path"]).is_file()
        assert (exported / "ns" / frame["depth_file_path"]).is_file()
        M = np.asarray(frame["transform_matrix"])
        assert M.shape == (4, 4) and np.allclose(M[3], [0, 0, 0, 1])
        # the run's projection: its Sim(3) pose and K, pixel centres at integers
        K = torch.from_numpy(read_keyframe_data(run_dir, kf["agent"], kf["keyframe"]).K)
        T_CW = sim3_inverse(torch.tensor(kf["T_WC"], dtype=torch.float64))
        x_run = sim3_act(T_CW[None], torch.from_numpy(points))
        front = (x_run[:, 2] > 0.1).numpy()
        uv_run = project(x_run[front], K).numpy()
        # nerfstudio's: OpenGL camera (looks down -z, y up), pixel centres at +0.5
        x_gl = (np.linalg.inv(M) @ np.c_[points[front], np.ones(int(front.sum()))].T).T
        assert (x_gl[:, 2] < 0).all()
        u = frame["fl_x"] * x_gl[:, 0] / -x_gl[:, 2] + frame["cx"]
        v = frame["fl_y"] * -x_gl[:, 1] / -x_gl[:, 2] + frame["cy"]
        seen = ((uv_run > -0.5) & (uv_run < [WIDTH - 0.5, HEIGHT - 0.5])).all(axis=1)
        assert seen.sum() > 100
        np.testing.assert_allclose((np.c_[u, v] - 0.5)[seen], uv_run[seen], atol=1e-3)
        assert (frame["w"], frame["h"]) == (WIDTH, HEIGHT)


def test_g2o_lines_and_poses(run_dir, exported) -> None:
    graph = _graph(run_dir)
    lines = (exported / "graph.g2o").read_text().splitlines()
    assert lines[0] == G2O_HEADER
    vertices = [line.split() for line in lines if line.startswith("VERTEX_SE3:QUAT ")]
    edges = [line.split() for line in lines if line.startswith("EDGE_SE3:QUAT ")]
    fixed = [line.split() for line in lines if line.startswith("FIX ")]
    assert all(
        line.startswith(("#", "VERTEX_SE3:QUAT ", "EDGE_SE3:QUAT ", "FIX ")) for line in lines
    )
    assert [int(v[1]) for v in vertices] == list(range(len(graph["keyframes"])))
    assert all(len(v) == 9 for v in vertices) and all(len(e) == 3 + 7 + 21 for e in edges)
    assert len(edges) == len(graph["edges"]) and fixed == [["FIX", "0"]]  # one component
    for vertex, kf in zip(vertices, graph["keyframes"]):
        t_q = np.asarray(vertex[2:], dtype=np.float64)
        T = np.asarray(kf["T_WC"], dtype=np.float64)
        np.testing.assert_allclose(t_q[:3], T[:3], atol=1e-5)
        q = T[3:7] / np.linalg.norm(T[3:7])
        assert min(np.abs(t_q[3:] - q).max(), np.abs(t_q[3:] + q).max()) < 1e-5
    for edge, entry in zip(edges, graph["edges"]):
        information = np.zeros((6, 6))
        information[np.triu_indices(6)] = np.asarray(edge[10:], dtype=np.float64)
        weight = (
            min(entry["nu_i"], entry["nu_j"])
            if "nu_i" in entry
            else entry.get("match_fraction", 1.0)
        )
        np.testing.assert_allclose(information, weight * np.eye(6), atol=1e-12)

    gtsam = pytest.importorskip("gtsam")
    factors, values = gtsam.readG2o(str(exported / "graph.g2o"), True)
    assert values.size() == len(vertices) and factors.size() == len(edges)
    for k, M in enumerate(_rigid_matrices(graph)):
        np.testing.assert_allclose(values.atPose3(k).matrix(), M, atol=1e-5)
    assert factors.error(values) < 1e-8  # measurements are the final estimates' relative poses


def test_depth_npz_and_png_scale(run_dir, exported) -> None:
    graph = _graph(run_dir)
    for kf in graph["keyframes"]:
        name = f"agent{kf['agent']}_kf{kf['keyframe']:06d}"
        with np.load(exported / "depth" / f"{name}.npz") as data:
            depth, confidence = data["depth"], data["confidence"]
            assert depth.dtype == confidence.dtype == np.float32
            np.testing.assert_allclose(
                data["T_WC"], _rigid_matrices({"keyframes": [kf]})[0], atol=1e-6
            )
        source = read_keyframe_data(run_dir, kf["agent"], kf["keyframe"])
        expected_depth = kf["T_WC"][7] * source.X[..., 2].astype(np.float64)
        expected_depth[~(expected_depth > 0)] = 0.0  # invalid: 0
        np.testing.assert_allclose(depth, expected_depth, rtol=1e-6)
        np.testing.assert_array_equal(confidence, source.C)
        png = np.asarray(Image.open(exported / "depth" / f"{name}.png"))
        assert png.dtype == np.uint16 and png.shape == depth.shape
        expected = np.round(depth.astype(np.float64) * DEPTH_PNG_SCALE)
        in_range = (depth > 0) & (expected <= 65535)
        np.testing.assert_array_equal(png[in_range], expected[in_range])
        assert (png[~in_range] == 0).all() and in_range.mean() > 0.5


def test_depth_png_fixed_scale_and_invalid_zero() -> None:
    depth = np.array([[1.2344, 0.0, np.nan, -1.0], [0.0004, 65.535, 65.6, 0.001]], np.float32)
    assert depth_png(depth).tolist() == [[1234, 0, 0, 0], [0, 65535, 0, 1]]


def test_focal_from_the_pointmap_without_intrinsics(tmp_path) -> None:
    K = intrinsics_matrix(50.0, 50.0, 15.5, 11.5, dtype=torch.float64)
    X = unproject_depth(torch.full((24, 32), 2.0, dtype=torch.float64), K).float().numpy()
    camera = keyframe_intrinsics(
        KeyframeData(X, np.ones((24, 32), np.float32), None, tmp_path / "x.png")
    )
    assert camera.fx == pytest.approx(50.0, rel=1e-4) and camera.fy == camera.fx
    assert (camera.cx, camera.cy, camera.width, camera.height) == (15.5, 11.5, 32, 24)


@pytest.mark.parametrize("suffix", [".c3z", ".npz"])
def test_no_focal_to_estimate_names_the_file_the_arrays_came_from(tmp_path, suffix) -> None:
    behind = np.full((24, 32, 3), -1.0, np.float32)  # every point behind the camera
    data = KeyframeData(behind, np.ones((24, 32), np.float32), None, tmp_path / "000003.png")
    if suffix == ".npz":
        data = replace(data, arrays_path=tmp_path / "000003.npz")
    with pytest.raises(InputError, match=rf"000003\{suffix}: no intrinsics"):
        keyframe_intrinsics(data)


def test_a_failed_export_leaves_nothing(run_dir, tmp_path, monkeypatch) -> None:
    def broken(*args, **kwargs):
        raise InputError("disk full")

    monkeypatch.setattr(export_module, "write_g2o", broken)
    with pytest.raises(InputError, match="disk full"):
        export_run(run_dir, colmap=tmp_path / "colmap", g2o=tmp_path / "graph.g2o")
    assert sorted(tmp_path.iterdir()) == []  # no colmap folder, no .partial left


def test_overwrite_replaces_only_exports_of_como3r(run_dir, tmp_path) -> None:
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    (tmp_path / "mine.g2o").write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="not written by como3r"):
        export_run(run_dir, depth=tmp_path / "mine", overwrite=True)
    with pytest.raises(InputError, match="not written by como3r"):
        export_run(run_dir, g2o=tmp_path / "mine.g2o", overwrite=True)
    with pytest.raises(InputError, match="may not replace the run folder"):
        export_run(run_dir, depth=run_dir.parent, overwrite=True)
    export_run(run_dir, g2o=tmp_path / "ours.g2o")
    with pytest.raises(InputError, match="exists"):
        export_run(run_dir, g2o=tmp_path / "ours.g2o")
    export_run(run_dir, g2o=tmp_path / "ours.g2o", overwrite=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def _invoke(*args: str):
    return CliRunner().invoke(app, ["export", *args], env={"COLUMNS": "200"})


def test_cli_refuses_a_missing_run(tmp_path, only_error_line) -> None:
    line = only_error_line(_invoke(str(tmp_path / "nothing"), "--g2o", str(tmp_path / "g.g2o")))
    assert "nothing: no such run folder" in line
    assert not (tmp_path / "g.g2o").exists()


def test_cli_needs_an_export_option(run_dir, only_error_line) -> None:
    assert "nothing to export" in only_error_line(_invoke(str(run_dir)))


def test_cli_names_what_an_unfinished_or_old_run_lacks(run_dir, tmp_path, only_error_line) -> None:
    partial = tmp_path / "run.partial"
    partial.mkdir()
    assert "unfinished run" in only_error_line(_invoke(str(partial), "--g2o", "x.g2o"))
    old = tmp_path / "old"  # a run folder from before the export: no keyframe data
    old.mkdir()
    shutil.copy(run_dir / "graph.json", old)
    shutil.copy(run_dir / "map.ply", old)
    assert "no graph.json" in only_error_line(_invoke(str(tmp_path), "--g2o", "x.g2o"))
    line = only_error_line(_invoke(str(old), "--colmap", str(tmp_path / "c")))
    assert "no keyframe data for" in line and "--g2o only" in line
    result = _invoke(str(old), "--g2o", str(tmp_path / "old.g2o"))
    assert result.exit_code == 0, result.output
    assert (tmp_path / "old.g2o").read_text().startswith(G2O_HEADER)


def test_read_run_graph_rejects_a_malformed_graph(tmp_path) -> None:
    (tmp_path / "graph.json").write_text(
        json.dumps(
            {
                "keyframes": [
                    {
                        "agent": 0,
                        "keyframe": 0,
                        "frame": 0,
                        "timestamp": 0.0,
                        "T_WC": [0, 0, 0, 0, 0, 0, 1, 1],
                    }
                ],
                "edges": [{"type": "inter", "from": [0, 0], "to": [1, 3]}],
            }
        )
    )
    with pytest.raises(InputError, match="no keyframe 3 of agent 1"):
        read_run_graph(tmp_path)


def test_cli_progress_lines_and_quiet(run_dir, tmp_path) -> None:
    """Not on a terminal: a line when the keyframe count completes (as run's plain
    progress); --quiet: none, the table of exports still printed."""
    keyframes = len(_graph(run_dir)["keyframes"])
    plain = _invoke(str(run_dir), "--depth", str(tmp_path / "a"))
    assert plain.exit_code == 0, plain.output
    lines = [line for line in plain.output.splitlines() if re.match(r"^\[\d+:\d\d:\d\d\] ", line)]
    assert [line.split("] ", 1)[1] for line in lines] == [
        f"exporting keyframes: {keyframes}/{keyframes}"
    ]
    quiet = _invoke(str(run_dir), "--depth", str(tmp_path / "b"), "--quiet")
    assert quiet.exit_code == 0, quiet.output
    assert not re.search(r"^\[\d+:\d\d:\d\d\] ", quiet.output, re.M), quiet.output
    assert "exports" in quiet.output and str(tmp_path / "b") in quiet.output
