"""What ``como3r run`` (centralized and decentralized) / ``synth`` print while they work
(como3r.cli_progress): plain lines when stderr is not a terminal, a rich display on a
terminal, nothing under ``--quiet``."""

from __future__ import annotations

import io
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rich.console import Console
from rich.progress import Progress
from typer.testing import CliRunner

from como3r import cli_common
from como3r.cli import app
from como3r.cli_progress import RunProgress, phase_text, run_progress
from como3r.data.synth import synthesize
from como3r.decentralized.messages import DRIVER, RobotProgress, RobotReport
from como3r.decentralized.odometry_sim import add_odometry
from como3r.decentralized.runner import RobotProgressAdapter
from como3r.progress import AgentProgress, PhaseEvent

FRAMES = 16  # 8 processed per agent (input.subsample 2), the lens covered on frames 6 to 8
LINE = re.compile(r"^\[\d+:\d\d:\d\d\] ")


@pytest.fixture(scope="module")
def covered(tmp_path_factory) -> Path:
    """Two agents whose lenses are covered for a few frames: lost, then relocalized."""
    root = tmp_path_factory.mktemp("covered")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.2,
        frames=FRAMES,
        preset="covered",
        width=64,
        height=48,
        loop_frames=100,
        progress=None,
    )
    return root


def _run(scene: Path, out: Path, *args: str):
    return CliRunner().invoke(
        app,
        [
            "run",
            "--agent",
            str(scene / "agent_0"),
            "--agent",
            str(scene / "agent_1"),
            "--prior",
            "simulated",
            "--out",
            str(out),
            "--set",
            "input.long_side=64",
            *args,
        ],
    )


def _progress_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if LINE.match(line)]


@pytest.mark.slow
def test_a_run_not_on_a_terminal_prints_plain_lines_per_agent_and_phase(covered, tmp_path):
    """The multi-process runtime: per-agent lines from the agents' FrameDone messages (the
    last frame always), then one line as each coordinator phase starts."""
    result = _run(covered, tmp_path / "run")
    assert result.exit_code == 0, result.output
    lines = _progress_lines(result.output)
    assert not any("\x1b" in line for line in lines)  # no terminal control codes
    for agent in (0, 1):
        last = [line for line in lines if f" agent {agent}: " in line][-1]
        # frames done/total, fps, keyframes, lost frames, tracking state
        match = re.search(
            r"8/8 frames, [\d.]+ fps, (\d+) keyframes?, (\d+) lost, "
            r"(?:\d+ relocalized, )?(tracking|lost|relocalized)$",
            last,
        )
        assert match is not None, last
        assert int(match.group(1)) >= 1 and int(match.group(2)) >= 1, last
    phases = [line.split(" coordinator: ", 1)[1] for line in lines if " coordinator: " in line]
    assert any(p.startswith("alternation round 1/") for p in phases), phases
    assert any(p.startswith("cleanup pass 1/") for p in phases), phases
    names = [p.split(" ")[0] for p in phases]
    for name in ("outputs", "evaluation", "report"):
        assert name in names, phases
    # the phases come in the order they run, and before the summary
    assert names.index("outputs") < names.index("evaluation") < names.index("report")
    assert result.output.index("report (report.html)") < result.output.index("wrote ")


@pytest.mark.slow
def test_quiet_prints_no_progress_only_the_summary(covered, tmp_path):
    out = tmp_path / "run"
    result = _run(covered, out, "--quiet", "--single-process")
    assert result.exit_code == 0, result.output
    assert _progress_lines(result.output) == []
    assert "coordinator" not in result.output
    assert "agents" in result.output  # the summary table
    assert " ".join(result.output.split()).endswith(f"wrote {out}")


def test_synth_plain_and_quiet(tmp_path):
    args = ["synth", "--agents", "1", "--frames", "3", "--width", "32", "--height", "24"]
    plain = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert plain.exit_code == 0, plain.output
    assert [line.split("] ", 1)[1] for line in _progress_lines(plain.output)] == ["rendering: 3/3"]
    quiet = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "b"), "-q"])
    assert quiet.exit_code == 0, quiet.output
    assert " ".join(quiet.output.split()) == f"wrote 1 agent folder(s) to {tmp_path / 'b'}"


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _plain(monkeypatch) -> tuple[RunProgress, FakeClock, io.StringIO]:
    log = io.StringIO()
    monkeypatch.setattr(cli_common, "err_console", Console(file=log, width=200))
    clock = FakeClock()
    bar = Progress(disable=True)  # plain mode draws no bar
    return RunProgress(bar, "plain", interval=5.0, clock=clock), clock, log


def _event(frames_done: int, **kwargs) -> AgentProgress:
    return AgentProgress(
        **{
            "agent": 0,
            "frames_done": frames_done,
            "frames_total": 10,
            "keyframes": 2,
            "lost": 0,
            "relocalized": 0,
            **kwargs,
        }
    )


def test_plain_agent_lines_at_most_every_interval_and_the_last_frame(monkeypatch):
    progress, clock, log = _plain(monkeypatch)
    for done in range(1, 11):
        clock.now += 2.0  # 0.5 fps
        progress(_event(done, lost=done // 4, state="lost" if done == 4 else "tracking"))
    lines = log.getvalue().splitlines()
    # at 6 s (frame 3), 12 s (frame 6), 18 s (frame 9), and frame 10, the last
    assert [line.split(": ", 1)[1].split(" frames")[0] for line in lines] == [
        "3/10",
        "6/10",
        "9/10",
        "10/10",
    ]
    assert lines[0] == (
        "[0:00:06] agent 0: 3/10 frames, 0.50 fps, 2 keyframes, 0 lost, tracking"
    )  # too early for a time left: the pace spans 1 frame
    assert lines[2] == (
        "[0:00:18] agent 0: 9/10 frames, 0.50 fps, 2 keyframes, 2 lost, tracking, 0:00:02 left"
    )
    assert lines[-1].endswith("10/10 frames, 0.50 fps, 2 keyframes, 2 lost, tracking")


def _left(line: str) -> float | None:
    """The time left a line gives, in seconds (None: none)."""
    match = re.search(r"(\d+):(\d\d):(\d\d) left$", line)
    return None if match is None else 3600 * int(match[1]) + 60 * int(match[2]) + int(match[3])


def test_the_time_left_is_the_pace_after_the_warm_up(monkeypatch):
    """As the demo: 60 frames, the first three slow (compilation, the first keyframes),
    then one a second; the time left, once shown, is the time the rest takes."""
    progress, clock, log = _plain(monkeypatch)
    progress.interval = 0.0  # a line per frame
    progress(_event(0, frames_total=60))
    for done in range(1, 61):
        clock.now += 20.0 if done <= 3 else 1.0
        progress(_event(done, frames_total=60))
    lines = log.getvalue().splitlines()[1:]  # after the first event's
    estimates = {done: _left(line) for done, line in enumerate(lines, start=1)}
    assert all(estimates[done] is None for done in range(1, 6))  # too early to tell
    shown = {done: left for done, left in estimates.items() if left is not None}
    # the pace since the start would say 5:35 at frame 10 (50 frames at 10/67 fps)
    assert shown == {done: 60 - done for done in range(6, 60)}


def test_plain_lines_of_a_live_input_have_no_total_and_no_time_left(monkeypatch):
    progress, clock, log = _plain(monkeypatch)
    for done in range(1, 5):
        clock.now += 2.0
        progress(_event(done, frames_total=None))  # a camera without --max-frames
    assert log.getvalue().splitlines() == [
        "[0:00:06] agent 0: 3 frames, 0.50 fps, 2 keyframes, 0 lost, tracking"
    ]


def test_plain_agent_failure_is_always_printed(monkeypatch):
    progress, clock, log = _plain(monkeypatch)
    progress(_event(1))
    clock.now += 1.0
    progress(_event(1, state="failed"))
    assert log.getvalue().splitlines() == [
        "[0:00:01] agent 0: 1/10 frames, - fps, 2 keyframes, 0 lost, failed"
    ]


def test_plain_phase_lines_one_per_phase_and_slow_steps(monkeypatch):
    progress, clock, log = _plain(monkeypatch)
    steps = [
        ("queued keyframes", 0, 3, 0.1),
        ("queued keyframes", 1, 3, 0.1),
        ("queued keyframes", 2, 3, 0.1),
        ("alternation round", 0, 100, 6.0),
        ("alternation round", 1, 100, 1.0),
        ("alternation round", 2, 100, 1.0),
        ("outputs", 0, 3, 0.0),
    ]
    for name, done, total, seconds in steps:
        progress(PhaseEvent(name, "agents 0, 1", done, total))
        clock.now += seconds
    assert [line.split("coordinator: ", 1)[1] for line in log.getvalue().splitlines()] == [
        "queued keyframes 1/3 (agents 0, 1)",
        "alternation round 1/100 (agents 0, 1)",
        "alternation round 2/100 (agents 0, 1)",
        "outputs 1/3 (agents 0, 1)",
    ]


def test_phase_text():
    assert phase_text(PhaseEvent("report", "report.html")) == "report (report.html)"
    assert phase_text(PhaseEvent("cleanup pass", "", 1, 5)) == "cleanup pass 2/5"


@pytest.mark.parametrize("quiet", [False, True])
def test_rich_display_on_a_terminal(quiet, monkeypatch):
    terminal = io.StringIO()
    monkeypatch.setattr(
        cli_common, "err_console", Console(file=terminal, force_terminal=True, width=150)
    )
    with run_progress(quiet) as progress:
        assert progress.mode == ("quiet" if quiet else "rich")
        progress(_event(4, lost=3, relocalized=1, state="relocalized"))
        progress(PhaseEvent("alternation round", "agents 0, 1", 2, 100))
    shown = terminal.getvalue()
    if quiet:
        assert shown == ""
        return
    assert "agent 0" in shown and "4/10" in shown
    assert "3 lost, 1 relocalized, relocalized" in shown
    assert "alternation round" in shown and "2/100" in shown and "agents 0, 1" in shown


@pytest.fixture(scope="module")
def robots(tmp_path_factory) -> Path:
    """Two robots with simulated VIO odometry (decentralized mode inputs), 8 frames each."""
    root = tmp_path_factory.mktemp("robots")
    synthesize(
        root,
        agents=2,
        seed=0,
        overlap=0.2,
        frames=8,
        preset="default",
        width=64,
        height=48,
        progress=None,
    )
    for a in range(2):
        add_odometry(root / f"agent_{a}", seed=a, params="vio")
    return root


def _run_decentralized(scene: Path, out: Path, *args: str):
    return _run(scene, out, "--mode", "decentralized", *args)


@pytest.mark.slow
def test_a_decentralized_run_prints_plain_lines_per_robot_and_phase(robots, tmp_path):
    """Robot processes (the default): each robot's line from its progress message after its
    round (here the one at the mission's end), once; then the driver's phases in order."""
    result = _run_decentralized(robots, tmp_path / "run")
    assert result.exit_code == 0, result.output
    lines = _progress_lines(result.output)
    for agent in (0, 1):
        mine = [line for line in lines if f" agent {agent}: " in line]
        assert len(mine) == 1, lines
        assert re.search(
            r"8/8 frames, [\d.]+ fps, [1-9]\d* keyframes?, 0 lost, tracking$", mine[0]
        ), mine
    names = [
        line.split(" coordinator: ", 1)[1].split(" (")[0]
        for line in lines
        if " coordinator: " in line
    ]
    assert [n for n in names if n != "formulation table"] == ["outputs", "evaluation", "report"]
    assert result.output.index("report (report.html)") < result.output.index("wrote ")


@pytest.mark.slow
def test_a_quiet_decentralized_run_prints_only_the_summary(robots, tmp_path):
    out = tmp_path / "run"
    result = _run_decentralized(
        robots, out, "--quiet", "--set", "decentralized.protocol.processes=false"
    )
    assert result.exit_code == 0, result.output
    assert _progress_lines(result.output) == []
    assert "agents" in result.output
    assert " ".join(result.output.split()).endswith(f"wrote {out}")


def test_robot_messages_become_agent_progress_events():
    """A robot's progress after a round, a report that adds nothing (no event), a report of
    a robot that was in no round (every frame done), a failure."""
    events: list[AgentProgress] = []
    robots = {r: SimpleNamespace(odometry=range(n)) for r, n in enumerate((10, 6, 4))}
    adapter = RobotProgressAdapter(events.append, robots)
    assert [(e.agent, e.frames_done, e.frames_total) for e in events] == [
        (0, 0, 10),
        (1, 0, 6),
        (2, 0, 4),
    ]

    def report(robot: int, **kwargs) -> RobotReport:
        return RobotReport(
            sender=robot,
            recipient=DRIVER,
            estimate=np.zeros((0, 8)),
            frame=robot,
            loops=[],
            rejected=[],
            **kwargs,
        )

    events.clear()
    adapter(RobotProgress(sender=0, recipient=DRIVER, round=0, frames_done=10, keyframes=3))
    adapter(report(0, stats={"keyframes": 3}))
    adapter(report(1, stats={"keyframes": 2}))
    adapter(report(2, error="RuntimeError: the robot process died"))
    assert [(e.agent, e.frames_done, e.keyframes, e.state) for e in events] == [
        (0, 10, 3, "tracking"),
        (1, 6, 2, "tracking"),
        (2, 0, 0, "failed"),
    ]
