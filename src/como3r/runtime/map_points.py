"""``map.ply``: every keyframe's confident points in the world, fused a keyframe at a time
(a long run's map is never held whole) and thinned to the first point of each voxel; the
outputs (:mod:`.outputs`, which re-exports these names) write it and score the map with it.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from como3r.config import Config
from como3r.frontend.agent import AgentFrontend
from como3r.geometry.lie import sim3_act
from como3r.geometry.units import median_range
from como3r.io.ply import write_ply_pieces


def fused_map(
    keyframes: Mapping[int, Iterable[Any]], min_confidence: float, voxel_size: float = 0.0
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every keyframe's canonical pointmap in the world, above a confidence threshold, one
    keyframe at a time (a long run's map is never held whole, issue 14).

    Args:
        keyframes: agent id -> its keyframes (``T_WC``, ``X_hat``, ``colors``,
            ``mean_confidence()``).
        min_confidence: keep points whose per-frame confidence exceeds this.
        voxel_size: keep the first point of every voxel of this size; 0 keeps all.

    Yields:
        per keyframe ``xyz (N, 3)`` float32, ``rgb (N, 3)`` uint8 and ``agent_id (N,)``
        int32.
    """
    voxels = _FirstPerVoxel(voxel_size) if voxel_size > 0 else None
    for agent, agent_keyframes in keyframes.items():
        for kf in agent_keyframes:
            points, keep = _world_points(kf, min_confidence)
            rgb = kf.colors.reshape(-1, 3)[keep]
            if voxels is not None:
                first = voxels.new_points(points)
                points, rgb = points[first], rgb[first]
            yield points, rgb, np.full(points.shape[0], agent, dtype=np.int32)


class _FirstPerVoxel:
    """The voxels of a grid seen so far, to keep the first point of each over pieces.

    Seen voxels are kept sorted, each cell's three int64 as one 24-byte key (any extent): a
    piece costs a sort of its own cells and an insertion into the seen ones, not a sort of
    every voxel seen (which made writing the map quadratic in keyframes).
    """

    def __init__(self, voxel_size: float) -> None:
        self.voxel_size = voxel_size
        self._seen = np.zeros(0, dtype="V24")

    def new_points(self, points: np.ndarray) -> np.ndarray:
        """Indices (ascending) of the points of ``points (N, 3)`` that are the first in a
        voxel not seen before; their voxels are seen from now on."""
        cells = np.ascontiguousarray(np.floor(points / self.voxel_size).astype(np.int64))
        voxels, first = np.unique(cells.view("V24").reshape(-1), return_index=True)
        at = np.searchsorted(self._seen, voxels)
        seen = at < self._seen.size
        seen[seen] = self._seen[at[seen]] == voxels[seen]
        self._seen = np.insert(self._seen, at[~seen], voxels[~seen])
        return np.sort(first[~seen])


def _world_points(kf: Any, min_confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """A keyframe's canonical points in the world above a confidence: ``(N, 3)`` float32
    and the ``(H*W,)`` bool mask of the pixels kept."""
    keep = (kf.mean_confidence() > min_confidence).reshape(-1).cpu()
    points = sim3_act(kf.T_WC[None, None, :].to(kf.X_hat), kf.X_hat).reshape(-1, 3).cpu()
    return points[keep].numpy().astype(np.float32), keep.numpy()


def fused_points(
    keyframes: Mapping[int, Iterable[Any]], min_confidence: float
) -> Iterator[np.ndarray]:
    """:func:`fused_map`'s points, one ``(N_k, 3)`` float32 piece per keyframe."""
    for xyz, _, _ in fused_map(keyframes, min_confidence):
        yield xyz


def map_voxel(keyframes: Mapping[int, Iterable[Any]], config: Config) -> tuple[float, int]:
    """The voxel edge ``map.ply`` is thinned with (world units; 0 keeps every point) and
    the points above the confidence threshold before it: ``visualization.voxel_size_m``
    where set, else ``visualization.map_voxel`` times the median over keyframes of their
    confident points' median range (``s`` times that of ``X_hat``)."""
    min_confidence = config.visualization.map_min_confidence
    ranges, confident = [], 0
    for agent_keyframes in keyframes.values():
        for kf in agent_keyframes:
            keep = kf.mean_confidence() > min_confidence
            confident += int(keep.sum())
            if bool(keep.any()):
                ranges.append(float(median_range(kf.X_hat, keep)) * float(kf.T_WC[7]))
    if config.visualization.voxel_size_m > 0:
        return config.visualization.voxel_size_m, confident
    return config.visualization.map_voxel * (float(np.median(ranges)) if ranges else 0.0), confident


def write_map(out: Path, frontends: Sequence[AgentFrontend], config: Config) -> dict[str, Any]:
    """Write ``map.ply`` a keyframe at a time, thinned by :func:`map_voxel`; returns
    ``metrics.json``'s ``map``: ``points`` written, ``confident_points`` before the thinning
    and the ``voxel`` edge (world units, 0: none)."""
    keyframes = {fe.agent: fe.keyframes for fe in frontends}
    voxel, confident = map_voxel(keyframes, config)
    points = write_ply_pieces(
        out / "map.ply",
        fused_map(keyframes, config.visualization.map_min_confidence, voxel),
    )
    return {"points": points, "confident_points": confident, "voxel": voxel}
