"""``como3r run --viewer save FILE.rrd`` end to end, read back with rerun's own reader.

Two agents that meet (the tiny scene of tests/runtime/test_processes.py, calibrated and
without depth refinement to stay short: about 20 s multi-process and 10 s single-process on
2 cores), run by the command line in both runtimes; the recording must hold every agent's
camera (pose, pinhole, image), trajectory, keyframe points and tracking state, on the
``frame`` and ``wall_time`` timelines, and the coordinator's merged map with both agents'
points and the cross-agent edge that merged them.
"""

from __future__ import annotations

import json
import socket
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

rerun = pytest.importorskip(
    "rerun", reason='rerun-sdk is not installed (the viewer extra: pip install "como3r[viewer]")'
)
from rerun.chunk import RrdReader  # noqa: E402

from como3r import cli_viewer  # noqa: E402
from como3r.cli import app  # noqa: E402
from como3r.data.synth import synthesize  # noqa: E402
from como3r.live import FrameEvent  # noqa: E402
from como3r.viewer import ViewerSpec, open_viewer  # noqa: E402
from como3r.viewer.recording import PALETTE  # noqa: E402

# no test here reads a figure of its runs' report.html (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("undrawn_report_figures")

#: the scene's own size, and the easy prior (the recording, not the accuracy, is tested)
OVERRIDES = ["input.long_side=64", "simulated_prior.model=easy"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scene")
    synthesize(
        root, agents=2, seed=0, overlap=0.5, frames=12, preset="default", width=64, height=48
    )
    return root


def _run(scene: Path, root: Path, *extra: str) -> tuple[Path, Path]:
    out, recording = root / "out", root / "run.rrd"
    args = [
        "run",
        "--agent",
        str(scene / "agent_0"),
        "--agent",
        str(scene / "agent_1"),
        "--out",
        str(out),
        "--prior",
        "simulated",
        "--calib",
        "-q",
        *extra,
        "--viewer",
        "save",
        str(recording),
    ]
    for override in OVERRIDES:
        args += ["--set", override]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert f"viewer: wrote {recording}" in result.output
    return out, recording


@pytest.fixture(scope="module", params=["multi-process", "single-process"])
def run(request, scene, tmp_path_factory) -> tuple[Path, Path]:
    extra = ("--single-process",) if request.param == "single-process" else ()
    return _run(scene, tmp_path_factory.mktemp(request.param), *extra)


def _read(recording: Path) -> dict[str, list]:
    """Entity path -> its chunks' record batches (in the file's order)."""
    entities: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(recording).stream().to_chunks():
        entities[chunk.entity_path].append(chunk.to_record_batch())
    return entities


def _rows(batches: list, name: str) -> list[list]:
    """Every row's instances of component ``name`` (rows without it left out)."""
    return [
        value
        for batch in batches
        if name in batch.schema.names
        for value in batch.column(name).to_pylist()
        if value is not None
    ]


@pytest.mark.slow
def test_every_agent_is_recorded(run) -> None:
    out, recording = run
    entities = _read(recording)
    metrics = json.loads((out / "metrics.json").read_text())
    for agent in (0, 1):
        frames, tracked, keyframes = (
            metrics["agents"][agent][k] for k in ("frames", "tracked", "keyframes")
        )
        base = f"/world/agents/{agent}"
        camera = entities[f"{base}/camera"]
        assert len(_rows(camera, "Transform3D:translation")) == tracked
        assert {"frame", "wall_time"} <= set(camera[0].schema.names)
        image = entities[f"{base}/camera/image"]
        assert len(_rows(image, "EncodedImage:blob")) == frames
        (K, *_), resolution = (
            _rows(image, "Pinhole:image_from_camera"),
            _rows(image, "Pinhole:resolution"),
        )
        assert np.asarray(K).reshape(3, 3)[0, 0] > 0 and resolution[0] == [[64.0, 48.0]]
        strips = _rows(entities[f"{base}/trajectory"], "LineStrips3D:strips")
        assert len(strips[-1][0]) == tracked  # the final trajectory: every tracked frame
        points = _rows(entities[f"{base}/keyframes/0/points"], "Points3D:positions")
        assert len(points[-1]) > 100
        assert sum(f"{base}/keyframes/{k}" in entities for k in range(keyframes + 1)) == keyframes
        states = [text for (text,) in _rows(entities[f"/agents/{agent}/state"], "TextLog:text")]
        assert len(states) == frames and set(states) <= {"tracking", "lost", "relocalized"}


@pytest.mark.slow
def test_the_merged_map_and_the_edge_that_merged_it(run) -> None:
    out, recording = run
    entities = _read(recording)
    assert json.loads((out / "metrics.json").read_text())["components"] == [[0, 1]]
    events = [text for (text,) in _rows(entities["/coordinator/events"], "TextLog:text")]
    assert events[0].startswith("gauge") and events[-1].startswith("final")
    assert events[-1].endswith("gauge components {0, 1}")
    colors = _rows(entities["/world/map/points"], "Points3D:colors")[-1]
    expected = {int.from_bytes(bytes([*PALETTE[a], 255]), "big") for a in (0, 1)}
    assert set(colors) == expected  # both agents' points, each in its colour
    inter = _rows(entities["/world/map/edges/inter"], "LineStrips3D:strips")
    assert len(inter[-1]) >= 1


def test_serve_mode_answers_on_its_ports() -> None:
    grpc, web = (_free_port() for _ in range(2))
    viewer = open_viewer(ViewerSpec("serve"), grpc_port=grpc, web_port=web)
    try:
        assert viewer.urls is not None
        assert viewer.urls[0] == f"rerun+http://127.0.0.1:{grpc}/proxy"
        assert viewer.urls[1].startswith(f"http://localhost:{web}/?url=rerun%2Bhttp://")
        viewer(
            FrameEvent(
                agent=0,
                frame_index=0,
                timestamp=0.0,
                state="tracking",
                T_WC=np.array([0, 0, 0, 0, 0, 0, 1, 1.0]),
                K=np.eye(3),
                image=np.zeros((4, 6, 3), np.uint8),
                wall_time=0.0,
            )
        )
        for port in (grpc, web):
            with socket.create_connection(("127.0.0.1", port), timeout=5):
                pass
    finally:
        viewer.close()


def test_serve_keeps_serving_after_the_run_until_ctrl_c(monkeypatch, capsys) -> None:
    ports = (_free_port(), _free_port())
    monkeypatch.setattr(
        cli_viewer,
        "open_viewer",
        lambda spec: open_viewer(spec, grpc_port=ports[0], web_port=ports[1]),
    )
    waited = []

    def sleep(seconds: float) -> None:
        waited.append(seconds)
        if len(waited) == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(cli_viewer.time, "sleep", sleep)
    with cli_viewer.live_viewer(ViewerSpec("serve")) as live:
        assert live is not None
    assert len(waited) == 3  # the block's end waited for Ctrl-C, which ended it quietly
    printed = capsys.readouterr().err
    assert f"rerun rerun+http://127.0.0.1:{ports[0]}/proxy" in printed
    assert "still serving the recording (Ctrl-C to stop)" in printed


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
