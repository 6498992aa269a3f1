"""A rendered view of the fused map (``map.ply``): top-down and oblique point splats.

The cloud is subsampled deterministically (a seeded choice of at most
:data:`MAX_MAP_POINTS` points) and drawn with matplotlib in each point's colour, far points
first so near ones cover them. "Up" is the mean of the cameras' up directions (minus their
image y axes): hand-held and robot cameras are held roughly upright, which the run's world
frame (the first camera's) need not be.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.evaluation.plot import agent_colour, new_figure
from como3r.evaluation.report_data import AgentTrack
from como3r.io.ply import iter_ply

logger = logging.getLogger(__name__)

#: points drawn at most
MAX_MAP_POINTS = 50_000
#: the view keeps the points between these percentiles (per screen axis), plus a margin
VIEW_PERCENTILES = (1.0, 99.0)
#: the oblique view: turned this far about the up axis, looking down this steeply [deg]
OBLIQUE_AZIMUTH_DEG, OBLIQUE_ELEVATION_DEG = 35.0, 35.0


@dataclass(frozen=True)
class MapSample:
    """A deterministic subsample of the fused map.

    Attributes:
        xyz: ``(N, 3)`` float64 points in the run's world frame.
        rgb: ``(N, 3)`` uint8 colours.
        total: points in ``map.ply``.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    total: int


#: vertices read at a time
_CHUNK = 1 << 20


def sample_map(path: Path, max_points: int = MAX_MAP_POINTS, seed: int = 0) -> MapSample | None:
    """At most ``max_points`` finite points of ``map.ply``, the same ones every time, in
    file order; None without a readable, non-empty map. Two passes over the file, a chunk
    at a time (a long run's map is never read whole): count the finite points, then take
    the drawn ones."""
    if not path.is_file():
        return None
    try:
        finite = [int(_finite(chunk).sum()) for chunk in iter_ply(path, _CHUNK)]
    except InputError as exc:
        logger.warning("report: %s; the map is not rendered", exc)
        return None
    total_finite = sum(finite)
    if not total_finite:
        return None
    ranks = np.arange(total_finite)  # k-th finite vertex of the file
    if total_finite > max_points:
        ranks = np.sort(np.random.default_rng(seed).choice(total_finite, max_points, replace=False))
    samples, first, total = [], 0, 0
    for chunk, count in zip(iter_ply(path, _CHUNK), finite):
        mine = ranks[(ranks >= first) & (ranks < first + count)] - first
        samples.append(chunk[np.flatnonzero(_finite(chunk))[mine]])
        first, total = first + count, total + len(chunk)
    sample = np.concatenate(samples)
    xyz = np.stack([sample[k] for k in "xyz"], axis=1).astype(np.float64)
    rgb = np.stack([sample[k] for k in ("red", "green", "blue")], axis=1)
    return MapSample(xyz, rgb, total)


def _finite(vertices: np.ndarray) -> np.ndarray:
    """``(N,)`` whether each vertex's position is finite."""
    return np.isfinite(vertices["x"]) & np.isfinite(vertices["y"]) & np.isfinite(vertices["z"])


def up_basis(orientations: Sequence[np.ndarray]) -> np.ndarray:
    """``(3, 3)`` rows: two horizontal axes and "up", right-handed, in the world frame.

    Args:
        orientations: per agent ``(N_a, 4)`` camera orientations (x, y, z, w).
    """
    quats = [q for q in orientations if len(q)]
    up = np.array([0.0, -1.0, 0.0])  # a y-down camera frame
    if quats:
        y_axes = Rotation.from_quat(np.concatenate(quats)).as_matrix()[:, :, 1]
        mean = -y_axes.mean(axis=0)
        if np.linalg.norm(mean) > 0.3:  # cameras agree on what is up
            up = mean / np.linalg.norm(mean)
    seed = np.eye(3)[0] if abs(up[0]) < 0.9 else np.eye(3)[2]
    first = seed - (seed @ up) * up
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(up, first), up])


def _oblique(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Screen coordinates ``(N, 2)`` and depth ``(N,)`` (larger is farther) of points in the
    up basis, seen from :data:`OBLIQUE_AZIMUTH_DEG` and :data:`OBLIQUE_ELEVATION_DEG`."""
    az, el = np.radians(OBLIQUE_AZIMUTH_DEG), np.radians(OBLIQUE_ELEVATION_DEG)
    a = np.cos(az) * local[:, 0] - np.sin(az) * local[:, 1]
    b = np.sin(az) * local[:, 0] + np.cos(az) * local[:, 1]
    screen = np.stack([a, np.sin(el) * b + np.cos(el) * local[:, 2]], axis=1)
    return screen, np.cos(el) * b - np.sin(el) * local[:, 2]


def _splat(
    ax: Axes, screen: np.ndarray, colours: np.ndarray, depth: np.ndarray, title: str
) -> None:
    order = np.argsort(-depth, kind="stable")  # far first
    ax.scatter(
        screen[order, 0],
        screen[order, 1],
        c=colours[order] / 255.0,
        s=2.0,
        marker="o",
        linewidths=0,
        rasterized=True,
    )
    low, high = np.percentile(screen, VIEW_PERCENTILES, axis=0)
    margin = 0.05 * np.maximum(high - low, 1e-6)
    ax.set_xlim(low[0] - margin[0], high[0] + margin[0])
    ax.set_ylim(low[1] - margin[1], high[1] + margin[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_title(title)
    ax.tick_params(labelsize="small")


def map_figure(sample: MapSample, tracks: Sequence[AgentTrack]) -> Figure:
    """Top-down view (with the estimated trajectories) and oblique view of the map sample.

    Args:
        sample: the points to draw (:func:`sample_map`).
        tracks: the agents' estimates in the run's world frame (the map's frame).
    """
    basis = up_basis([t.orientations for t in tracks])
    local = sample.xyz @ basis.T
    figure = new_figure(11.0, 5.2)
    top, oblique = figure.add_subplot(1, 2, 1), figure.add_subplot(1, 2, 2)
    _splat(top, local[:, :2], sample.rgb, -local[:, 2], "top-down")
    for track in tracks:
        if len(track.positions):
            path = track.positions @ basis.T
            top.plot(
                path[:, 0],
                path[:, 1],
                "-",
                color=agent_colour(track.agent),
                linewidth=1.4,
                label=f"agent {track.agent}",
            )
    if top.get_legend_handles_labels()[0]:
        top.legend(loc="best", fontsize="small")
    top.set_xlabel("horizontal [m]")
    screen, depth = _oblique(local)
    _splat(oblique, screen, sample.rgb, depth, "oblique")
    figure.suptitle(f"Fused map: {len(sample.xyz):,} of {sample.total:,} points")
    figure.tight_layout()
    return figure
