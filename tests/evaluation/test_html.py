"""report.html of a tiny real run: every section, embedded images only, estimate and ground
truth drawn differently and after the evaluation's alignment, and graceful degradation (no
ground truth, one agent, no map, no metrics); opened in headless Chromium where installed."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib.colors import to_rgba
from PIL import Image

from como3r.data.agent import open_agent
from como3r.evaluation.html import REPORT_NAME, SECTIONS, run_label, write_report
from como3r.evaluation.plot import GT_STYLE, ate_figure, trajectory_figure
from como3r.evaluation.plot_map import map_figure, sample_map
from como3r.evaluation.plot_run import timeline_figure
from como3r.evaluation.report_data import agent_rows, load_run, timeline, traffic
from como3r.io.tum import Trajectory

AGENTS = 2
IMAGE = re.compile(r"<img alt='([^']*)' src='([^']*)'")


@pytest.fixture(scope="module")
def scene(tiny_run_dir) -> Path:
    """Two agents that meet, 12 frames each at 64x48 (tests/io/tiny_run.py)."""
    return tiny_run_dir.parent / "scene"


@pytest.fixture(scope="module")
def ground_truth(scene) -> list[Trajectory]:
    return [open_agent(scene / f"agent_{a}").groundtruth for a in range(AGENTS)]


@pytest.fixture(scope="module")
def real_run(tiny_run_dir) -> Path:
    """A single-process run of the scene on the simulated prior with short global solves
    (its report.html written by the run itself), shared with the export tests."""
    return tiny_run_dir


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    return copy


def _images(page: str) -> dict[str, bytes]:
    found = {}
    for alt, src in IMAGE.findall(page):
        assert src.startswith("data:image/png;base64,"), (alt, src[:60])
        found[alt] = base64.b64decode(src.split(",", 1)[1])
    return found


@pytest.mark.slow
def test_the_report_of_a_run_has_every_section_and_embeds_its_images(real_run) -> None:
    page = (real_run / REPORT_NAME).read_text()
    # named by its folder and the one above (the run was written in run.partial)
    label = f"{real_run.parent.name}/run"
    assert f"<title>{label} - como3r report</title>" in page
    assert f"<h1>como3r report <span class='name'>{label}</span></h1>" in page
    for ident, heading in SECTIONS:
        assert f"<section id='{ident}'><h2>{heading}</h2>" in page, ident
    # self-contained: no script, no external resource, every image a data URI
    assert "<script" not in page and "http://" not in page and "https://" not in page
    assert not re.search(r"""(src|href)=['"](?!data:|#)""", page)
    images = _images(page)
    assert set(images) == {"trajectories", "ATE over time", "timing", "timeline", "map"}
    for data in images.values():
        with Image.open(io.BytesIO(data)) as png:
            assert png.format == "PNG" and png.width > 300
    # the run's notes, the per-agent table, the merge events, the folded appendix
    assert "prior: simulated" in page
    for column in (
        "frames",
        "tracked",
        "lost",
        "relocalized",
        "keyframes",
        "ATE RMSE [m]",
        "RPE trans [m]",
        "RPE rot [deg]",
        "fps",
    ):
        assert f"<th>{column}</th>" in page, column
    assert "<th>moved agents</th>" in page
    assert "single-process run" in page.lower()  # bandwidth: nothing was sent
    appendix = page[page.index("<section id='appendix'>") :]
    assert "<details><summary>Configuration (config.yaml)</summary>" in appendix
    assert "<details><summary>Prior: SimulatedPrior</summary>" in appendix
    assert "conf_base" in appendix and "conf_base" not in page[: page.index("id='appendix'")]


@pytest.mark.slow
def test_ground_truth_and_estimates_are_drawn_differently_after_the_alignment(
    real_run, ground_truth
) -> None:
    data = load_run(real_run, ground_truth)
    assert data.has_ground_truth and "one Sim(3) per gauge component" in data.alignment_text
    figure, (u, v) = trajectory_figure(
        [t.aligned for t in data.tracks], [t.gt for t in data.tracks]
    )
    lines = [line for line in figure.axes[0].lines if line.get_linestyle() != "None"]
    gt_lines = [line for line in lines if line.get_color() == GT_STYLE["color"]]
    est_lines = [line for line in lines if line not in gt_lines]
    assert len(gt_lines) == len(est_lines) == AGENTS
    for gt_line, est_line, track in zip(gt_lines, est_lines, data.tracks):
        assert gt_line.get_linestyle() == "--" and est_line.get_linestyle() == "-"
        assert np.allclose(gt_line.get_xydata(), track.gt[:, [u, v]])
        assert np.allclose(est_line.get_xydata(), track.aligned[:, [u, v]])
        assert to_rgba(gt_line.get_color()) != to_rgba(est_line.get_color())
        assert gt_line.get_zorder() < est_line.get_zorder()
    assert len({to_rgba(line.get_color()) for line in est_lines}) == AGENTS
    # the estimates are in the ground-truth frame: the shared (merged) alignment's errors
    ate = json.loads((real_run / "ate.json").read_text())
    merged = []
    for track, truth in zip(data.tracks, ground_truth):
        est = np.abs(track.timestamps[None] - track.error_times[:, None]).argmin(axis=1)
        gt = np.abs(truth.timestamps[None] - track.error_times[:, None]).argmin(axis=1)
        merged.append(np.linalg.norm(track.aligned[est] - track.gt[gt], axis=1))
    rmse = float(np.sqrt(np.mean(np.square(np.concatenate(merged)))))
    assert rmse == pytest.approx(ate["merged"]["ate"]["rmse"], rel=1e-6)


@pytest.mark.slow
def test_ate_over_time_is_the_evaluated_error(real_run, ground_truth) -> None:
    data = load_run(real_run, ground_truth)
    ate = json.loads((real_run / "ate.json").read_text())
    for track, entry in zip(data.tracks, ate["agents"]):
        assert len(track.errors) == entry["frames"]
        rmse = float(np.sqrt(np.mean(np.square(track.errors))))
        assert rmse == pytest.approx(entry["ate"]["rmse"], rel=1e-6)
    figure = ate_figure([(t.agent, t.error_times, t.errors) for t in data.tracks])
    for line, track in zip(figure.axes[0].lines, data.tracks):
        assert np.array_equal(line.get_ydata(), track.errors)
    rows = agent_rows(data)
    assert [r["agent"] for r in rows] == [0, 1, "merged 0+1"]
    metrics = json.loads((real_run / "metrics.json").read_text())
    for row, agent in zip(rows, metrics["agents"]):
        assert (row["frames"], row["tracked"], row["keyframes"]) == (
            agent["frames"],
            agent["tracked"],
            agent["keyframes"],
        )


@pytest.mark.slow
def test_the_timeline_holds_the_candidates_and_gauge_events(real_run) -> None:
    data = load_run(real_run)
    graph = json.loads((real_run / "graph.json").read_text())
    line = timeline(data)
    assert len(line.links) == len(graph["candidates"])
    assert [e.details for e in line.events] == graph["gauge_events"]
    stamps = {(k["agent"], k["keyframe"]): k["timestamp"] for k in graph["keyframes"]}
    for event in line.events:
        ends = [tuple(end) for edge in event.details["edges"] for end in edge]
        assert event.time == max(stamps[e] for e in ends)
    figure = timeline_figure(line, [0, 1])
    assert len(figure.axes[0].lines) >= len(line.links) + AGENTS


@pytest.mark.slow
def test_the_map_sample_is_deterministic_and_bounded(real_run) -> None:
    a, b = sample_map(real_run / "map.ply", 500), sample_map(real_run / "map.ply", 500)
    assert a is not None and b is not None and len(a.xyz) == 500
    assert np.array_equal(a.xyz, b.xyz) and np.array_equal(a.rgb, b.rgb)
    assert a.total == json.loads((real_run / "metrics.json").read_text())["map_points"]
    figure = map_figure(a, load_run(real_run).tracks)
    assert [ax.get_title() for ax in figure.axes] == ["top-down", "oblique"]
    assert sample_map(real_run / "missing.ply") is None


def test_the_map_sample_read_in_chunks_is_the_one_of_the_whole_file(tmp_path, monkeypatch) -> None:
    """sample_map reads map.ply a chunk at a time (bounded memory): across chunk boundaries
    and non-finite points it draws what a draw over the whole file's finite points does."""
    from como3r.evaluation import plot_map
    from como3r.io.ply import write_ply

    rng = np.random.default_rng(4)
    xyz = rng.normal(size=(3000, 3)).astype(np.float32)
    xyz[rng.choice(3000, 40, replace=False), rng.integers(0, 3, 40)] = np.nan
    rgb = rng.integers(0, 255, size=(3000, 3)).astype(np.uint8)
    write_ply(tmp_path / "map.ply", xyz, rgb, np.zeros(3000, np.int32))
    finite = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    drawn = np.sort(np.random.default_rng(0).choice(finite, 500, replace=False))
    monkeypatch.setattr(plot_map, "_CHUNK", 7)
    sample = sample_map(tmp_path / "map.ply", 500)
    np.testing.assert_array_equal(sample.xyz, xyz[drawn].astype(np.float64))
    np.testing.assert_array_equal(sample.rgb, rgb[drawn])
    assert sample.total == 3000
    whole = sample_map(tmp_path / "map.ply", 5000)  # fewer finite points than asked
    np.testing.assert_array_equal(whole.xyz, xyz[finite].astype(np.float64))


@pytest.mark.slow
def test_without_ground_truth_the_report_says_so(real_run, tmp_path) -> None:
    copy = _copy(real_run, tmp_path)
    metrics = json.loads((copy / "metrics.json").read_text())
    metrics["ate"] = None
    (copy / "metrics.json").write_text(json.dumps(metrics))
    (copy / "ate.json").unlink()
    page = write_report(copy, ["no ground truth for every agent: ATE not computed"]).read_text()
    assert "No ground truth was given for this run" in page
    assert "No ground truth: no error over time." in page
    assert "ATE RMSE" in page  # the column stays, empty
    assert set(_images(page)) == {"trajectories", "timing", "timeline", "map"}
    data = load_run(copy)
    assert not data.has_ground_truth and all(t.aligned is None for t in data.tracks)


@pytest.mark.slow
def test_a_single_agent_folder_without_map_or_metrics(real_run, tmp_path) -> None:
    folder = tmp_path / "bare"
    (folder / "trajectories").mkdir(parents=True)
    shutil.copy(real_run / "trajectories" / "agent_0.txt", folder / "trajectories")
    page = write_report(folder).read_text()
    for ident, _ in SECTIONS:
        assert f"<section id='{ident}'>" in page
    assert "One agent: there is nothing to merge." in page
    assert "No map.ply in this run" in page
    assert "This run recorded no per-stage times." in page
    assert "This run recorded no message bytes." in page
    assert set(_images(page)) == {"trajectories"}


@pytest.mark.slow
def test_missing_map_and_multiprocess_bandwidth(real_run, tmp_path) -> None:
    copy = _copy(real_run, tmp_path)
    (copy / "map.ply").unlink()
    metrics = json.loads((copy / "metrics.json").read_text())
    sent = [{"KeyframeMessage": 4_000_000 + a, "FrameDone": 1200} for a in range(AGENTS)]
    metrics["runtime"] = {
        "mode": "multiprocess",
        "bytes_by_type": {"KeyframeMessage": 8_000_001},
        "agents": [
            {"agent": a, "bytes_from_agent": sent[a], "bytes_to_agent": {"PoseUpdateMessage": 700}}
            for a in range(AGENTS)
        ],
    }
    (copy / "metrics.json").write_text(json.dumps(metrics))
    page = write_report(copy).read_text()
    assert "No map.ply in this run" in page and "map" not in _images(page)
    assert "bandwidth" in _images(page)
    assert "<td>4 MB</td>" in page and "<td>KeyframeMessage</td>" in page
    found = traffic(load_run(copy))
    assert {a: sum(t.sent.values()) for a, t in found.items()} == {0: 4_001_200, 1: 4_001_201}
    assert "mode</b> multiprocess" in page


def _browser() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
@pytest.mark.skipif(
    _browser() is None,
    reason="chromium is not installed: the report is "
    "not opened in a browser (apt-get install chromium to run this test)",
)
def test_the_report_renders_in_headless_chromium(real_run, tmp_path) -> None:
    shot = tmp_path / "shot.png"
    result = subprocess.run(
        [
            _browser(),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--window-size=1000,2400",
            f"--screenshot={shot}",
            (real_run / REPORT_NAME).resolve().as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert shot.is_file(), result.stderr[-2000:]
    with Image.open(shot) as image:
        pixels = np.asarray(image.convert("RGB"))
    assert pixels.shape[:2] == (2400, 1000)
    ink = (pixels < 200).any(axis=2)
    assert ink.mean() > 0.02  # text and plots, not a blank page
    colourful = np.ptp(pixels.astype(int), axis=2) > 60  # the agents' coloured lines
    assert colourful.sum() > 500


@pytest.mark.parametrize(
    "run_dir, label",
    [
        ("/tmp/demo_out.partial/run", "demo_out/run"),  # the demo's run, still being written
        ("/data/results/tum_desk", "results/tum_desk"),
        ("/run", "run"),
    ],
)
def test_the_report_title_names_the_run_by_its_last_two_folders(run_dir, label) -> None:
    assert run_label(Path(run_dir)) == label
