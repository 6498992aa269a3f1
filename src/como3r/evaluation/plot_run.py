"""Figures of how a run spent its time and bandwidth and when its agents merged.

Built on :mod:`como3r.evaluation.plot` (Agg canvas, agent colours); each builder returns
its :class:`~matplotlib.figure.Figure`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure

from como3r.evaluation.plot import agent_colour, new_figure
from como3r.evaluation.report_data import Timeline, Traffic

#: colour of a cross-agent link by its status (centralized candidates, decentralized loops)
LINK_COLOURS = {
    "admitted": "tab:green",
    "accepted": "tab:green",
    "pending": "tab:orange",
    "inconsistent": "tab:purple",
    "rejected": "tab:red",
}
#: more stacked parts than this are drawn as "other"
MAX_PARTS = 12


def stage_order(columns: Mapping[str, Mapping[str, float]]) -> list[str]:
    """Every stage of any column, largest total first, ``other`` last."""
    totals: dict[str, float] = {}
    for stages in columns.values():
        for stage, seconds in stages.items():
            totals[stage] = totals.get(stage, 0.0) + float(seconds)
    return sorted(totals, key=lambda s: (s == "other", -totals[s], s))


def stacked_bar_figure(
    columns: Mapping[str, Mapping[str, float]],
    unit: str,
    title: str,
    scale: float = 1.0,
    total_label: Callable[[float], str] | None = None,
) -> Figure:
    """Horizontal stacked bars, one per column, one colour per part (consistent across bars).

    Args:
        columns: bar name -> part name -> value.
        unit: axis label of the values (after ``scale``).
        title: the figure title.
        scale: the values are divided by this (e.g. 1e6 for MB).
        total_label: writes each bar's total (unscaled) at its end, so short bars stay
            readable.
    """
    parts = stage_order(columns)
    if len(parts) > MAX_PARTS:
        kept, rest = parts[: MAX_PARTS - 1], set(parts[MAX_PARTS - 1 :])
        columns = {
            name: {
                **{p: v for p, v in c.items() if p not in rest},
                "other": sum(v for p, v in c.items() if p in rest),
            }
            for name, c in columns.items()
        }
        parts = kept + ["other"]
    names = list(columns)
    figure = new_figure(7.5, 1.4 + 0.45 * len(names))
    ax = figure.add_subplot(1, 1, 1)
    left = np.zeros(len(names))
    palette = colormaps["tab20"]  # dark shades first, then the light ones
    colours = [palette((2 * i) % 20 + (2 * i) // 20) for i in range(len(parts))]
    for part, colour in zip(parts, colours):
        widths = np.array([float(columns[n].get(part, 0.0)) / scale for n in names])
        ax.barh(names, widths, left=left, color=colour, label=part, height=0.6)
        left += widths
    if total_label is not None:
        for y, (name, width) in enumerate(zip(names, left)):
            ax.annotate(
                " " + total_label(sum(columns[name].values())),
                (width, y),
                va="center",
                fontsize="small",
            )
        ax.set_xlim(right=1.15 * max(left.max(), 1e-9))
    ax.invert_yaxis()
    ax.set_xlabel(unit)
    ax.set_title(title)
    ax.grid(True, axis="x", linewidth=0.4, alpha=0.5)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    figure.tight_layout()
    return figure


def traffic_columns(traffic: Mapping[int, Traffic]) -> dict[str, dict[str, float]]:
    """Bars of :func:`stacked_bar_figure`: per agent, bytes sent and received by type."""
    columns: dict[str, dict[str, float]] = {}
    for agent, t in traffic.items():
        columns[f"agent {agent} sent"] = {k: float(v) for k, v in t.sent.items()}
        columns[f"agent {agent} received"] = {k: float(v) for k, v in t.received.items()}
    return columns


def timeline_figure(line: Timeline, agents: Sequence[int]) -> Figure:
    """Keyframes of every agent on a time axis, cross-agent links between the agents' rows
    coloured by status, and merge events as vertical lines.

    Args:
        line: what to draw (:func:`como3r.evaluation.report_data.timeline`).
        agents: the agents, one row each, top to bottom.
    """
    figure = new_figure(7.5, 1.8 + 0.6 * len(agents))
    ax = figure.add_subplot(1, 1, 1)
    row = {agent: i for i, agent in enumerate(agents)}
    for agent in agents:
        stamps = line.keyframes.get(agent, np.zeros(0))
        ax.plot(
            stamps,
            np.full(len(stamps), row[agent]),
            "|",
            color=agent_colour(agent),
            markersize=12,
            markeredgewidth=2,
            zorder=3,
        )
    shown: set[str] = set()
    for link in line.links:
        (a, _), (b, _) = link.ends
        if a not in row or b not in row:
            continue
        colour = LINK_COLOURS.get(link.status, "0.5")
        good = link.status in ("admitted", "accepted")
        ax.plot(
            link.times,
            (row[a], row[b]),
            "-",
            color=colour,
            zorder=2 if good else 1,
            linewidth=1.6 if good else 0.8,
            alpha=1.0 if good else 0.6,
            label=None if link.status in shown else link.status,
        )
        shown.add(link.status)
    for i, event in enumerate(line.events):
        if not np.isfinite(event.time):
            continue
        ax.axvline(
            event.time,
            color="black",
            linestyle=":",
            linewidth=1.2,
            zorder=0,
            label=None if "merge" in shown else "merge",
        )
        shown.add("merge")
        ax.annotate(
            f"{i + 1}",
            (event.time, 1.0),
            xycoords=ax.get_xaxis_transform(),
            ha="center",
            va="bottom",
            fontsize="small",
            annotation_clip=False,
        )
    ax.set_yticks(range(len(agents)), [f"agent {a}" for a in agents])
    ax.set_ylim(len(agents) - 0.5, -0.5)
    ax.set_xlabel("timestamp [s]")
    ax.set_title("Keyframes, cross-agent links and merges", pad=14)
    ax.grid(True, axis="x", linewidth=0.4, alpha=0.5)
    if shown:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    figure.tight_layout()
    return figure
