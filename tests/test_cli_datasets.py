"""``como3r run`` / ``como3r eval`` pointed at unmodified dataset folders (issue 15): a
TUM RGB-D layout written from a synthetic scene and the real 7-Scenes excerpt run end to end
with the simulated prior; --format and what the simulated prior needs are one error line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.io.packed_arrays import read_packed
from como3r.io.tum import read_tum, write_tum
from como3r.prior.mast3r.testing import tiny_network, write_checkpoint

from .data.readers.layouts import (
    SEVEN_SCENES_REAL,
    link_frames,
    write_7scenes,
)
from .data.readers.layouts import (
    write_tum as write_tum_layout,
)
from .data.readers.logs import image_stream, write_log
from .data.readers.test_kitti import KITTI_GREY_REAL
from .data.test_poses import TEDDY


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})


def tum_from_synthetic(root: Path, frames: int = 8) -> Path:
    """A TUM RGB-D sequence folder (rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/ at 5000
    per metre) holding a small synthetic scene, depth stamped 5 ms after each image; the
    scene's own intrinsics in calib.txt (they are not freiburg 1's)."""
    scene = root / "scene"
    scene.mkdir()
    synthesize(
        scene,
        agents=1,
        seed=1,
        overlap=0.2,
        frames=frames,
        preset="default",
        width=64,
        height=48,
        scale=0.3,
        loop_frames=100,
        progress=None,
    )
    agent = scene / "agent_0"
    seq = root / "rgbd_dataset_freiburg1_synthetic"
    (seq / "rgb").mkdir(parents=True)
    (seq / "depth").mkdir()
    gt = read_tum(agent / "groundtruth.txt")
    stamps = 1305031102.0 + gt.timestamps
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for t, png in zip(stamps, sorted((agent / "rgb").iterdir())):
        (seq / "rgb" / f"{t:.6f}.png").write_bytes(png.read_bytes())
        metres = read_packed(agent / "depth" / f"{png.stem}.c3z")["depth"]
        units = np.where(metres * 5000 < 65535, np.round(metres * 5000), 0).astype(np.uint16)
        Image.fromarray(units).save(seq / "depth" / f"{t + 0.005:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    write_tum(seq / "groundtruth.txt", stamps, gt.T_WC)
    (seq / "calib.txt").write_text((agent / "calib.txt").read_text())
    return seq


@pytest.mark.slow
def test_a_tum_sequence_runs_with_the_simulated_prior_and_evaluates(tmp_path):
    """`como3r run --agent <TUM folder> --prior simulated` as a user types it (the default
    multi-process runtime; only the input size set for a 64x48 sequence), then `como3r eval`
    against the same folder: every processed frame tracked, the ATE near the measured one,
    and eval's report.html drawn against the ground truth."""
    seq = tum_from_synthetic(tmp_path, frames=16)
    out = tmp_path / "out"
    result = _invoke(
        "run",
        "--agent",
        str(seq),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--set",
        "input.long_side=64",
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    agent = metrics["agents"][0]
    assert agent["frames"] == agent["tracked"] == 8 and agent["lost"] == 0, agent
    ate = metrics["ate"]["agents"][0]
    assert ate["frames"] == 8 and ate["gt"] == str(seq / "groundtruth.txt")
    # measured 0.0035 m on the 0.30 m path of the processed frames (deterministic; the
    # default multi-process runtime and --single-process agree)
    assert ate["ate"]["rmse"] < 0.007, ate
    evaluated = tmp_path / "eval"
    result = _invoke("eval", "--est", str(out), "--gt", str(seq), "--out", str(evaluated))
    assert result.exit_code == 0, result.output
    again = json.loads((evaluated / "ate.json").read_text())["agents"][0]
    assert again["ate"]["rmse"] == pytest.approx(ate["ate"]["rmse"])
    assert "ground truth dashed grey" in (evaluated / "report.html").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("runtime", [["--single-process"], []])
def test_frames_in_a_ground_truth_gap_are_skipped_with_one_warning(tmp_path, caplog, runtime):
    """Ground truth with a hole wider than 0.1 s (frames 5-8 of a 30 Hz sequence): the run
    goes on without the frames in it (frame indices and timestamps of the rest kept), says
    so once, and evaluates the rest; in one process and in the default agent processes."""
    seq = tum_from_synthetic(tmp_path, frames=16)
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    rows = [line for line in lines if not line.startswith("#")]
    stamps = np.array([float(line.split()[0]) for line in rows])
    (seq / "groundtruth.txt").write_text("\n".join(rows[:5] + rows[9:]) + "\n")
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        result = _invoke(
            "run",
            "--agent",
            str(seq),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--set",
            "input.long_side=64",
            *runtime,
        )
    assert result.exit_code == 0, result.output
    warnings = [r.getMessage() for r in caplog.records if "ground-truth pose" in r.getMessage()]
    assert warnings == [
        f"{seq}: 4 of 16 frames have no ground-truth pose (4 in gaps wider "
        "than 0.1 s); --prior simulated skips them"
    ]
    trajectory = read_tum(out / "trajectories" / "agent_0.txt")
    np.testing.assert_allclose(trajectory.timestamps, stamps[[0, 2, 4, 10, 12, 14]], atol=1e-6)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["agents"][0]["frames"] == 6
    assert metrics["ate"]["agents"][0]["frames"] == 6


@pytest.mark.slow
def test_the_check_before_the_run_does_not_repeat_reader_warnings(tmp_path, caplog):
    """The command line opens the input to check it before the run opens it: a reader's
    warning (an rgb image without depth) is said once in one process."""
    seq = tum_from_synthetic(tmp_path, frames=6)
    lines = (seq / "depth.txt").read_text().splitlines()
    (seq / "depth.txt").write_text("\n".join(lines[:3] + lines[4:]) + "\n")
    with caplog.at_level("WARNING"):
        result = _invoke(
            "run",
            "--agent",
            str(seq),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--set",
            "input.long_side=64",
            "--single-process",
        )
    assert result.exit_code == 0, result.output
    said = [r.getMessage() for r in caplog.records if "no depth image" in r.getMessage()]
    assert len(said) == 1, said


@pytest.mark.slow
def test_agent_processes_do_not_repeat_reader_warnings(tmp_path):
    """In the default agent processes the main process opens the input (and says a reader's
    warning) before each agent process opens it again: still said once."""
    seq = tum_from_synthetic(tmp_path, frames=6)
    lines = (seq / "depth.txt").read_text().splitlines()
    (seq / "depth.txt").write_text("\n".join(lines[:3] + lines[4:]) + "\n")
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "como3r.cli",
            "run",
            "--agent",
            str(seq),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--set",
            "input.long_side=64",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    output = run.stdout + run.stderr
    assert output.count("no depth image") == 1, output


def test_decentralized_robots_need_a_pose_for_every_frame(tmp_path, only_error_line):
    """--mode decentralized picks keyframes by odometry and skips no frame: a ground-truth
    gap is still refused there, in one line, before any work."""
    from .data.test_agent import write_agent

    robots = [
        write_agent(
            tmp_path / f"robot_{k}",
            n=8,
            depth="npy",
            calib="20 20 16 12",
            groundtruth=True,
            odometry=True,
        )
        for k in range(2)
    ]
    rows = (robots[1] / "groundtruth.txt").read_text().splitlines()
    (robots[1] / "groundtruth.txt").write_text("\n".join(rows[:2] + rows[6:]) + "\n")
    args = [a for r in robots for a in ("--agent", str(r))]
    line = only_error_line(
        _invoke(
            "run",
            *args,
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            "--mode",
            "decentralized",
        )
    )
    assert f"{robots[1]}: 4 of 8 frames have no ground-truth pose within 0.1 s" in line
    assert "--mode decentralized" in line and not (tmp_path / "out").exists()


def test_eval_against_a_7scenes_sequence(tmp_path):
    """A trajectory equal to the sequence's poses has no error; --format is honoured."""
    seq = tmp_path / "seq-01"
    write_7scenes(seq, n=5, start=20)
    from como3r.data.readers import read_ground_truth

    _, gt = read_ground_truth(seq)
    write_tum(tmp_path / "est.txt", gt.timestamps, gt.T_WC)
    result = _invoke(
        "eval",
        "--est",
        str(tmp_path / "est.txt"),
        "--gt",
        str(seq),
        "--out",
        str(tmp_path / "eval"),
    )
    assert result.exit_code == 0, result.output
    ate = json.loads((tmp_path / "eval" / "ate.json").read_text())["agents"][0]
    assert ate["frames"] == 5 and ate["ate"]["rmse"] < 1e-6


@pytest.mark.parametrize(
    "args, fragment",
    [
        (
            ["--format", "colmap"],
            "unknown --format 'colmap'; choose one of auto, agent, tum, "
            "7scenes, euroc, kitti, tanks, rosbag",
        ),
        (["--format", "tum"], "not a TUM RGB-D sequence (--format tum): expected rgb.txt"),
    ],
)
def test_format_errors_are_one_line(tmp_path, only_error_line, args, fragment):
    seq = tmp_path / "seq-01"
    write_7scenes(seq, n=2)
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(seq),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
            *args,
        )
    )
    assert fragment in line
    line = only_error_line(_invoke("eval", "--est", str(tmp_path), "--gt", str(seq), *args))
    assert fragment in line
    assert not (tmp_path / "out").exists()


def test_a_folder_of_no_known_layout_is_one_line(tmp_path, only_error_line):
    (tmp_path / "nothing").mkdir()
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(tmp_path / "nothing"),
            "--out",
            str(tmp_path / "out"),
            "--prior",
            "simulated",
        )
    )
    assert "nothing: not an input of a known layout: expected an agent folder" in line


@pytest.mark.parametrize(
    "case, fragment",
    [
        ("no depth", "no depth.txt (with depth/), which --prior simulated needs"),
        ("no calib", "no intrinsics (calib.txt 'fx fy cx cy'), which --prior simulated needs"),
        ("no groundtruth", "no ground truth, which --prior simulated needs"),
        (
            "gt after",
            "no frame has a ground-truth pose within 0.1 s, which --prior simulated needs",
        ),
    ],
)
def test_what_the_simulated_prior_needs_is_one_line(tmp_path, only_error_line, case, fragment):
    name = "my_sequence" if case == "no calib" else "rgbd_dataset_freiburg1_x"
    seq = tmp_path / name
    write_tum_layout(seq, n=3, depth=case != "no depth", groundtruth=case != "no groundtruth")
    if case == "gt after":  # one pose, 50 ms after the last frame
        lines = (seq / "groundtruth.txt").read_text().splitlines()
        (seq / "groundtruth.txt").write_text("\n".join(lines[:3] + lines[-1:]) + "\n")
    line = only_error_line(
        _invoke("run", "--agent", str(seq), "--out", str(tmp_path / "out"), "--prior", "simulated")
    )
    assert f"{seq}: {fragment}" in line and "--prior mast3r" in line


def test_run_takes_a_ros_log_and_its_topic(tmp_path, only_error_line):
    """--agent reads a ROS log and --topic reaches its reader (the simulated prior then says
    the log has no depth: a run on images alone takes MASt3R, too slow for this test)."""
    bag = write_log(
        tmp_path / "log.bag",
        "ros1",
        image_stream("/left/image_raw", 2) + image_stream("/right/image_raw", 2),
    )
    args = ["run", "--agent", str(bag), "--out", str(tmp_path / "out"), "--prior", "simulated"]
    line = only_error_line(_invoke(*args))
    assert "2 image topics, choose one with --topic: /left/image_raw" in line
    line = only_error_line(_invoke(*args, "--topic", "/nope"))
    assert f"{bag}: no topic '/nope'; image topics: /left/image_raw" in line
    line = only_error_line(_invoke(*args, "--topic", "/right/image_raw"))
    assert (
        f"{bag}: no depth (the ROS log reader takes images only), which --prior "
        "simulated needs" in line
    )
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
@pytest.mark.skipif(
    not SEVEN_SCENES_REAL.is_dir(), reason=f"7-Scenes excerpt not found at {SEVEN_SCENES_REAL}"
)
def test_the_real_7scenes_excerpt_runs_end_to_end(tmp_path):
    """The first 10 real Kinect frames (symbolic links, nothing copied; every second one
    processed, the default), simulated prior from their depth with 12 % holes, default
    configuration at long side 256: trajectories written, ATE against the dataset's own poses
    0.94 mm on the 3.7 cm path of the processed frames, 4 s (at the default 512: 0.59 mm)."""
    seq = link_frames(SEVEN_SCENES_REAL / "rgbd-frames", tmp_path / "seq", 10)
    out = tmp_path / "out"
    result = _invoke(
        "run",
        "--agent",
        str(seq),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--single-process",
        "--set",
        "input.long_side=256",
    )
    assert result.exit_code == 0, result.output
    trajectory = read_tum(out / "trajectories" / "agent_0.txt")
    assert len(trajectory) == 5
    np.testing.assert_allclose(trajectory.timestamps, np.arange(150, 160, 2) / 30.0, atol=1e-6)
    ate = json.loads((out / "metrics.json").read_text())["ate"]["agents"][0]
    assert ate["frames"] == 5
    assert np.isfinite(ate["ate"]["rmse"]) and ate["ate"]["rmse"] < 0.002, ate


def test_split_makes_overlapping_agents_from_a_dataset_sequence(tmp_path):
    seq = tum_from_synthetic(tmp_path, frames=20)
    result = _invoke(
        "split", str(seq), "--agents", "3", "--overlap", "0.2", "--out", str(tmp_path / "agents")
    )
    assert result.exit_code == 0, result.output
    folders = sorted((tmp_path / "agents").glob("agent_*"))
    assert [f.name for f in folders] == ["agent_0", "agent_1", "agent_2"]
    stamps = [np.loadtxt(f / "timestamps.txt", ndmin=1, usecols=0) for f in folders]
    assert sum(len(s) for s in stamps) > 20  # every frame, and the shared ones twice
    for earlier, later in zip(stamps, stamps[1:]):
        assert later[0] <= earlier[-1]  # consecutive agents share a stretch
    truth = read_tum(folders[1] / "groundtruth.txt")
    assert truth.timestamps[0] <= stamps[1][0] and stamps[1][-1] <= truth.timestamps[-1]


def test_split_fails_without_leaving_a_folder(tmp_path, only_error_line):
    seq = tum_from_synthetic(tmp_path, frames=4)
    line = only_error_line(
        _invoke("split", str(seq), "--agents", "3", "--out", str(tmp_path / "agents"))
    )
    assert "too few for 3 agents" in line
    assert not (tmp_path / "agents").exists()


def test_input_problems_come_before_missing_weights(tmp_path, only_error_line):
    """--prior mast3r (the default) with an empty weights cache: a folder of no known layout
    is said first; a good input gets past the layout check and only then the weights are
    missing."""
    (tmp_path / "nothing").mkdir()
    (tmp_path / "nothing" / "notes.txt").write_text("x")
    line = only_error_line(
        _invoke("run", "--agent", str(tmp_path / "nothing"), "--out", str(tmp_path / "out"))
    )
    assert "not an input of a known layout" in line and "weights" not in line
    seq = tum_from_synthetic(tmp_path, frames=4)
    (seq / "rgb" / sorted((seq / "rgb").iterdir())[1].name).write_bytes(b"not a png")
    line = only_error_line(_invoke("run", "--agent", str(seq), "--out", str(tmp_path / "out")))
    assert "cannot read image" in line and "weights" not in line


def link_kitti(source: Path, target: Path, count: int) -> Path:
    """``target/sequences/00`` of symbolic links to the first ``count`` images of a KITTI
    sequence's ``image_0/``, its times.txt and calib.txt, and ``target/poses/00.txt``."""
    sequence = target / "sequences" / source.name
    (sequence / "image_0").mkdir(parents=True)
    for image in sorted((source / "image_0").iterdir())[:count]:
        (sequence / "image_0" / image.name).symlink_to(image)
    for name in ("times.txt", "calib.txt"):
        (sequence / name).symlink_to(source / name)
    (target / "poses").mkdir()
    (target / "poses" / f"{source.name}.txt").symlink_to(
        source.parent.parent / "poses" / f"{source.name}.txt"
    )
    return sequence


@pytest.mark.slow
@pytest.mark.skipif(
    not KITTI_GREY_REAL.is_dir(), reason=f"KITTI grey excerpt not found at {KITTI_GREY_REAL}"
)
def test_the_real_kitti_grey_excerpt_takes_mast3r(tmp_path, only_error_line):
    """data_odometry_gray.zip as downloaded: without weights the run gets past the layout
    check and only then asks for them; with a tiny random checkpoint the grey frames reach
    the network as three channels and the run goes through (a random network tracks
    nothing: only the plumbing is tested)."""
    line = only_error_line(
        _invoke(
            "run",
            "--agent",
            str(KITTI_GREY_REAL),
            "--out",
            str(tmp_path / "none"),
            "--prior",
            "mast3r",
        )
    )
    assert "como3r weights fetch" in line and "layout" not in line
    seq = link_kitti(KITTI_GREY_REAL, tmp_path / "dataset", 6)
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    out = tmp_path / "out"
    result = _invoke(
        "run",
        "--agent",
        str(seq),
        "--out",
        str(out),
        "--prior",
        "mast3r",
        "--weights",
        str(ckpt),
        "--set",
        "input.long_side=64",
        "--single-process",
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["agents"][0]["frames"] == 3
    assert metrics["prior"]["name"] != "SimulatedPrior"


def cut_tum(source: Path, target: Path, frames: int, hole: tuple[float, float]) -> Path:
    """A TUM sequence folder of links to ``source``'s images, its lists cut to the first
    ``frames`` entries and its ground truth without the samples ``hole[0] .. hole[0] +
    hole[1]`` seconds after its first one."""
    target.mkdir(parents=True)
    for name in ("rgb", "depth"):
        (target / name).symlink_to(source / name)
    for name in ("rgb.txt", "depth.txt"):
        lines = (source / name).read_text().splitlines()
        comments = [line for line in lines if line.startswith("#")]
        (target / name).write_text("\n".join(comments + lines[len(comments) :][:frames]) + "\n")
    lines = (source / "groundtruth.txt").read_text().splitlines()
    first = read_tum(source / "groundtruth.txt").timestamps[0]
    kept = [
        line
        for line in lines
        if line.startswith("#") or not hole[0] <= float(line.split()[0]) - first < hole[0] + hole[1]
    ]
    (target / "groundtruth.txt").write_text("\n".join(kept) + "\n")
    return target


@pytest.mark.slow
@pytest.mark.skipif(not TEDDY.is_dir(), reason=f"TUM excerpt not found at {TEDDY}")
def test_the_real_tum_excerpt_with_a_motion_capture_dropout_runs(tmp_path, caplog):
    """The real freiburg3_teddy excerpt's first 30 frames, as published but for a 40 ms hole
    cut into the motion capture 0.3 s after it starts: with default settings (long side 128
    to keep it short) the run skips the 5 frames before the capture starts with one warning,
    bridges the hole, and evaluates every frame it processed."""
    seq = cut_tum(TEDDY, tmp_path / TEDDY.name, 30, (0.3, 0.04))
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        result = _invoke(
            "run",
            "--agent",
            str(seq),
            "--out",
            str(out),
            "--prior",
            "simulated",
            "--set",
            "input.long_side=128",
            "--single-process",
        )
    assert result.exit_code == 0, result.output
    said = [r.getMessage() for r in caplog.records if "ground-truth pose" in r.getMessage()]
    assert said == [
        f"{seq}: 5 of 30 frames have no ground-truth pose (5 before the first "
        "ground-truth pose); --prior simulated skips them"
    ]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["agents"][0]["frames"] == 12  # 6, 8, ..., 28
    # evaluation associates as evo does (a sample within 10 ms): a frame inside the hole
    # took an interpolated pose for the prior but has no sample that close
    estimate = read_tum(out / "trajectories" / "agent_0.txt").timestamps
    samples = read_tum(seq / "groundtruth.txt").timestamps
    near = np.abs(estimate[:, None] - samples[None]).min(axis=1) <= 0.01
    assert 10 <= near.sum() < 12
    assert metrics["ate"]["agents"][0]["frames"] == near.sum()
    assert metrics["ate"]["agents"][0]["ate"]["rmse"] < 0.05
