"""Writing a run's output folder (manual: docs/outputs.md, "Run output").

``config.yaml``, ``trajectories/agent_<a>.txt`` (every tracked frame), ``keyframes/agent_<a>.txt``
and ``keyframes/agent_<a>/`` (:mod:`como3r.io.keyframe_data`),
``map.ply`` (fused coloured cloud with agent ids), ``graph.json`` and ``metrics.json``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.config import Config, dump_config
from como3r.coordination.coordinator import Coordinator
from como3r.frontend.agent import AgentFrontend
from como3r.frontend.timing import with_remainder
from como3r.io.keyframe_data import write_keyframe_data
from como3r.io.tum import write_tum
from como3r.progress import PhaseCallback, report_phase
from como3r.runtime.map_points import fused_map, fused_points, map_voxel, write_map

logger = logging.getLogger(__name__)

#: ``map.ply``'s points (map_points.py) stay importable from here
__all__ = [
    "MIN_TRACKED_FRACTION",
    "SIMULATED_NOTE",
    "agent_row",
    "bandwidth",
    "evaluate_and_finish",
    "frontend_metrics",
    "fused_map",
    "fused_points",
    "graph_document",
    "in_final_folder",
    "keyframe_bandwidth",
    "map_voxel",
    "tracking_warnings",
    "write_config",
    "write_json",
    "write_map",
    "write_run_files",
    "write_trajectories",
]

#: the first note of every run on the simulated prior (CLI summary, report.html)
SIMULATED_NOTE = (
    "prior: simulated (made from the input's ground-truth depth as a stand-in "
    "for MASt3R): these results do not measure MASt3R"
)


def write_trajectories(out: Path, frontends: Sequence[AgentFrontend]) -> None:
    """All-frame and keyframe TUM trajectories per agent."""
    for fe in frontends:
        _, stamps, T_WC = fe.trajectory()
        write_tum(out / "trajectories" / f"agent_{fe.agent}.txt", stamps, T_WC)
        _, kf_stamps, kf_T_WC = fe.keyframe_trajectory()
        write_tum(out / "keyframes" / f"agent_{fe.agent}.txt", kf_stamps, kf_T_WC)


def graph_document(
    frontends: Sequence[AgentFrontend], coordinator: Coordinator | None = None
) -> dict[str, Any]:
    """The keyframe graph as JSON-ready data.

    Keyframes carry the agents' final poses. Edges are the coordinator's global graph
    (sequential and verified inter-agent edges with their match fractions ``nu_i``, ``nu_j``
    and retrieval similarity) plus the intra-agent loop edges that stay in the agents'
    local graphs (C-Sec. A.3); ``candidates`` lists every verified cross-agent candidate,
    accepted or not (``nu_i`` and ``covisible_ratio`` null where its first direction failed
    and the second was not matched), and ``components`` the gauge components.
    """
    keyframes, local_loops = [], []
    for fe in frontends:
        for kf in fe.keyframes:
            keyframes.append(
                {
                    "agent": fe.agent,
                    "keyframe": kf.kf_id,
                    "frame": kf.frame_index,
                    "timestamp": kf.timestamp,
                    "T_WC": kf.T_WC.tolist(),
                }
            )
        local_loops.extend(
            {
                "type": e.kind,
                "from": [fe.agent, e.i],
                "to": [fe.agent, e.j],
                "match_fraction": e.matches.match_fraction,
            }
            for e in fe.edges
            if e.kind == "loop" or coordinator is None
        )
    document: dict[str, Any] = {
        "keyframes": keyframes,
        "edges": local_loops,
        "components": [[fe.agent] for fe in frontends],
    }
    if coordinator is not None:
        coordinated = coordinator.graph_document()
        document["edges"] = coordinated["edges"] + local_loops
        for key in ("candidates", "gauge_events", "components"):
            document[key] = coordinated[key]
    return document


def write_json(path: Path, document: dict[str, Any]) -> None:
    """Write pretty JSON (numbers, strings, lists, dicts only)."""
    path.write_text(json.dumps(document, indent=2, default=_jsonable))


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, (np.ndarray, torch.Tensor)):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def frontend_metrics(fe: AgentFrontend, seconds: float) -> dict[str, Any]:
    """Per-agent counters and rates."""
    stats = asdict(fe.stats)
    stats["tracked_fraction"] = fe.stats.tracked / fe.stats.frames if fe.stats.frames else None
    stats["seconds"] = seconds
    stats["stage_seconds"] = with_remainder(fe.stats.stage_seconds, seconds)
    stats["fps"] = fe.stats.frames / seconds if seconds > 0 else None
    return stats


#: an agent tracked on fewer than this share of its processed frames is reported loudly
MIN_TRACKED_FRACTION = 0.95


def tracking_warnings(results: Sequence[Any]) -> list[str]:
    """One warning per agent tracked on fewer than :data:`MIN_TRACKED_FRACTION` of its
    processed frames, naming the agent and its lost frames (also logged as warnings).

    Args:
        results: front-ends or agent results (``agent``, ``stats``), in agent order.
    """
    warnings = []
    for result in results:
        stats = result.stats
        if stats.frames == 0 or stats.tracked >= MIN_TRACKED_FRACTION * stats.frames:
            continue
        lost = stats.lost_frames
        shown = ", ".join(str(f) for f in lost[:20]) + (", ..." if len(lost) > 20 else "")
        text = (
            f"agent {result.agent} was tracked on {stats.tracked} of "
            f"{stats.frames} processed frames ({100.0 * stats.tracked / stats.frames:.0f} %); "
            f"{stats.relocalized} relocalized, lost frames: {shown or 'none'}"
        )
        logger.warning(text)  # the log line has its own WARNING level
        warnings.append(f"warning: {text}")
    return warnings


def bandwidth(
    sent: Mapping[str, int],
    keyframes: int,
    image_shape: tuple[int, int],
    by_part: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """What one agent (or robot) sent, per keyframe, against the raw bytes of an image.

    Args:
        sent: bytes sent per message type, as they went on the wire.
        keyframes: its keyframes.
        image_shape: ``(H, W)`` of its images at network resolution (``input.long_side``),
            whose raw RGB bytes (``3 H W``) are the yardstick.
        by_part: mean bytes per keyframe message of each of its parts
            (:mod:`como3r.transport.keyframe_bytes`), where they were measured.

    Returns:
        ``metrics.json``'s ``bandwidth`` entry: totals, bytes per keyframe (all, per
        message type and, given ``by_part``, per part of the keyframe message) and their
        ratio to the raw image bytes (None without keyframes).
    """
    image = 3 * int(image_shape[0]) * int(image_shape[1])
    total = int(sum(sent.values()))
    per_keyframe = total / keyframes if keyframes else None
    return {
        "keyframes": keyframes,
        "bytes_sent": total,
        "bytes_per_keyframe": per_keyframe,
        "image_bytes": image,
        "per_keyframe_over_image": per_keyframe / image if per_keyframe else None,
        "bytes_per_keyframe_by_type": (
            {k: v / keyframes for k, v in sorted(sent.items())} if keyframes else {}
        ),
        "keyframe_message_bytes_by_part": dict(by_part) if by_part else None,
    }


def keyframe_bandwidth(
    runtime: Mapping[str, Any] | None, results: Sequence[Any]
) -> list[dict[str, Any]] | None:
    """Per agent of a multi-process run, :func:`bandwidth` of what it sent the coordinator
    (None without a ``runtime`` section: nothing travelled)."""
    if not runtime:
        return None
    by_agent: dict[int, Any] = {}
    for result in results:
        by_agent.setdefault(result.agent, result)
    rows = []
    for entry in runtime["agents"]:
        result = by_agent.get(entry["agent"])
        keyframes = list(result.keyframes) if result is not None else []
        shape = tuple(keyframes[0].colors.shape[:2]) if keyframes else (0, 0)
        rows.append(
            {
                "agent": entry["agent"],
                **bandwidth(
                    entry["bytes_from_agent"],
                    entry["keyframes_received"],
                    shape,
                    entry.get("keyframe_bytes_by_part"),
                ),
                "send_backlog": entry.get("send_backlog"),
            }
        )
    return rows


def write_config(out: Path, config: Config) -> None:
    """The full effective configuration."""
    dump_config(config, out / "config.yaml")


def in_final_folder(text: str, staging: Path) -> str:
    """``text`` naming the run folder the user will have instead of the staging folder
    (``DIR.partial``, :func:`~como3r.io.output.atomic_output_dir`) renamed into it."""
    return text.replace(str(staging), str(staging.with_name(staging.name.removesuffix(".partial"))))


def evaluate_and_finish(
    staging: Path,
    summary: Any,
    metrics: dict[str, Any],
    agents: Sequence[Any],
    components: Sequence[Sequence[int]],
    results: Sequence[Any],
    coordinator: Any,
    config: Config,
    progress: PhaseCallback | None = None,
) -> None:
    """Evaluate against ground truth (where every agent has it), then write
    ``metrics.json`` and ``report.html``; adds what the user should know to ``summary.notes``.

    Args:
        staging: the run folder being written.
        summary: the run's summary (``agents``, ``notes``, ``evaluation`` are filled in).
        metrics: the metrics document; gains ``ate`` and ``map_accuracy``.
        agents: the agent inputs (``root``, ``groundtruth``, depth and calibration);
            empty where this process has none (a networked coordinator).
        components: gauge components: merged ATE only within each.
        results: front-ends or agent results (``agent``, ``keyframes``), in agent order.
        coordinator: the run's coordinator (``pre_refinement`` keyframes).
        config: effective configuration.
        progress: called as the evaluation and the report start.
    """
    from como3r.errors import InputError
    from como3r.evaluation.html import write_report
    from como3r.evaluation.report import evaluate_run

    if metrics["prior"].get("name") == "SimulatedPrior":
        summary.notes.insert(0, SIMULATED_NOTE)
    metrics["ate"] = None
    if agents and all(a.groundtruth is not None for a in agents):
        report_phase(progress, "evaluation", "ATE and RPE through evo", 0, 2)
        try:
            evaluation = evaluate_run(
                staging,
                [a.root for a in agents],
                staging,
                components=[list(c) for c in components],
                gt_format=config.input.format,
                fps=config.input.frame_rate_hz,
            )
        except InputError as exc:  # e.g. too few tracked frames: the run itself stands
            summary.notes.append(f"ATE not computed: {in_final_folder(str(exc), staging)}")
        else:
            metrics["ate"] = evaluation.to_json()
            summary.evaluation = evaluation
    else:
        summary.notes.append("no ground truth for every agent: ATE not computed")
    if len(components) > 1:
        summary.notes.append(
            f"agents form {len(components)} separate gauge components "
            f"{[list(c) for c in components]}: no merged ATE across them"
        )
    summary.notes.extend(tracking_warnings(results))
    report_phase(progress, "evaluation", "map accuracy", 1, 2)
    metrics["map_accuracy"] = _map_accuracy(
        summary, agents, components, results, coordinator, config
    )
    metrics["bandwidth"] = keyframe_bandwidth(metrics.get("runtime"), results)
    write_json(staging / "metrics.json", metrics)
    truth = [a.groundtruth for a in agents] if summary.evaluation is not None else None
    report_phase(progress, "report", "report.html")
    write_report(staging, summary.notes, truth)


def write_run_files(
    staging: Path,
    agents: Sequence[Any],
    coordinator: Any,
    config: Config,
    prior_description: dict[str, Any],
    seconds: Sequence[float],
    progress: PhaseCallback | None = None,
) -> tuple[dict[str, Any], list[list[int]]]:
    """Write config, trajectories, keyframe data, map and graph of a run; returns the base
    metrics document and the gauge components.

    Args:
        agents: front-ends or agent results (``agent``, ``keyframes``, ``edges``, ``stats``,
            ``trajectory()``, ``keyframe_trajectory()``), in agent order.
        coordinator: the run's coordinator.
        config: effective configuration.
        prior_description: ``prior.describe()``.
        seconds: processing time per agent.
        progress: called as each group of files starts.
    """
    report_phase(progress, "outputs", "config.yaml, trajectories", 0, 3)
    write_config(staging, config)
    write_trajectories(staging, agents)
    report_phase(progress, "outputs", "keyframe data", 1, 3)
    write_keyframe_data(staging, agents)  # what `como3r export` reads
    report_phase(progress, "outputs", "map.ply, graph.json", 2, 3)
    written = write_map(staging, agents, config)
    components = coordinator.components()
    write_json(staging / "graph.json", graph_document(agents, coordinator))
    metrics = {
        "prior": prior_description,
        "agents": [frontend_metrics(a, s) for a, s in zip(agents, seconds)],
        "coordinator": coordinator.metrics(),
        "components": components,
        "map_points": written["points"],
        "map": written,
    }
    return metrics, components


def agent_row(agent: Any, seconds: float) -> dict[str, Any]:
    """One agent's line of the final summary table."""
    stats = agent.stats
    return {
        "agent": agent.agent,
        "frames": stats.frames,
        "tracked": stats.tracked,
        "lost": stats.lost,
        "keyframes": len(agent.keyframes),
        "fps": stats.frames / seconds if seconds > 0 else 0.0,
    }


def _map_accuracy(
    summary: Any,
    agents: Sequence[Any],
    components: Sequence[Sequence[int]],
    results: Sequence[Any],
    coordinator: Any,
    config: Config,
) -> list[dict[str, Any]] | None:
    """Reconstruction metrics of each component's fused map (C-Sec. B.5) after its trajectory
    alignment: the final map and, where the depth refinement ran, the map before it."""
    from como3r.errors import InputError
    from como3r.evaluation.reconstruction import evaluate_maps

    if summary.evaluation is None:
        return None
    if not all(a.has_depth and a.calib is not None for a in agents):
        summary.notes.append(
            "no ground-truth depth and calibration for every agent: map accuracy not computed"
        )
        return None
    min_confidence = config.visualization.map_min_confidence
    entries = []
    for component in components:
        alignment = summary.evaluation.alignment_of(component)
        if alignment is None:
            continue
        clouds = {
            "final": fused_points({a: results[a].keyframes for a in component}, min_confidence)
        }
        if all(a in coordinator.pre_refinement for a in component):
            clouds["before_refinement"] = fused_points(
                {a: coordinator.pre_refinement[a] for a in component}, min_confidence
            )
        try:
            scores = evaluate_maps([agents[a] for a in component], clouds, alignment)
        except InputError as exc:
            summary.notes.append(f"map accuracy of agents {list(component)} not computed: {exc}")
            continue
        entries.append(
            {"agents": list(component), **{name: m.to_json() for name, m in scores.items()}}
        )
        summary.notes.append(_map_note(component, scores))
    return entries


def _map_note(component: Sequence[int], scores: dict[str, Any]) -> str:
    from como3r.evaluation.reconstruction import MAP_THRESHOLD_RATIO

    final = scores["final"]
    text = (
        f"map of agents {list(component)}: accuracy {final.accuracy:.3f} m, completeness "
        f"{final.completeness:.3f} m, F-score@{final.threshold:.3g} m "
        f"({100 * MAP_THRESHOLD_RATIO:g} % of the median depth) {final.fscore:.3f}"
    )
    before = scores.get("before_refinement")
    if before is not None:
        text += (
            f" (before depth refinement: accuracy {before.accuracy:.3f} m, F-score "
            f"{before.fscore:.3f})"
        )
    return text
