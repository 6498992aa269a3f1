"""Tests of como3r.backend.alternation (C-Sec. A.7) with fake solvers."""

from __future__ import annotations

import pytest

from como3r.backend import alternation
from como3r.backend.alternation import AlternationSettings, alternate
from como3r.config import DepthRefinementConfig, GlobalBAConfig
from como3r.errors import ConfigError, SolverError


class FakeSolvers:
    """Pose passes and depth steps whose step sizes follow given sequences."""

    def __init__(self, translations, depth_changes):
        self.translations = list(translations)
        self.depth_changes = list(depth_changes)
        self.calls: list[tuple[str, int]] = []

    def pose_pass(self, iters: int) -> float:
        self.calls.append(("pose", iters))
        return self.translations.pop(0) if self.translations else 0.0

    def depth_step(self) -> float:
        self.calls.append(("depth", 0))
        return self.depth_changes.pop(0) if self.depth_changes else 0.0

    def broadcast(self) -> None:
        self.calls.append(("broadcast", 0))


def test_defaults_follow_table_3():
    settings = AlternationSettings.from_config(GlobalBAConfig(), DepthRefinementConfig())
    assert settings == AlternationSettings()
    assert settings.cleanup_iters == 100 and settings.cleanup_passes == 5
    assert settings.translation_tol == 5e-3
    assert (settings.rounds, settings.pose_pass_iters) == (100, 50)
    assert not settings.round_pose_pass  # departs from C-Sec. A.7 step 2d (alternation.py)
    paper = DepthRefinementConfig(round_poses="pose_pass")
    assert AlternationSettings.from_config(GlobalBAConfig(), paper).round_pose_pass


def test_terminates_by_convergence():
    # Step 1: 3 passes until below 5 mm; step 2: both step sizes shrink by 10x per round.
    solvers = FakeSolvers(
        translations=[0.5, 0.05, 0.004] + [0.02 * 0.1**r for r in range(20)],
        depth_changes=[0.05 * 0.1**r for r in range(20)],
    )
    report = alternate(
        solvers.pose_pass,
        solvers.depth_step,
        AlternationSettings(round_pose_pass=True),
        solvers.broadcast,
    )
    assert report.cleanup_translations == [0.5, 0.05, 0.004]
    # Round r has |ds| = 0.05 * 0.1^r (< 5e-3 from r = 2) and |dt| = 0.02 * 0.1^r (< 5e-3
    # from r = 1): both below tolerance at r = 2.
    assert len(report.rounds) == 3
    assert report.converged and report.reason == "converged"
    assert report.rounds[-1].max_depth_change < 1e-3
    assert report.rounds[-1].max_translation < 5e-3


def test_round_order_and_iteration_counts():
    solvers = FakeSolvers(translations=[0.0, 1.0, 1.0], depth_changes=[1.0, 1.0])
    settings = AlternationSettings(rounds=2, round_pose_pass=True)
    alternate(solvers.pose_pass, solvers.depth_step, settings, solvers.broadcast)
    assert solvers.calls == [
        ("pose", 100),
        ("depth", 0),
        ("pose", 50),
        ("broadcast", 0),
        ("depth", 0),
        ("pose", 50),
        ("broadcast", 0),
    ]


def test_by_default_one_depth_step_at_the_poses_of_step_1():
    # a second round at the same poses would repeat the depth solve: one step, not converged
    solvers = FakeSolvers(translations=[1.0, 0.001], depth_changes=[0.1, 0.01, 0.001])
    report = alternate(
        solvers.pose_pass, solvers.depth_step, AlternationSettings(), solvers.broadcast
    )
    assert solvers.calls == [("pose", 100), ("pose", 100), ("depth", 0), ("broadcast", 0)]
    assert [r.max_translation for r in report.rounds] == [0.0]
    assert report.reason == "poses_frozen" and not report.converged


def test_a_converged_depth_step_at_frozen_poses_is_converged():
    solvers = FakeSolvers(translations=[0.001], depth_changes=[0.001])
    report = alternate(solvers.pose_pass, solvers.depth_step, AlternationSettings())
    assert len(report.rounds) == 1 and report.converged and report.reason == "converged"


def test_respects_pass_and_round_bounds():
    solvers = FakeSolvers(translations=[1.0] * 1000, depth_changes=[1.0] * 1000)
    settings = AlternationSettings(rounds=7, round_pose_pass=True, stall_ratio=float("inf"))
    report = alternate(solvers.pose_pass, solvers.depth_step, settings, solvers.broadcast)
    assert len(report.cleanup_translations) == 5
    assert len(report.rounds) == 7
    assert not report.converged and report.reason == "max_rounds"
    assert sum(1 for name, _ in solvers.calls if name == "broadcast") == 7
    assert [iters for name, iters in solvers.calls if name == "pose"] == [100] * 5 + [50] * 7


def test_depth_alone_converged_does_not_stop_while_poses_move():
    solvers = FakeSolvers(translations=[0.0] + [0.01] * 4 + [0.0], depth_changes=[0.0] * 10)
    report = alternate(
        solvers.pose_pass, solvers.depth_step, AlternationSettings(rounds=10, round_pose_pass=True)
    )
    assert len(report.rounds) == 5
    assert report.converged


def test_a_depth_step_that_stops_shrinking_ends_the_rounds():
    # |ds| halves, then shrinks by only 20 %: the third round has stalled (ratio 0.5).
    solvers = FakeSolvers(
        translations=[0.0] + [0.001] * 10, depth_changes=[0.2, 0.1, 0.08, 0.07, 0.06]
    )
    report = alternate(
        solvers.pose_pass, solvers.depth_step, AlternationSettings(rounds=10, round_pose_pass=True)
    )
    assert [r.max_depth_change for r in report.rounds] == [0.2, 0.1, 0.08]
    assert report.reason == "stalled" and not report.converged


@pytest.mark.parametrize("round_pose_pass", [False, True])
def test_without_a_pose_solver_one_depth_step_runs(round_pose_pass):
    solvers = FakeSolvers(translations=[], depth_changes=[0.1, 0.01, 0.001])
    report = alternate(
        None, solvers.depth_step, AlternationSettings(rounds=10, round_pose_pass=round_pose_pass)
    )
    assert report.cleanup_translations == [] and report.pose_seconds == 0.0
    assert [r.max_translation for r in report.rounds] == [0.0]
    assert report.reason == "poses_frozen"
    assert solvers.calls == [("depth", 0)]


def test_without_rounds_only_the_pose_passes_run():
    solvers = FakeSolvers(translations=[1.0, 0.001], depth_changes=[])
    report = alternate(solvers.pose_pass, solvers.depth_step, AlternationSettings(rounds=0))
    assert report.rounds == [] and report.cleanup_translations == [1.0, 0.001]
    assert report.converged and report.reason == "pose_converged"
    assert all(name == "pose" for name, _ in solvers.calls)


def test_time_is_reported_per_phase(monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(alternation.time, "perf_counter", lambda: clock[0])

    def pose_pass(iters: int) -> float:
        clock[0] += 2.0
        return 1.0

    def depth_step() -> float:
        clock[0] += 3.0
        return 1.0

    def broadcast() -> None:
        clock[0] += 0.5

    settings = AlternationSettings(
        cleanup_passes=2, rounds=4, round_pose_pass=True, stall_ratio=float("inf")
    )
    report = alternate(pose_pass, depth_step, settings, broadcast)
    assert report.pose_seconds == pytest.approx(2.0 * (2 + 4))
    assert report.depth_seconds == pytest.approx(3.0 * 4)
    assert report.broadcast_seconds == pytest.approx(0.5 * 4)
    assert report.seconds == pytest.approx(12.0 + 12.0 + 2.0)


def test_non_finite_step_raises_solver_error():
    with pytest.raises(SolverError, match="finite"):
        alternate(lambda iters: float("nan"), lambda: 0.0)


@pytest.mark.parametrize(
    "field, value",
    [("cleanup_passes", 0), ("rounds", -1), ("depth_convergence_tol", -1.0), ("stall_ratio", -0.5)],
)
def test_invalid_settings_raise_config_error(field, value):
    with pytest.raises(ConfigError, match=field):
        AlternationSettings(**{field: value})


def test_progress_hears_every_pass_and_round_as_it_starts():
    """One PhaseEvent before each step-1 pass and each step-2 round, numbered from 0, with
    the previous step's size once there is one (the command line's coordinator line)."""
    from como3r.progress import PhaseEvent

    solvers = FakeSolvers(translations=[0.5, 0.004, 1.0, 1.0], depth_changes=[1.0, 1.0])
    events: list[PhaseEvent] = []
    report = alternate(
        solvers.pose_pass,
        solvers.depth_step,
        AlternationSettings(rounds=2, round_pose_pass=True),
        progress=events.append,
    )
    assert [(e.name, e.done, e.total) for e in events] == [
        ("cleanup pass", 0, 5),
        ("cleanup pass", 1, 5),
        ("alternation round", 0, 2),
        ("alternation round", 1, 2),
    ]
    assert [e.detail for e in events] == [
        "",
        "previous max ||dt||/depth 0.5",
        "",
        "previous max |ds| 1",
    ]
    assert len(report.rounds) == 2


def test_progress_counts_one_round_at_frozen_poses():
    from como3r.progress import PhaseEvent

    solvers = FakeSolvers(translations=[0.001], depth_changes=[1.0])
    events: list[PhaseEvent] = []
    alternate(solvers.pose_pass, solvers.depth_step, AlternationSettings(), progress=events.append)
    assert [(e.name, e.done, e.total) for e in events] == [
        ("cleanup pass", 0, 5),
        ("alternation round", 0, 1),
    ]
