"""``report.html``: the page a person opens first after a run.

A single self-contained file: the trajectory plot (embedded as base64 PNG), the per-agent
table, the accuracy numbers and the effective configuration, all read from the run folder.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any

_STYLE = """
body { font-family: sans-serif; margin: 2em; max-width: 60em; }
table { border-collapse: collapse; margin: 1em 0; }
td, th { border: 1px solid #ccc; padding: 0.3em 0.7em; text-align: right; }
th { background: #f0f0f0; }
pre { background: #f8f8f8; padding: 1em; overflow-x: auto; }
"""


def _table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "<p>none</p>"
    head = "".join(f"<th>{html.escape(str(k))}</th>" for k in rows[0])
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(_fmt(v))}</td>" for v in row.values()) + "</tr>"
        for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(value: Any) -> str:
    return f"{value:.4f}" if isinstance(value, float) else str(value)


def write_report(run_dir: Path, agent_rows: list[dict[str, Any]],
                 accuracy_rows: list[dict[str, Any]], notes: list[str]) -> Path:
    """Write ``run_dir/report.html`` from the run's tables and files; returns its path."""
    parts = [f"<html><head><meta charset='utf-8'><title>como3r run</title>"
             f"<style>{_STYLE}</style></head><body><h1>como3r run</h1>"]
    plot = run_dir / "trajectories.png"
    if plot.is_file():
        data = base64.b64encode(plot.read_bytes()).decode("ascii")
        parts.append(f"<img alt='trajectories' src='data:image/png;base64,{data}' width='640'>")
    parts.append("<h2>Agents</h2>" + _table(agent_rows))
    if accuracy_rows:
        parts.append("<h2>ATE RMSE [m] (Sim(3)-aligned)</h2>" + _table(accuracy_rows))
    parts.extend(f"<p>{html.escape(line)}</p>" for line in notes)
    metrics = run_dir / "metrics.json"
    if metrics.is_file():
        prior = json.loads(metrics.read_text()).get("prior", {})
        parts.append("<h2>Prior</h2><pre>" + html.escape(json.dumps(prior, indent=2)) + "</pre>")
    config = run_dir / "config.yaml"
    if config.is_file():
        parts.append("<h2>Configuration</h2><pre>" + html.escape(config.read_text()) + "</pre>")
    parts.append("</body></html>")
    out = run_dir / "report.html"
    out.write_text("\n".join(parts))
    return out
