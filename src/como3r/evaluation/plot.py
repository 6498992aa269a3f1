"""Top-view plot of estimated (Sim(3)-aligned) and ground-truth trajectories of all agents.

Rendered with matplotlib's Agg canvas directly (no pyplot), so plotting never touches a
display, a global figure registry or the process-wide backend.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

AXIS_NAMES = ("x", "y", "z")


def plane_axes(gt_positions: Sequence[np.ndarray]) -> tuple[int, int]:
    """The two world axes along which the ground truth spreads most, in index order.

    For a camera moving over the ground in a y-down frame this is the top view (x, z).

    Args:
        gt_positions: per agent ``(N_a, 3)`` ground-truth positions.
    """
    stacked = np.concatenate([p for p in gt_positions if len(p)], axis=0)
    spread = np.ptp(stacked, axis=0)
    # Ties prefer x, then z, then y: the top view of a y-down camera frame.
    order = sorted(range(3), key=lambda i: (-spread[i], (0, 2, 1).index(i)))
    first, second = sorted(order[:2])
    return first, second


def plot_trajectories(
    path: Path,
    gt_positions: Sequence[np.ndarray],
    est_positions: Sequence[np.ndarray],
    title: str = "Trajectories (estimate Sim(3)-aligned per agent)",
) -> tuple[int, int]:
    """Write a PNG with one colour per agent: ground truth solid, estimate dashed.

    Args:
        path: the PNG file to write.
        gt_positions: per agent ``(N_a, 3)`` ground-truth camera centres [m].
        est_positions: per agent ``(M_a, 3)`` estimated camera centres already aligned to
            the ground-truth frame [m].
        title: the figure title.

    Returns:
        The indices of the two plotted world axes.
    """
    u, v = plane_axes(gt_positions)
    figure = Figure(figsize=(7.0, 6.0), dpi=110)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot(1, 1, 1)
    colours = [f"C{a % 10}" for a in range(len(gt_positions))]
    for agent, (gt, est, colour) in enumerate(zip(gt_positions, est_positions, colours)):
        ax.plot(gt[:, u], gt[:, v], "-", color=colour, linewidth=1.6, label=f"agent {agent} GT")
        ax.plot(est[:, u], est[:, v], "--", color=colour, linewidth=1.2,
                label=f"agent {agent} estimate")
    ax.set_xlabel(f"{AXIS_NAMES[u]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[v]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="small")
    ax.set_title(title)
    figure.tight_layout()
    figure.savefig(path, format="png")
    return u, v
