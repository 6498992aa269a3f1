"""What ``report.html`` shows, read from a finished run's output folder.

The report reads files only (manual: docs/outputs.md, "Run output"): ``metrics.json``,
``graph.json``, ``trajectories/agent_<a>.txt``, ``config.yaml`` and, when the run was
evaluated, the ``ate`` section of ``metrics.json`` (or ``ate.json``). Ground truth is not in
the run folder; the caller passes the trajectories the evaluation read. Both modes are
understood: the centralized runs (single-process or one process per agent,
``metrics.runtime``) and the decentralized runs (``metrics.mode == "decentralized"``:
``robots``, ``bytes``, ``rounds``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from como3r.errors import InputError
from como3r.evaluation.report import AGENT_FILE, JSON_NAME, TRAJECTORY_DIR
from como3r.evaluation.trajectory import MAX_TIME_DIFF, Sim3Alignment, associate
from como3r.io.tum import Trajectory, read_tum

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class AgentTrack:
    """One agent's estimated trajectory and, with ground truth, its errors.

    Attributes:
        agent: agent index.
        timestamps: ``(N,)`` timestamps of the estimate [s].
        positions: ``(N, 3)`` estimated camera centres in the run's world frame.
        orientations: ``(N, 4)`` estimated camera orientations (x, y, z, w) in that frame.
        aligned: ``(N, 3)`` the estimate mapped into the ground-truth frame by the Sim(3) of
            its gauge component (:attr:`RunData.alignment_text`), or None.
        gt: ``(M, 3)`` ground-truth camera centres, or None.
        error_times: ``(K,)`` timestamps of the estimate's poses associated with ground truth.
        errors: ``(K,)`` their position errors after the agent's own Sim(3) alignment [m]
            (the per-agent ATE is their RMSE).
    """

    agent: int
    timestamps: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
    aligned: np.ndarray | None = None
    gt: np.ndarray | None = None
    error_times: np.ndarray | None = None
    errors: np.ndarray | None = None


@dataclass(frozen=True)
class Link:
    """A cross-agent candidate or loop closure between two keyframes.

    Attributes:
        ends: ``((agent, keyframe), (agent, keyframe))``.
        times: the two keyframes' timestamps [s].
        status: ``admitted``, ``rejected``, ``pending``, ``inconsistent`` (centralized
            candidates) or ``accepted`` / ``rejected`` (decentralized loops).
    """

    ends: tuple[tuple[int, int], tuple[int, int]]
    times: tuple[float, float]
    status: str


@dataclass(frozen=True)
class MergeEvent:
    """Agents joining one frame: a gauge synchronization or a rendezvous round.

    Attributes:
        time: when it could happen first: the latest timestamp of its supporting keyframes
            (centralized) or the round's time (decentralized) [s].
        label: one line for the figure.
        details: the event as ``graph.json`` / ``metrics.json`` hold it.
    """

    time: float
    label: str
    details: dict[str, Any]


@dataclass
class Timeline:
    """Keyframe times per agent, cross-agent links and merge events."""

    keyframes: dict[int, np.ndarray] = field(default_factory=dict)
    links: list[Link] = field(default_factory=list)
    events: list[MergeEvent] = field(default_factory=list)


@dataclass
class RunData:
    """Everything the report shows, read from one run folder.

    Attributes:
        run_dir: the run folder.
        metrics: ``metrics.json`` (empty if absent).
        ate: the evaluation (``metrics.json`` ``ate`` or ``ate.json``), or None.
        graph: ``graph.json``, or None.
        config_text: ``config.yaml``, or None.
        tracks: per agent, in agent order.
        alignment_text: how the estimates of the top view were aligned, or None.
    """

    run_dir: Path
    metrics: dict[str, Any]
    ate: dict[str, Any] | None
    graph: dict[str, Any] | None
    config_text: str | None
    tracks: list[AgentTrack]
    alignment_text: str | None = None

    @property
    def decentralized(self) -> bool:
        """Whether the run is a decentralized (FLOCC) one."""
        return self.metrics.get("mode") == "decentralized"

    @property
    def runtime_mode(self) -> str:
        """``decentralized``, ``multiprocess`` or ``single-process``."""
        if self.decentralized:
            return "decentralized"
        return str((self.metrics.get("runtime") or {}).get("mode", "single-process"))

    @property
    def has_ground_truth(self) -> bool:
        """Whether any agent's estimate is drawn against ground truth."""
        return any(t.gt is not None for t in self.tracks)


def _read_json(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        logger.warning("%s: not readable as JSON (%s); the report leaves it out", path, exc)
        return None


def _read_estimate(path: Path) -> Trajectory | None:
    try:
        return read_tum(path)
    except InputError as exc:  # an agent that tracked nothing writes an empty file
        logger.info("report: %s", exc)
        return None


def _shared_alignment(ate: dict[str, Any], agent: int) -> tuple[Sim3Alignment, list[int]] | None:
    """The merged (one Sim(3) per gauge component) alignment that covers ``agent``."""
    for merged in ate.get("merged_components") or []:
        if agent in merged["agents"]:
            return Sim3Alignment.from_json(merged["alignment"]), list(merged["agents"])
    return None


def _track(
    agent: int, est: Trajectory | None, gt: Trajectory | None, ate: dict[str, Any] | None
) -> tuple[AgentTrack, list[int] | None]:
    """An agent's track; with ground truth and an evaluation, aligned and with errors.

    Returns:
        The track and the agents sharing its top-view alignment (None: its own).
    """
    if est is None:
        empty = np.zeros((0, 3))
        return AgentTrack(agent, np.zeros(0), empty, np.zeros((0, 4))), None
    poses = est.T_WC.cpu().numpy()
    base = {
        "agent": agent,
        "timestamps": est.timestamps,
        "positions": poses[:, :3],
        "orientations": poses[:, 3:7],
    }
    entry = next((e for e in (ate or {}).get("agents", []) if e["agent"] == agent), None)
    if gt is None or entry is None:
        return AgentTrack(**base), None
    own = Sim3Alignment.from_json(entry["alignment"])
    shared = _shared_alignment(ate or {}, agent)
    alignment, group = shared if shared is not None else (own, None)
    max_diff = float((ate or {}).get("parameters", {}).get("max_time_diff_s", MAX_TIME_DIFF))
    try:
        pair = associate(est, gt, f"agent_{agent}", "ground truth", max_diff)
    except InputError as exc:
        logger.info("report: %s", exc)
        times = errors = None
    else:
        times = np.asarray(pair.est.timestamps)
        errors = np.linalg.norm(own.apply(pair.est.positions_xyz) - pair.gt.positions_xyz, axis=1)
    return AgentTrack(
        **base,
        aligned=alignment.apply(poses[:, :3]),
        gt=gt.positions,
        error_times=times,
        errors=errors,
    ), group


def _alignment_text(groups: list[list[int] | None], tracks: list[AgentTrack]) -> str | None:
    if not any(t.aligned is not None for t in tracks):
        return None
    shared = sorted({tuple(g) for g in groups if g is not None and len(g) > 1})
    if not shared:
        return "Each estimate is mapped onto its ground truth by its own Sim(3) (Umeyama)"
    named = ", ".join("+".join(map(str, g)) for g in shared)
    text = (
        f"Estimates are mapped onto ground truth by one Sim(3) per gauge component "
        f"(agents {named}), the alignment of the merged ATE, so a misplaced agent shows"
    )
    alone = [t.agent for t, g in zip(tracks, groups) if t.aligned is not None and g is None]
    if alone:
        text += f"; agents alone in their component ({', '.join(map(str, alone))}) use their own"
    return text


def load_run(
    run_dir: Path,
    ground_truth: Sequence[Trajectory | None] | None = None,
    ate: dict[str, Any] | None = None,
) -> RunData:
    """Read a run folder for the report.

    Args:
        run_dir: the run's output folder.
        ground_truth: per agent, the ground truth the evaluation used (None where an agent
            has none); without it the report draws no ground truth and no error curves.
        ate: the evaluation to show (``EvalSummary.to_json()``, as ``como3r eval`` computes
            it later); None takes the run's own (``metrics.json`` ``ate``, else ``ate.json``).
    """
    run_dir = Path(run_dir)
    metrics = _read_json(run_dir / "metrics.json") or {}
    if ate is None:
        ate = metrics.get("ate") or _read_json(run_dir / JSON_NAME)
    config = run_dir / "config.yaml"
    folder = run_dir / TRAJECTORY_DIR
    numbers = sorted(
        int(m.group(1))
        for p in (folder.iterdir() if folder.is_dir() else [])
        if (m := AGENT_FILE.fullmatch(p.name))
    )
    count = max(numbers) + 1 if numbers else 0
    truths = list(ground_truth or [])
    tracks, groups = [], []
    for agent in range(count):
        path = folder / f"agent_{agent}.txt"
        est = _read_estimate(path) if path.is_file() else None
        gt = truths[agent] if agent < len(truths) else None
        track, group = _track(agent, est, gt, ate)
        tracks.append(track)
        groups.append(group)
    return RunData(
        run_dir,
        metrics,
        ate,
        _read_json(run_dir / "graph.json"),
        config.read_text() if config.is_file() else None,
        tracks,
        _alignment_text(groups, tracks),
    )


# ---------------------------------------------------------------------------- tables


def _stat(entry: dict[str, Any] | None, key: str) -> float | None:
    return None if entry is None else entry[key]["rmse"]


def agent_rows(data: RunData) -> list[dict[str, Any]]:
    """One row per agent (frames, tracking, keyframes, ATE / RPE, fps) and one per merged
    group; None where the run has no such number."""
    per_agent = data.metrics.get("robots" if data.decentralized else "agents") or []
    ate_entries = {e["agent"]: e for e in (data.ate or {}).get("agents", [])}
    rows = []
    for track in data.tracks:
        m = per_agent[track.agent] if track.agent < len(per_agent) else {}
        e = ate_entries.get(track.agent)
        rows.append(
            {
                "agent": track.agent,
                "frames": m.get("frames", len(track.timestamps)),
                "tracked": m.get("tracked"),
                "lost": m.get("lost"),
                "relocalized": m.get("relocalized"),
                "keyframes": m.get("keyframes"),
                "ATE RMSE [m]": _stat(e, "ate"),
                "RPE trans [m]": _stat(e, "rpe_trans"),
                "RPE rot [deg]": _stat(e, "rpe_rot_deg"),
                "fps": m.get("fps"),
            }
        )
    for merged in (data.ate or {}).get("merged_components") or []:
        if len(merged["agents"]) < 2:
            continue
        row = dict.fromkeys(rows[0]) if rows else {}
        row.update(
            {
                "agent": "merged " + "+".join(map(str, merged["agents"])),
                "frames": merged["frames"],
                "ATE RMSE [m]": merged["ate"]["rmse"],
            }
        )
        rows.append(row)
    return rows


def stage_seconds(data: RunData) -> dict[str, dict[str, float]]:
    """Wall seconds per stage, by column (``agent <a>``, ``coordinator``).

    Centralized runs record every stage; decentralized runs per robot the prior's encoder and
    decoder time and the registration's descriptor matching and pose fitting.
    """
    columns: dict[str, dict[str, float]] = {}
    if data.decentralized:
        for a, robot in enumerate(data.metrics.get("robots") or []):
            times = {
                "prior_encode": robot.get("encode_seconds"),
                "prior_decode": robot.get("decode_seconds"),
                "matching": robot.get("match_seconds"),
                "registration_fit": robot.get("fit_seconds"),
            }
            if any(v is not None for v in times.values()):
                columns[f"agent {a}"] = {k: float(v) for k, v in times.items() if v is not None}
        return columns
    for a, agent in enumerate(data.metrics.get("agents") or []):
        if agent.get("stage_seconds"):
            columns[f"agent {a}"] = dict(agent["stage_seconds"])
    coordinator = (data.metrics.get("coordinator") or {}).get("stage_seconds")
    if coordinator:
        columns["coordinator"] = dict(coordinator)
    return columns


@dataclass(frozen=True)
class Traffic:
    """Bytes one agent sent and received, by message type."""

    sent: dict[str, int]
    received: dict[str, int]


def traffic(data: RunData) -> dict[int, Traffic] | None:
    """Bytes per agent and message type, or None where nothing was sent as a message
    (single-process runs hand data over in memory)."""
    if data.decentralized:
        per_robot = (data.metrics.get("bytes") or {}).get("per_robot") or {}
        found = {
            int(r): Traffic(dict(v.get("sent", {})), dict(v.get("received", {})))
            for r, v in per_robot.items()
        }
    else:
        found = {
            int(a.get("agent", i)): Traffic(
                dict(a.get("bytes_from_agent", {})), dict(a.get("bytes_to_agent", {}))
            )
            for i, a in enumerate((data.metrics.get("runtime") or {}).get("agents") or [])
        }
    return dict(sorted(found.items())) or None


# -------------------------------------------------------------------------- timeline


def _gauge_event(event: dict[str, Any], times: dict[tuple[int, int], float]) -> MergeEvent:
    stamps = [times.get(tuple(end), np.nan) for edge in event.get("edges", []) for end in edge]
    known = [t for t in stamps if np.isfinite(t)]
    moved = event.get("moved_agents", [])
    label = (
        f"agent{'s' if len(moved) > 1 else ''} {', '.join(map(str, moved))} join "
        f"component {event.get('anchor_component')} ({event.get('method')})"
    )
    return MergeEvent(max(known) if known else float("nan"), label, dict(event))


def timeline(data: RunData) -> Timeline:
    """Keyframe times, cross-agent links and merge events of the run (``graph.json``;
    decentralized rounds from ``metrics.json``)."""
    result = Timeline()
    graph = data.graph or {}
    times: dict[tuple[int, int], float] = {}
    for kf in graph.get("keyframes", []):
        times[(int(kf["agent"]), int(kf["keyframe"]))] = float(kf["timestamp"])
    for agent in sorted({a for a, _ in times}):
        result.keyframes[agent] = np.sort([t for (a, _), t in times.items() if a == agent])
    if data.decentralized:
        links = [
            (e["from"], e["to"], "accepted" if e.get("accepted") else "rejected")
            for e in graph.get("edges", [])
            if e.get("type") == "inter"
        ]
        result.events = [
            MergeEvent(
                float(r["time_s"]),
                f"round {r['round']}: robots {', '.join(map(str, r['group']))}",
                dict(r),
            )
            for r in data.metrics.get("rounds") or []
        ]
    else:
        links = [
            (c["from"], c["to"], str(c.get("status", "rejected")))
            for c in graph.get("candidates", [])
        ]
        result.events = [_gauge_event(e, times) for e in graph.get("gauge_events", [])]
    for start, end, status in links:
        a, b = (int(start[0]), int(start[1])), (int(end[0]), int(end[1]))
        if a in times and b in times:
            result.links.append(Link((a, b), (times[a], times[b]), status))
    return result
