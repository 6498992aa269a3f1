"""``report.html``: the page a person opens first after a run.

One self-contained file (images embedded as base64 PNG, no script, no network) read from
the run folder (:mod:`como3r.evaluation.report_data`): a summary and the run's notes, the
trajectories against ground truth, the error over time, a per-agent table, where the time
and the bytes went, when the agents merged, a rendered view of the fused map, and, folded
away in an appendix, the configuration and the prior's constants.

Every section says so in a sentence when the run has nothing to show there (no ground
truth, one agent, a single-process run that sent no messages, no map).
"""

from __future__ import annotations

import html
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from como3r.evaluation.html_parts import (
    STYLE,
    details,
    fmt,
    image,
    missing,
    section,
    table,
)
from como3r.evaluation.html_run import bandwidth_section, merges_section, timing_section
from como3r.evaluation.plot import ate_figure, trajectory_figure
from como3r.evaluation.plot_map import map_figure, sample_map
from como3r.evaluation.report import EvalSummary
from como3r.evaluation.report_data import (
    RunData,
    agent_rows,
    load_run,
)
from como3r.io.tum import Trajectory

logger = logging.getLogger(__name__)

#: ``image`` is html_parts.py's; importable from here as before
__all__ = [
    "REPORT_NAME",
    "SECTIONS",
    "image",
    "render",
    "run_label",
    "write_evaluation_report",
    "write_report",
]

REPORT_NAME = "report.html"
#: the sections of the report, in order: (id, heading)
SECTIONS = (
    ("trajectories", "Trajectories"),
    ("error", "Error over time"),
    ("agents", "Agents"),
    ("timing", "Timing"),
    ("bandwidth", "Bandwidth"),
    ("merges", "Cross-agent merges"),
    ("map", "Map"),
    ("appendix", "Appendix"),
)


# --------------------------------------------------------------------------- sections


def _summary(data: RunData, notes: Sequence[str]) -> str:
    m = data.metrics
    prior = (m.get("prior") or {}).get("name", "unknown")
    facts = [("mode", data.runtime_mode), ("agents", len(data.tracks)), ("prior", prior)]
    frames = [r.get("frames") for r in agent_rows(data) if isinstance(r["agent"], int)]
    if frames and all(f is not None for f in frames):
        facts.append(("frames", sum(frames)))
    components = m.get("components") or m.get("frame_groups")
    if components:
        facts.append(
            ("gauge components", " ".join("{" + ", ".join(map(str, c)) + "}" for c in components))
        )
    merged = (data.ate or {}).get("merged")
    if merged:
        facts.append(("merged ATE RMSE [m]", merged["ate"]["rmse"]))
    if m.get("map_points") is not None:
        facts.append(("map points", m["map_points"]))
    items = "".join(f"<div><b>{html.escape(k)}</b> {html.escape(fmt(v))}</div>" for k, v in facts)
    text = f"<div class='facts'>{items}</div>"
    if notes:
        lines = "".join(
            f"<li class='{'warn' if n.startswith('warning') else ''}'>{html.escape(n)}</li>"
            for n in notes
        )
        text += f"<ul class='notes'>{lines}</ul>"
    toc = " · ".join(f"<a href='#{i}'>{h}</a>" for i, h in SECTIONS)
    return text + f"<nav>{toc}</nav>"


def _trajectories(data: RunData) -> str:
    if not any(len(t.positions) for t in data.tracks):
        return missing("No agent has an estimated trajectory.")
    if data.has_ground_truth:
        est = [t.aligned if t.aligned is not None else t.positions for t in data.tracks]
        caption = (
            "Top view. Estimates solid, one colour per agent (a dot marks the start); "
            "ground truth dashed grey. " + (data.alignment_text or "") + "."
        )
        return image(
            lambda: trajectory_figure(est, [t.gt for t in data.tracks])[0],
            "trajectories",
            html.escape(caption),
        )
    sentence = (
        "No ground truth was given for this run, so the estimates are drawn alone, "
        "in the run's world frame (the first camera's), and no error is computed."
    )
    if data.ate is not None:
        sentence = (
            "The run was evaluated, but its ground truth was not handed to the "
            "report: the estimates are drawn alone, in the run's world frame."
        )
    return missing(sentence) + image(
        lambda: trajectory_figure(
            [t.positions for t in data.tracks],
            None,
            "Estimated trajectories (top view, world frame)",
        )[0],
        "trajectories",
        "Top view of the estimates, one colour per agent.",
    )


def _error(data: RunData) -> str:
    series = [
        (t.agent, t.error_times, t.errors)
        for t in data.tracks
        if t.errors is not None and t.error_times is not None
    ]
    if not series:
        return missing("No ground truth: no error over time.")
    caption = (
        "Distance between each estimated camera centre and its ground truth (nearest "
        "timestamp) after the agent's own Sim(3) alignment; its RMSE is the agent's "
        "ATE in the table below."
    )
    return image(lambda: ate_figure(series), "ATE over time", html.escape(caption))


def _agents(data: RunData) -> str:
    rows = agent_rows(data)
    if not rows:
        return missing("No agents.")
    note = (
        ""
        if data.ate
        else "<p>ATE and RPE need ground truth for every agent; "
        "this run has none, or its evaluation failed (see the notes above).</p>"
    )
    rpe = ""
    if data.ate:
        p = data.ate.get("parameters", {})
        rpe = (
            f"<p class='small'>ATE: RMSE of camera-centre errors after a Sim(3) Umeyama "
            f"alignment per agent (merged rows: one Sim(3) for the group). RPE: between "
            f"associated poses {p.get('rpe_delta', 1)} {p.get('rpe_delta_unit', 'frames')}"
            f" apart. "
            f"Computed with evo {html.escape(str(p.get('evo_version', '')))}.</p>"
        )
    return table(rows) + rpe + note


def _map(data: RunData) -> str:
    path = data.run_dir / "map.ply"
    sample = sample_map(path)
    if sample is None:
        text = missing(
            "No map.ply in this run (or it is empty): nothing to render."
            if not data.decentralized
            else "The decentralized mode writes no fused map."
        )
    else:
        text = image(
            lambda: map_figure(sample, data.tracks),
            "map",
            f"map.ply, {len(sample.xyz):,} of {sample.total:,} points drawn (a fixed "
            f"random subset) in their colours; top-down with the estimated "
            f"trajectories, and oblique. Up is the cameras' mean up direction.",
        )
    rows = []
    for entry in data.metrics.get("map_accuracy") or []:
        for which in ("final", "before_refinement"):
            if which in entry:
                m = entry[which]
                rows.append(
                    {
                        "agents": "+".join(map(str, entry["agents"])),
                        "map": which,
                        "accuracy [m]": m.get("accuracy"),
                        "completeness [m]": m.get("completeness"),
                        "Chamfer [m]": m.get("chamfer"),
                        "F-score": m.get("fscore"),
                        "threshold [m]": m.get("threshold"),
                    }
                )
    return text + (table(rows) if rows else "")


def _appendix(data: RunData) -> str:
    parts = []
    if data.config_text is not None:
        parts.append(
            details("Configuration (config.yaml)", f"<pre>{html.escape(data.config_text)}</pre>")
        )
    prior = data.metrics.get("prior") or {}
    if prior:
        flat = {k: v for k, v in prior.items() if not isinstance(v, dict)}
        nested = "".join(
            f"<h4>{html.escape(k)}</h4>" + table([{"name": n, "value": v} for n, v in v.items()])
            for k, v in prior.items()
            if isinstance(v, dict)
        )
        parts.append(
            details(
                f"Prior: {prior.get('name', '')}",
                table([{"name": k, "value": v} for k, v in flat.items()]) + nested,
            )
        )
    if data.ate:
        parts.append(
            details(
                "Evaluation parameters",
                table([{"name": k, "value": v} for k, v in data.ate.get("parameters", {}).items()]),
            )
        )
    coordinator = data.metrics.get("coordinator") or {}
    counters = {k: v for k, v in coordinator.items() if not isinstance(v, (dict, list))}
    if counters:
        parts.append(
            details(
                "Coordinator counters",
                table([{"name": k, "value": v} for k, v in counters.items()]),
            )
        )
    if coordinator.get("alternation"):
        text = html.escape(json.dumps(coordinator["alternation"], indent=1))
        parts.append(details("Terminal alternation", f"<pre>{text}</pre>"))
    for key, title in (
        ("loops", "Loop closures"),
        ("two_stage", "Two-stage registration"),
        ("table", "Formulations (F-Tables II-III)"),
    ):
        if data.metrics.get(key):
            value = data.metrics[key]
            body = (
                table(value)
                if isinstance(value, list)
                else table([{"name": k, "value": v} for k, v in value.items()])
            )
            parts.append(details(title, body))
    return "".join(parts) or missing("Nothing to add.")


def run_label(run_dir: Path) -> str:
    """The run's name in the report's title: its folder and the one above it
    (``demo_out/run``, not a bare ``run``), without the ``.partial`` of a run still being
    written (:mod:`como3r.io.output`)."""
    parts = Path(run_dir).resolve().parts[-2:]
    return "/".join(p.removesuffix(".partial") for p in parts if p != Path(p).anchor)


def render(data: RunData, notes: Sequence[str] = ()) -> str:
    """The HTML page of a loaded run."""
    name = html.escape(run_label(data.run_dir))
    builders = {
        "trajectories": _trajectories,
        "error": _error,
        "agents": _agents,
        "timing": timing_section,
        "bandwidth": bandwidth_section,
        "merges": merges_section,
        "map": _map,
        "appendix": _appendix,
    }
    body = "".join(section(i, h, builders[i](data)) for i, h in SECTIONS)
    return (
        f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>{name} - como3r report</title><style>{STYLE}</style></head><body>"
        f"<h1>como3r report <span class='name'>{name}</span></h1>"
        f"{_summary(data, notes)}{body}</body></html>\n"
    )


def write_report(
    run_dir: Path,
    notes: Sequence[str] = (),
    ground_truth: Sequence[Trajectory | None] | None = None,
    ate: dict[str, Any] | None = None,
    path: Path | None = None,
) -> Path:
    """Write the report of a run folder; returns its path.

    The page is written beside its place and renamed into it, so an interrupted report
    leaves the previous one, never half of one.

    Args:
        run_dir: the run's output folder (metrics.json, graph.json, trajectories, ...).
        notes: lines for the reader (the run summary's notes and warnings).
        ground_truth: per agent, the ground truth the evaluation used, or None: the
            trajectories and error curves are then drawn without it.
        ate: the evaluation to show (``EvalSummary.to_json()``); None: the run's own.
        path: where to write the page; None: ``run_dir/report.html``.
    """
    run_dir = Path(run_dir)
    page = render(load_run(run_dir, ground_truth, ate), notes)
    out = Path(path) if path is not None else run_dir / REPORT_NAME
    tmp = out.with_name(out.name + ".tmp")
    try:
        tmp.write_text(page, encoding="utf-8")
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    logger.info("wrote %s", out)
    return out


def write_evaluation_report(run_dir: Path, summary: EvalSummary, path: Path | None = None) -> Path:
    """The report of a run folder showing the evaluation ``summary`` of ``como3r eval``
    (which may differ from the run's own: other ground truth, or none at run time) instead
    of the run's; returns its path.

    Args:
        run_dir: the evaluated run folder.
        summary: what :func:`~como3r.evaluation.report.evaluate_run` returned for it.
        path: where to write the page; None: ``run_dir/report.html``.
    """
    truth = ", ".join(str(result.gt_path) for result in summary.agents)
    notes = [f"evaluated by como3r eval against {truth}"]
    # the files the evaluation wrote are the command's output, not the report's
    notes += [note for note in summary.notes if not note.startswith("wrote ")]
    return write_report(run_dir, notes, summary.ground_truth, summary.to_json(), path)
