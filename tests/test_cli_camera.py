"""``como3r run --camera``: a live input end to end (a video played as a camera, a tiny
MASt3R checkpoint) and what a live input cannot do, as one error line each."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest
from typer.testing import CliRunner

from como3r.cli import app
from como3r.data.synth import synthesize
from como3r.prior.mast3r.testing import tiny_network, write_checkpoint


def _invoke(*args: str):
    return CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})


def _scene_video(root: Path, frames: int = 12) -> Path:
    """An MJPG video at 4 Hz of a small synthetic scene's frames (what a camera sees): 3 s,
    longer than the run takes to load its prior and take its frames."""
    scene = root / "scene"
    scene.mkdir(parents=True)
    synthesize(
        scene,
        agents=1,
        seed=1,
        overlap=0.2,
        frames=frames,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    video = root / "camera.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 4, (64, 48))
    for png in sorted((scene / "agent_0" / "rgb").iterdir()):
        writer.write(cv2.imread(str(png)))
    writer.release()
    return video


@pytest.mark.slow
def test_a_camera_runs_until_max_frames_and_reports_its_drops(tmp_path):
    video = _scene_video(tmp_path)
    ckpt = write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    out = tmp_path / "out"
    result = _invoke(
        "run",
        "--camera",
        str(video),
        "--out",
        str(out),
        "--weights",
        str(ckpt),
        "--set",
        "input.long_side=64",
        "--max-frames",
        "3",
    )
    assert result.exit_code == 0, result.output
    for name in ("map.ply", "metrics.json", "report.html", "trajectories/agent_0.txt"):
        assert (out / name).is_file(), name
    note = next(line for line in result.output.splitlines() if "frames processed" in line)
    assert note.startswith(f"{video}: 3 frames processed, ") and "dropped while SLAM" in note
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["agents"][0]["frames"] == 3
    # the drops the note counts, per live agent in metrics.json
    dropped = int(note.split(" frames processed, ")[1].split(" ")[0])
    assert metrics["agents"][0]["frames_dropped"] == dropped


@pytest.mark.parametrize(
    "args, fragment",
    [
        (
            ["--camera", "0", "--prior", "simulated"],
            "--camera: a live camera has no depth, which --prior simulated needs",
        ),
        (
            ["--camera", "0", "--mode", "decentralized"],
            "--camera: --mode decentralized needs each robot's odometry",
        ),
        (
            ["--camera", "0", "--agent", "{tmp}"],
            "a run takes recorded inputs (--agent) or live ones (--camera), not both",
        ),
        (
            ["--agent", "{tmp}", "--max-frames", "3"],
            "--max-frames ends --camera streams; there is none",
        ),
        (["--camera", "nowhere"], "--camera nowhere: expected a device index (0), a stream URL"),
        (
            ["--agent", "rtsp://10.0.0.2/live"],
            "rtsp:/10.0.0.2/live: agent input does not exist (a stream URL goes to --camera)",
        ),
        ([], "no input: give --agent PATH or --camera SOURCE"),
        (
            ["--camera", "97", "--weights", "{tmp}/tiny.pth"],
            "camera 97: cannot open (no such device, or it is in use)",
        ),
    ],
)
def test_what_a_live_input_cannot_do_is_one_line(tmp_path, only_error_line, args, fragment):
    write_checkpoint(tmp_path / "tiny.pth", tiny_network(seed=0))
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    line = only_error_line(_invoke("run", *args, "--out", str(tmp_path / "out")))
    assert fragment in line
    assert not (tmp_path / "out").exists()
