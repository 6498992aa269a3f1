"""The sections of ``report.html`` (:mod:`.html`) on how the run went: where the time and
the bytes went, and when the agents merged, with :mod:`.plot_run`'s figures."""

from __future__ import annotations

import html
from collections.abc import Sequence
from typing import Any

from como3r.evaluation.html_parts import fmt, fmt_bytes, image, missing, table
from como3r.evaluation.plot_run import (
    stacked_bar_figure,
    stage_order,
    timeline_figure,
    traffic_columns,
)
from como3r.evaluation.report_data import (
    MergeEvent,
    RunData,
    agent_rows,
    stage_seconds,
    timeline,
    traffic,
)


def timing_section(data: RunData) -> str:
    """Wall seconds per stage of each agent and the coordinator (a robot's prior, in the
    decentralized mode): a table and a stacked bar chart."""
    columns = stage_seconds(data)
    if not columns:
        return missing("This run recorded no per-stage times.")
    stages = stage_order(columns)
    rows = [{"stage": s, **{f"{c} [s]": columns[c].get(s) for c in columns}} for s in stages]
    rows.append({"stage": "total", **{f"{c} [s]": sum(columns[c].values()) for c in columns}})
    text, caption = (
        "",
        (
            "Wall seconds per stage of each agent's front-end and of the "
            "coordinator (<i>other</i>: the rest of the agent's time)."
        ),
    )
    if data.decentralized:
        text = missing(
            "The decentralized mode records only the prior's encoder and decoder "
            f"time per robot; the whole mission took "
            f"{fmt(data.metrics.get('seconds'))} s."
        )
        caption = "Wall seconds each robot spent in the prior's encoder and decoder."
    return (
        text
        + table(rows)
        + image(
            lambda: stacked_bar_figure(
                columns, "wall time [s]", "Time per stage", total_label=lambda v: f"{v:.3g} s"
            ),
            "timing",
            caption,
        )
    )


def bandwidth_section(data: RunData) -> str:
    """Bytes each agent sent and received, per keyframe and by message type; a sentence
    where the run sent none (one process) or did not count them."""
    found = traffic(data)
    if found is None and data.runtime_mode == "single-process" and data.metrics:
        return missing(
            "Single-process run: the agents and the coordinator shared memory and "
            "sent no messages, so there is no bandwidth to report (run without "
            "--single-process to measure it)."
        )
    if found is None:
        return missing("This run recorded no message bytes.")
    rows, keyframe_counts = [], {r["agent"]: r.get("keyframes") for r in agent_rows(data)}
    for agent, t in found.items():
        sent, received = sum(t.sent.values()), sum(t.received.values())
        keyframes = keyframe_counts.get(agent)
        rows.append(
            {
                "agent": agent,
                "sent": fmt_bytes(sent),
                "received": fmt_bytes(received),
                "sent per keyframe": fmt_bytes(sent / keyframes) if keyframes else None,
                "largest sent type": max(t.sent, key=t.sent.get) if t.sent else None,
            }
        )
    by_type = (data.metrics.get("bytes") or data.metrics.get("runtime") or {}).get(
        "bytes_by_type"
    ) or {}
    types = (
        table(
            [
                {"message type": k, "bytes": fmt_bytes(v)}
                for k, v in sorted(by_type.items(), key=lambda kv: -kv[1])
            ]
        )
        if by_type
        else ""
    )
    return (
        table(rows)
        + image(
            lambda: stacked_bar_figure(
                traffic_columns(found),
                "MB",
                "Bytes per agent and message type",
                scale=1e6,
                total_label=fmt_bytes,
            ),
            "bandwidth",
            "Encoded message bytes each agent sent and received, by message type.",
        )
        + types
    )


def _event_rows(data: RunData, events: Sequence[MergeEvent]) -> list[dict[str, Any]]:
    rows = []
    for i, event in enumerate(events, 1):
        d = event.details
        if data.decentralized:
            rows.append(
                {
                    "#": i,
                    "time [s]": event.time,
                    "round": d.get("round"),
                    "robots": ", ".join(map(str, d.get("group", []))),
                }
            )
            continue
        edges = "; ".join(f"{a[0]}:{a[1]} ↔ {b[0]}:{b[1]}" for a, b in d.get("edges", []))
        rows.append(
            {
                "#": i,
                "time [s]": event.time,
                "after keyframes": d.get("keyframes"),
                "moved agents": ", ".join(map(str, d.get("moved_agents", []))),
                "into component": d.get("anchor_component"),
                "edges (agent:kf)": edges,
                "method": d.get("method"),
                "correspondences": d.get("correspondences"),
                "RMSE": d.get("rmse"),
                "scale": d.get("scale"),
                "focal factor": d.get("focal_factor"),
            }
        )
    return rows


def merges_section(data: RunData) -> str:
    """When the agents' maps joined: the cross-agent links on a timeline and the gauge
    synchronizations (rendezvous rounds, decentralized) in a table."""
    if len(data.tracks) < 2:
        return missing("One agent: there is nothing to merge.")
    line = timeline(data)
    if not line.keyframes:
        return missing("graph.json is missing: no keyframes to place on a timeline.")
    counts: dict[str, int] = {}
    for link in line.links:
        counts[link.status] = counts.get(link.status, 0) + 1
    what = "loop closures" if data.decentralized else "verified candidates"
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) or "none"
    kind = "rendezvous rounds" if data.decentralized else "gauge synchronizations"
    text = (
        f"<p>Cross-agent {what}: {html.escape(summary)}. "
        f"{len(line.events)} {kind} (dotted lines, numbered as in the table).</p>"
    )
    caption = (
        "Each tick is a keyframe at its timestamp; a line joins the two keyframes of a "
        "cross-agent link, green where it was admitted, red where it was rejected."
    )
    text += image(
        lambda: timeline_figure(line, [t.agent for t in data.tracks]), "timeline", caption
    )
    if line.events:
        text += table(_event_rows(data, line.events))
    elif not data.decentralized:
        text += missing("No gauge synchronization: the agents never joined one frame.")
    return text
