"""Tests of como3r.data.readers: layout detection, forced formats, the ground truth
``como3r eval`` reads, and dataset sequences split into agent folders."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from como3r.data.agent import open_agent
from como3r.data.readers import detect_format, read_ground_truth, resolve_format
from como3r.data.split import split_sequence

from ..test_agent import write_agent, write_video
from .layouts import (
    input_error,
    pixels,
    write_7scenes,
    write_euroc,
    write_kitti,
    write_tanks,
    write_tum,
)

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")


@pytest.fixture
def layouts(tmp_path):
    """One folder of each layout, plus a 7-Scenes sequence one level down and a EuRoC
    sequence's mav0 folder."""
    folders = {
        "agent": write_agent(tmp_path / "agent", n=3),
        "tum": tmp_path / "rgbd_dataset_freiburg3_x",
        "7scenes": tmp_path / "seq-01",
        "7scenes_below": tmp_path / "excerpt",
        "euroc": tmp_path / "MH_01_easy",
        "euroc_mav0": tmp_path / "MH_01_easy" / "mav0",
        "kitti": write_kitti(tmp_path / "dataset", n=3)["sequence"],
        "kitti_grey": write_kitti(tmp_path / "grey", n=3, folders=("image_0", "image_1"))[
            "sequence"
        ],
        "tanks": tmp_path / "Barn",
    }
    write_tum(folders["tum"], n=3)
    write_7scenes(folders["7scenes"], n=2)
    write_7scenes(folders["7scenes_below"] / "rgbd-frames", n=2)
    write_euroc(folders["euroc"], n=3)
    write_tanks(folders["tanks"])
    return folders


def test_detection(layouts, tmp_path):
    assert detect_format(layouts["agent"]) == "agent"
    assert detect_format(layouts["tum"]) == "tum"  # although it has rgb/ too
    assert detect_format(layouts["7scenes"]) == "7scenes"
    assert detect_format(layouts["7scenes_below"]) == "7scenes"
    for kind in ("euroc", "euroc_mav0", "kitti", "kitti_grey", "tanks"):
        assert detect_format(layouts[kind]) == kind.split("_")[0]
        assert open_agent(layouts[kind]).format == kind.split("_")[0]
    write_video(tmp_path / "clip.avi", n=3)
    assert detect_format(tmp_path / "clip.avi") == "agent"


def test_forced_format_is_used_and_checked(layouts):
    assert resolve_format(layouts["tum"], "tum") == "tum"
    assert resolve_format(layouts["7scenes_below"], "7scenes") == "7scenes"
    # the TUM folder read as an agent folder: rgb/ by name, depth/ stems differ
    input_error("depth map missing for frame", open_agent, layouts["tum"], format="agent")
    input_error(
        f"{layouts['agent']}: not a TUM RGB-D sequence (--format tum): expected rgb.txt",
        open_agent,
        layouts["agent"],
        format="tum",
    )
    input_error(
        f"{layouts['tum']}: not a 7-Scenes sequence (--format 7scenes): expected "
        "frame-NNNNNN.color.png|jpg",
        open_agent,
        layouts["tum"],
        format="7scenes",
    )
    input_error("not a TUM RGB-D sequence", open_agent, layouts["7scenes"], format="tum")
    for kind, expected in (
        ("euroc", "not a EuRoC sequence (--format euroc): expected mav0/cam0/data.csv"),
        (
            "kitti",
            "not a KITTI odometry sequence (--format kitti): "
            "expected image_2/ (colour) or image_0/ (grey) and "
            "times.txt",
        ),
        ("tanks", "not a Tanks and Temples sequence (--format tanks): expected image/"),
    ):
        assert resolve_format(layouts[kind], kind) == kind
        input_error(f"{layouts['agent']}: {expected}", open_agent, layouts["agent"], format=kind)
    input_error(
        "unknown format 'colmap'; choose one of auto, agent, tum, 7scenes, euroc, kitti, tanks",
        open_agent,
        layouts["agent"],
        format="colmap",
    )


def test_a_folder_of_no_known_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    message = input_error(
        f"{tmp_path / 'empty'}: not an input of a known layout: expected an agent "
        "folder (rgb/ or a video file), a TUM RGB-D sequence (rgb.txt",
        open_agent,
        tmp_path / "empty",
    )
    assert "7-Scenes sequence (frame-NNNNNN.color.png" in message
    assert "a EuRoC sequence (mav0/cam0/data.csv" in message
    assert "a KITTI odometry sequence (image_2/ or image_0/, times.txt" in message
    assert "a Tanks and Temples sequence (image/, gt_traj.txt)" in message
    (tmp_path / "flat").mkdir()
    Image.fromarray(pixels(0)).save(tmp_path / "flat" / "IMG_0001.jpg")
    input_error(f"its images belong in {tmp_path / 'flat' / 'rgb'}/", open_agent, tmp_path / "flat")
    input_error("input does not exist", open_agent, tmp_path / "nowhere")


def test_ground_truth_of_an_agent_folder_a_file_and_a_video(tmp_path):
    root = write_agent(tmp_path / "agent", n=3, groundtruth=True)
    source, trajectory = read_ground_truth(root)
    assert source == root / "groundtruth.txt" and len(trajectory) == 3
    assert read_ground_truth(root / "groundtruth.txt")[0] == root / "groundtruth.txt"
    video_dir = write_agent(tmp_path / "v", n=2, groundtruth=True)
    write_video(video_dir / "clip.avi", n=2)
    assert read_ground_truth(video_dir / "clip.avi")[0] == video_dir / "groundtruth.txt"
    input_error(
        "agent folder has no groundtruth.txt",
        read_ground_truth,
        write_agent(tmp_path / "bare", n=2),
    )


def test_ground_truth_of_each_dataset_layout(layouts, tmp_path):
    """``eval --gt`` takes each dataset folder; ground truth alone is enough for EuRoC
    (state_groundtruth_estimate0 and sensor.yaml) and Tanks and Temples (gt_traj.txt)."""
    for kind, name in (
        ("euroc", "data.csv"),
        ("euroc_mav0", "data.csv"),
        ("kitti", "05.txt"),
        ("kitti_grey", "05.txt"),
        ("tanks", "gt_traj.txt"),
    ):
        source, trajectory = read_ground_truth(layouts[kind])
        assert source.name == name and len(trajectory) >= 3
    gt_only = tmp_path / "gt_only"
    (gt_only / "mav0" / "cam0").mkdir(parents=True)
    (gt_only / "mav0" / "cam0" / "sensor.yaml").write_bytes(
        (layouts["euroc_mav0"] / "cam0" / "sensor.yaml").read_bytes()
    )
    (gt_only / "mav0" / "state_groundtruth_estimate0").mkdir()
    gt = layouts["euroc_mav0"] / "state_groundtruth_estimate0" / "data.csv"
    (gt_only / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_bytes(gt.read_bytes())
    assert len(read_ground_truth(gt_only)[1]) == len(read_ground_truth(layouts["euroc"])[1])
    (tmp_path / "tanks_gt").mkdir()
    (tmp_path / "tanks_gt" / "gt_traj.txt").write_bytes(
        (layouts["tanks"] / "gt_traj.txt").read_bytes()
    )
    np.testing.assert_allclose(
        read_ground_truth(tmp_path / "tanks_gt", fps=10.0)[1].timestamps, [0.1, 0.2, 0.3, 0.5]
    )


@pytest.mark.parametrize("kind", ["tum", "tum-freiburg1", "7scenes"])
def test_a_dataset_sequence_splits_into_agent_folders(layouts, tmp_path, kind):
    """Images and depth are named by frame stem so they pair up in the agent layout;
    7-Scenes millimetre depth is written as metres (.npy), TUM depth (5000 per metre, the
    agent layout's scale) is linked, except where the reader undistorts (freiburg 1): then
    the undistorted frames and depth maps are written."""
    if kind.startswith("tum"):
        kinect = "1" if kind == "tum-freiburg1" else "3"
        source_path = tmp_path / f"rgbd_dataset_freiburg{kinect}_long"
        write_tum(source_path, n=8)
    else:
        source_path = tmp_path / "seq-long"
        write_7scenes(source_path, n=8, start=40)
    source = open_agent(source_path)
    folders = split_sequence(source_path, tmp_path / "split", agents=2, overlap=0.25)
    first = open_agent(folders[0])
    assert first.format == "agent" and first.calib == source.calib
    suffixes = {p.suffix for p in (folders[0] / "depth").iterdir()}
    assert suffixes == ({".png"} if kind == "tum" else {".npy"})
    assert (folders[0] / "rgb" / f"{source.stems[0]}.png").samefile(source.image_paths[0]) == (
        kind != "tum-freiburg1"
    )
    for i in range(first.num_frames):
        mine, theirs = first.load_frame(i), source.load_frame(i)
        assert mine.timestamp == theirs.timestamp
        np.testing.assert_array_equal(mine.image, theirs.image)
        np.testing.assert_array_equal(mine.depth, theirs.depth)
        torch.testing.assert_close(mine.T_WC_gt, theirs.T_WC_gt)


@pytest.mark.parametrize(
    "kind, fragment",
    [
        ("euroc", "no depth (EuRoC sequences have none), which --prior simulated needs"),
        ("kitti", "no depth (KITTI odometry sequences have none), which --prior simulated needs"),
        (
            "tanks",
            "no depth (the Tanks and Temples layout has none), which --prior simulated needs",
        ),
    ],
)
def test_the_cli_takes_each_dataset_folder(layouts, tmp_path, only_error_line, kind, fragment):
    """``run --format KIND`` passes the configuration's check and stops at the missing depth
    in one line; ``eval --gt`` of the folder scores its own ground truth at the frames 0."""
    from typer.testing import CliRunner

    from como3r.cli import app
    from como3r.io.tum import write_tum

    def invoke(*args: str):
        return CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})

    folder = layouts[kind]
    line = only_error_line(
        invoke(
            "run",
            "--agent",
            str(folder),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--format",
            kind,
        )
    )
    assert fragment in line
    frames, gt = open_agent(folder).gt_for_frames()
    write_tum(tmp_path / "est.txt", gt.timestamps, gt.T_WC)
    result = invoke(
        "eval",
        "--est",
        str(tmp_path / "est.txt"),
        "--gt",
        str(folder),
        "--out",
        str(tmp_path / "eval"),
    )
    assert result.exit_code == 0, result.output
    ate = json.loads((tmp_path / "eval" / "ate.json").read_text())["agents"][0]
    assert ate["frames"] == len(frames) >= 3 and ate["ate"]["rmse"] < 1e-6
