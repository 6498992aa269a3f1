"""``como3r eval``: trajectory accuracy of a run against ground truth, as files and a table.

:func:`evaluate_run` resolves the run's per-agent trajectories and the ground truth, computes
ATE / RPE per agent and the merged ATE (:mod:`como3r.evaluation.trajectory`), and writes

- ``ate.json``: every number, the alignments and the evaluation parameters;
- ``trajectories.png``: a top view of estimate (aligned per agent) and ground truth.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import evo

from como3r.data.readers import read_ground_truth
from como3r.errors import InputError
from como3r.evaluation.gt_order import ground_truth_order_warning, in_one_frame
from como3r.evaluation.plot import plot_trajectories
from como3r.evaluation.trajectory import (
    MAX_TIME_DIFF,
    RPE_DELTA_FRAMES,
    AgentErrors,
    MergedErrors,
    Sim3Alignment,
    agent_errors,
    associate,
    merged_errors_by_component,
)
from como3r.io.tum import Trajectory, read_tum

TRAJECTORY_DIR = "trajectories"
AGENT_FILE = re.compile(r"agent_(\d+)\.txt")
JSON_NAME = "ate.json"
PLOT_NAME = "trajectories.png"


@dataclass(frozen=True)
class AgentResult:
    """One agent's files and errors.

    Attributes:
        agent: agent index.
        est_path: the estimated TUM trajectory (relative to the run folder when it is in
            one).
        gt_path: where the ground truth was read: a TUM trajectory file, or a 7-Scenes
            frames folder (its ``.pose.txt`` files).
        est_poses: number of poses in the estimate (before association).
        errors: ATE / RPE after the agent's own Sim(3) alignment.
    """

    agent: int
    est_path: Path
    gt_path: Path
    est_poses: int
    errors: AgentErrors

    def to_json(self) -> dict[str, object]:
        e = self.errors
        return {
            "agent": self.agent,
            "est": str(self.est_path),
            "gt": str(self.gt_path),
            "est_poses": self.est_poses,
            "frames": e.frames,
            "ate": e.ate.to_json(),
            "rpe_trans": e.rpe_trans.to_json(),
            "rpe_rot_deg": e.rpe_rot_deg.to_json(),
            "alignment": e.alignment.to_json(),
        }


def _merged_json(m: MergedErrors) -> dict[str, object]:
    return {
        "agents": list(m.agents),
        "frames": m.frames,
        "ate": m.ate.to_json(),
        "alignment": m.alignment.to_json(),
    }


@dataclass
class EvalSummary:
    """Everything ``como3r eval`` reports.

    Attributes:
        agents: per-agent results in agent order.
        merged_groups: merged ATE (one Sim(3) per group) of every group of agents sharing a
            gauge; a single group of all agents unless the caller passed components.
        components: the gauge components the caller gave, or None (all agents share one).
        max_diff: the timestamp association window used [s].
        notes: lines for the user (files written, partial association, components).
        ground_truth: per agent, the ground-truth trajectory it was evaluated against.
    """

    agents: list[AgentResult]
    merged_groups: list[MergedErrors]
    components: list[list[int]] | None = None
    max_diff: float = MAX_TIME_DIFF
    notes: list[str] = field(default_factory=list)
    ground_truth: list[Trajectory] = field(default_factory=list, repr=False)

    @property
    def merged(self) -> MergedErrors | None:
        """The merged ATE over ALL agents with one Sim(3), or None if they are split."""
        everyone = tuple(range(len(self.agents)))
        return next((m for m in self.merged_groups if m.agents == everyone), None)

    @property
    def merged_ate(self) -> float | None:
        """RMSE of :attr:`merged` [m], or None."""
        merged = self.merged
        return None if merged is None else merged.ate.rmse

    def alignment_of(self, agents: Sequence[int]) -> Sim3Alignment | None:
        """The Sim(3) mapping the world frame of a gauge component onto ground truth: its
        merged alignment, or the agent's own for one agent (None if not computed)."""
        key = tuple(sorted(agents))
        if len(key) == 1 and 0 <= key[0] < len(self.agents):
            return self.agents[key[0]].errors.alignment
        return next((m.alignment for m in self.merged_groups if m.agents == key), None)

    def table_rows(self) -> list[dict[str, object]]:
        """One row per agent and one per merged group ("merged" = all agents, one Sim(3))."""
        rows: list[dict[str, object]] = []
        for result in self.agents:
            e = result.errors
            rows.append(
                {
                    "agent": result.agent,
                    "frames": e.frames,
                    "ATE RMSE": e.ate.rmse,
                    "ATE mean": e.ate.mean,
                    "RPE trans": e.rpe_trans.rmse,
                    "RPE rot deg": e.rpe_rot_deg.rmse,
                    "scale": e.alignment.scale,
                }
            )
        for m in self.merged_groups:
            name = "merged" if m is self.merged else "merged " + "+".join(map(str, m.agents))
            rows.append(
                {
                    "agent": name,
                    "frames": m.frames,
                    "ATE RMSE": m.ate.rmse,
                    "ATE mean": m.ate.mean,
                    "RPE trans": "-",
                    "RPE rot deg": "-",
                    "scale": m.alignment.scale,
                }
            )
        return rows

    def to_json(self) -> dict[str, object]:
        merged = self.merged
        return {
            "parameters": {
                "alignment": "Sim(3) Umeyama (evo align, correct_scale=True), per agent",
                "association": "nearest timestamp, each agent with its own ground truth",
                "max_time_diff_s": self.max_diff,
                "ate_pose_relation": "translation_part",
                "rpe_delta": RPE_DELTA_FRAMES,
                "rpe_delta_unit": "frames",
                "merged": "associated poses of all agents stacked, one Sim(3) Umeyama",
                "evo_version": evo.__version__,
            },
            "agents": [a.to_json() for a in self.agents],
            "merged": None if merged is None else _merged_json(merged),
            "components": self.components,
            "merged_components": [_merged_json(m) for m in self.merged_groups],
        }


def resolve_est_files(est: Path, num_gt: int) -> list[Path]:
    """The estimated trajectory of each agent, in agent order.

    ``est`` is a run output folder with ``trajectories/agent_<a>.txt``, or (with exactly one
    ground truth) a single TUM file.

    Raises:
        InputError: a missing folder or file, or a number of trajectories that differs from
            the number of ground-truth paths.
    """
    if not est.exists():
        raise InputError(f"{est}: no such run output folder or trajectory file")
    if est.is_file():
        if num_gt != 1:
            raise InputError(
                f"{est}: a single trajectory file needs exactly one --gt, got {num_gt}"
            )
        return [est]
    folder = est / TRAJECTORY_DIR
    if not folder.is_dir():
        raise InputError(f"{folder}: run output has no {TRAJECTORY_DIR}/ folder")
    found = sorted(p for p in folder.iterdir() if AGENT_FILE.fullmatch(p.name))
    if not found:
        raise InputError(f"{folder}: no agent_<a>.txt trajectories")
    if len(found) != num_gt:
        raise InputError(
            f"{folder}: {len(found)} estimated trajectories but {num_gt} ground-truth path(s)"
        )
    files = [folder / f"agent_{a}.txt" for a in range(num_gt)]
    for path in files:
        if not path.is_file():
            raise InputError(f"{path}: missing trajectory (agents are numbered 0..{num_gt - 1})")
    return files


def _prepare_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{out}: cannot create output folder ({exc.strerror})") from None


def _write_plot(
    path: Path,
    results: Sequence[AgentResult],
    ests: Sequence[Trajectory],
    gts: Sequence[Trajectory],
) -> None:
    aligned = [r.errors.alignment.apply(t.positions) for r, t in zip(results, ests)]
    plot_trajectories(path, [g.positions for g in gts], aligned)


def _name_ground_truth(gt_path: Path, est: Path) -> Path:
    """How ``ate.json`` names a ground truth: relative to the run folder ``est`` when both lie
    in one staging folder (``como3r demo`` writes scene and run in ``OUT.partial`` and renames
    it, so the absolute path would name a folder that no longer exists), else as given."""
    if not est.is_dir():
        return gt_path
    gt_abs, est_abs = gt_path.resolve(), est.resolve()
    for staging in est_abs.parents:
        if staging.name.endswith(".partial") and gt_abs.is_relative_to(staging):
            return Path(os.path.relpath(gt_abs, est_abs))
    return gt_path


def evaluate_run(
    est: Path,
    gt: Sequence[Path],
    out: Path,
    components: list[list[int]] | None = None,
    max_diff: float = MAX_TIME_DIFF,
    gt_format: str = "auto",
    fps: float = 30.0,
    check_gt_order: bool = False,
) -> EvalSummary:
    """ATE / RPE of every agent of a run and the merged ATE; writes ate.json and a plot.

    Args:
        est: run output folder (``trajectories/agent_<a>.txt``) or, with one ``gt``, a TUM file.
        gt: ground truth per agent, in agent order: a TUM file, or an input folder of any
            format (:func:`como3r.data.readers.read_ground_truth`: an agent folder's or TUM
            sequence's ``groundtruth.txt``, a 7-Scenes sequence's ``.pose.txt`` files).
        out: folder to write ``ate.json`` and ``trajectories.png`` to (created if needed).
        components: groups of agents that share one gauge. When given, the merged ATE is
            computed per group with more than one agent instead of over all agents.
        max_diff: timestamp association window [s].
        gt_format: layout of the ``gt`` folders (``auto`` detects it; as ``--format``).
        fps: frame rate that stamps 7-Scenes frames (frame number / fps), as in the run.
        check_gt_order: note a warning (once, first of the notes) when the ground truths fit
            the agents much better in another order (:mod:`como3r.evaluation.gt_order`;
            agents in one world frame): for ``gt`` given by a user, not by a run that pairs
            each agent with its own input.

    Raises:
        InputError: missing or malformed files, mismatched counts, too few associated poses
            or a degenerate alignment; the message names the file.
    """
    est, out = Path(est), Path(out)
    if not gt:
        raise InputError("--gt: at least one ground-truth path is required")
    ground_truth = [read_ground_truth(Path(g), gt_format, fps) for g in gt]
    gt_files = [source for source, _ in ground_truth]
    est_files = resolve_est_files(est, len(gt_files))
    ests = [read_tum(p) for p in est_files]
    gts = [trajectory for _, trajectory in ground_truth]
    pairs = [
        associate(e, g, str(ep), str(gp), max_diff)
        for e, g, ep, gp in zip(ests, gts, est_files, gt_files)
    ]
    # inside a run folder the estimate is named relative to it: the run is written to
    # DIR.partial and renamed, so an absolute path would name a folder that no longer exists
    named = [ep.relative_to(est) if est.is_dir() else ep for ep in est_files]
    gt_named = [_name_ground_truth(gp, est) for gp in gt_files]
    results = [
        AgentResult(a, ep, gp, len(e), agent_errors(pair))
        for a, (e, ep, gp, pair) in enumerate(zip(ests, named, gt_named, pairs))
    ]
    summary = EvalSummary(
        results,
        merged_errors_by_component(pairs, components),
        components,
        max_diff,
        ground_truth=gts,
    )

    for r in results:
        if r.errors.frames < r.est_poses:
            summary.notes.append(
                f"agent {r.agent}: {r.errors.frames} of {r.est_poses} estimated "
                f"poses matched a ground-truth timestamp"
            )
    if (
        check_gt_order
        and (components is None or len(components) == 1)
        and (not est.is_dir() or in_one_frame(est))
    ):
        warning = ground_truth_order_warning(ests, gts, max_diff)
        if warning is not None:
            summary.notes.insert(0, warning)
    if summary.merged is None:
        summary.notes.append(
            f"agents form separate gauge components {components}: merged ATE "
            f"(one Sim(3)) is reported per component with more than one agent"
        )

    _prepare_out(out)
    json_path, plot_path = out / JSON_NAME, out / PLOT_NAME
    # each file is written beside its place and renamed into it: an interrupted evaluation
    # leaves the previous ate.json / plot, never half of one
    json_tmp, plot_tmp = json_path.with_suffix(".json.tmp"), plot_path.with_suffix(".png.tmp")
    try:
        json_tmp.write_text(json.dumps(summary.to_json(), indent=2) + "\n")
        _write_plot(plot_tmp, results, ests, gts)
        json_tmp.replace(json_path)
        plot_tmp.replace(plot_path)
    finally:
        json_tmp.unlink(missing_ok=True)
        plot_tmp.unlink(missing_ok=True)
    summary.notes += [f"wrote {json_path}", f"wrote {plot_path}"]
    return summary
