"""Trajectory figures: top view of estimates against ground truth, and ATE over time.

Rendered with matplotlib's Agg canvas directly (no pyplot), so plotting never touches a
display, a global figure registry or the process-wide backend. Figure builders return the
:class:`~matplotlib.figure.Figure` (what is drawn can be inspected: its lines, colours and
styles); :func:`png_bytes` and :func:`save_png` turn one into an image.

Styles are fixed so every figure reads the same way: each agent has its colour
(:func:`agent_colour`), an estimate is a solid line in that colour, ground truth is a dashed
grey line (:data:`GT_STYLE`) drawn underneath.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

AXIS_NAMES = ("x", "y", "z")

#: ground truth: dashed, grey, beneath the estimates
GT_STYLE: dict[str, Any] = {
    "color": "0.55",
    "linestyle": (0, (5, 3)),
    "linewidth": 1.4,
    "zorder": 1,
}
#: an estimate: solid, in its agent's colour (``color`` is added per agent)
EST_STYLE: dict[str, Any] = {"linestyle": "-", "linewidth": 1.8, "zorder": 2}


def agent_colour(agent: int) -> str:
    """The colour of ``agent`` in every figure (matplotlib's tab10 cycle)."""
    return f"C{agent % 10}"


def new_figure(width: float = 7.0, height: float = 5.5, dpi: int = 110) -> Figure:
    """A figure on its own Agg canvas (not registered with pyplot)."""
    figure = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(figure)
    return figure


def png_bytes(figure: Figure) -> bytes:
    """The figure as PNG file contents."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def save_png(figure: Figure, path: Path) -> None:
    """Write the figure to ``path`` as PNG."""
    figure.savefig(path, format="png")


def plane_axes(positions: Sequence[np.ndarray]) -> tuple[int, int]:
    """The two world axes along which the positions spread most, in index order.

    For a camera moving over the ground in a y-down frame this is the top view (x, z).

    Args:
        positions: per agent ``(N_a, 3)`` positions (ground truth where there is some).
    """
    present = [p for p in positions if len(p)]
    if not present:
        return 0, 2
    spread = np.ptp(np.concatenate(present, axis=0), axis=0)
    # Ties prefer x, then z, then y: the top view of a y-down camera frame.
    order = sorted(range(3), key=lambda i: (-spread[i], (0, 2, 1).index(i)))
    first, second = sorted(order[:2])
    return first, second


def draw_trajectories(
    ax: Axes,
    est_positions: Sequence[np.ndarray],
    gt_positions: Sequence[np.ndarray | None] | None = None,
    axes: tuple[int, int] | None = None,
) -> tuple[int, int]:
    """Top view of every agent: estimate solid in its colour, ground truth dashed grey.

    Args:
        ax: where to draw.
        est_positions: per agent ``(N_a, 3)`` estimated camera centres, already in the
            frame of the ground truth when there is some [m].
        gt_positions: per agent ``(M_a, 3)`` ground-truth camera centres, or None for an
            agent (or all agents) without.
        axes: the two world axes to plot; by default :func:`plane_axes` of the ground truth
            (of the estimates where there is none).

    Returns:
        The indices of the two plotted world axes.
    """
    gts = list(gt_positions) if gt_positions is not None else [None] * len(est_positions)
    if axes is None:
        known = [g for g in gts if g is not None]
        axes = plane_axes(known if known else est_positions)
    u, v = axes
    gt_labelled = False
    for agent, (est, gt) in enumerate(zip(est_positions, gts)):
        if gt is not None and len(gt):
            ax.plot(gt[:, u], gt[:, v], **GT_STYLE, label=None if gt_labelled else "ground truth")
            gt_labelled = True
        if len(est):
            colour = agent_colour(agent)
            ax.plot(est[:, u], est[:, v], color=colour, **EST_STYLE, label=f"agent {agent}")
            ax.plot(est[:1, u], est[:1, v], "o", color=colour, markersize=5, zorder=3)
    ax.set_xlabel(f"{AXIS_NAMES[u]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[v]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    return u, v


def trajectory_figure(
    est_positions: Sequence[np.ndarray],
    gt_positions: Sequence[np.ndarray | None] | None = None,
    title: str = "Trajectories (top view)",
) -> tuple[Figure, tuple[int, int]]:
    """A figure with :func:`draw_trajectories` and the two world axes it shows."""
    figure = new_figure(7.0, 6.0)
    ax = figure.add_subplot(1, 1, 1)
    axes = draw_trajectories(ax, est_positions, gt_positions)
    ax.set_title(title)
    figure.tight_layout()
    return figure, axes


def plot_trajectories(
    path: Path,
    gt_positions: Sequence[np.ndarray],
    est_positions: Sequence[np.ndarray],
    title: str = "Trajectories (estimate Sim(3)-aligned per agent)",
) -> tuple[int, int]:
    """Write ``trajectories.png``: estimates solid per agent, ground truth dashed grey.

    Args:
        path: the PNG file to write.
        gt_positions: per agent ``(N_a, 3)`` ground-truth camera centres [m].
        est_positions: per agent ``(M_a, 3)`` estimated camera centres already aligned to
            the ground-truth frame [m].
        title: the figure title.

    Returns:
        The indices of the two plotted world axes.
    """
    figure, axes = trajectory_figure(est_positions, gt_positions, title)
    save_png(figure, path)
    return axes


def ate_figure(series: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> Figure:
    """Absolute trajectory error over time, one line per agent.

    Args:
        series: ``(agent, timestamps (N,) [s], errors (N,) [m])`` per agent with ground
            truth; errors after the agent's own Sim(3) alignment.
    """
    figure = new_figure(7.0, 3.6)
    ax = figure.add_subplot(1, 1, 1)
    for agent, stamps, errors in series:
        rmse = float(np.sqrt(np.mean(np.square(errors)))) if len(errors) else float("nan")
        ax.plot(
            stamps,
            errors,
            color=agent_colour(agent),
            **EST_STYLE,
            label=f"agent {agent} (RMSE {rmse:.3g} m)",
        )
    ax.set_xlabel("timestamp [s]")
    ax.set_ylabel("ATE [m]")
    ax.set_ylim(bottom=0.0)
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small")
    ax.set_title("Absolute trajectory error over time (Sim(3)-aligned per agent)")
    figure.tight_layout()
    return figure
