"""Reconstruction metrics: accuracy, completeness, Chamfer distance, precision / recall / F-score.

The estimated cloud is the concatenation of every keyframe's refined canonical pointmap,
confidence-thresholded and lifted into the world frame (C-Sec. B.5, :func:`keyframe_cloud`);
the reference cloud is built from ground-truth depth and poses (:func:`ground_truth_cloud`).
The estimate lives in the SLAM gauge, so it is first mapped into the ground-truth frame by
the Sim(3) alignment found from the trajectories (:class:`~como3r.evaluation.trajectory.
Sim3Alignment`); both clouds may be voxel-downsampled so that dense regions do not dominate
the means. Nearest neighbours come from ``scipy.spatial.cKDTree``.

Definitions (distances in metres of the ground-truth frame):

* accuracy: mean distance from each estimated point to its nearest ground-truth point;
* completeness: mean distance from each ground-truth point to its nearest estimated point;
* Chamfer distance: ``(accuracy + completeness) / 2``;
* precision / recall: share of estimated / ground-truth points within ``threshold`` of the
  other cloud; F-score: their harmonic mean.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from como3r.data.agent import open_agent
from como3r.data.agent_input import AgentInput
from como3r.errors import InputError
from como3r.evaluation.trajectory import Sim3Alignment
from como3r.geometry.camera import intrinsics_matrix, unproject_depth
from como3r.geometry.lie import sim3_act

logger = logging.getLogger(__name__)

__all__ = [
    "ReconstructionMetrics",
    "VoxelCentroids",
    "reconstruction_metrics",
    "nearest_distances",
    "voxel_downsample",
    "unique_rows",
    "keyframe_cloud",
    "cloud_from_depth",
    "ground_truth_cloud",
    "evaluate_maps",
    "median_ground_truth_depth",
]

DEFAULT_THRESHOLD_M = 0.05
"""Precision / recall distance threshold [m] of :func:`reconstruction_metrics`."""

MAP_THRESHOLD_RATIO = 0.05
"""A run's map: precision / recall threshold as a fraction of the median ground-truth depth
(5 cm at the 1 m reference depth of :mod:`como3r.geometry.units`)."""

MAP_VOXEL_RATIO = 0.05
"""A run's map: both clouds are reduced to voxels of this fraction of the median
ground-truth depth before they are compared."""

GT_POINTS_PER_FRAME = 20_000
"""Roughly how many depth pixels of each ground-truth frame enter the reference cloud."""


@dataclass(frozen=True)
class ReconstructionMetrics:
    """Metrics of an estimated cloud against ground truth (see the module docstring).

    Attributes:
        accuracy: mean distance estimate -> ground truth [m].
        completeness: mean distance ground truth -> estimate [m].
        chamfer: ``(accuracy + completeness) / 2`` [m].
        precision: share of estimated points within ``threshold`` of ground truth.
        recall: share of ground-truth points within ``threshold`` of the estimate.
        fscore: harmonic mean of precision and recall (0 when both are 0).
        threshold: the distance threshold [m].
        num_estimated: estimated points compared (after downsampling).
        num_ground_truth: ground-truth points compared (after downsampling).
    """

    accuracy: float
    completeness: float
    chamfer: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    num_estimated: int
    num_ground_truth: int

    def to_json(self) -> dict[str, float | int]:
        return asdict(self)


def _as_points(points: np.ndarray | Tensor, name: str) -> np.ndarray:
    """``(N, 3)`` float64 finite points; non-finite rows are dropped."""
    if isinstance(points, Tensor):
        points = points.detach().to("cpu", torch.float64).numpy()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{name} cloud must be (N, 3), got {points.shape}")
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        logger.warning("%s cloud: dropping %d non-finite points", name, int((~finite).sum()))
        points = points[finite]
    if points.shape[0] == 0:
        raise InputError(f"{name} cloud is empty")
    return points


class VoxelCentroids:
    """Centroid of the points in each occupied voxel of an axis-aligned grid, over points
    given in any number of pieces: memory grows with the occupied voxels and one buffer of
    ``buffer_points`` points, not with the points given (a long run's reference cloud
    visits the same voxels from thousands of frames, issue 14).

    Args:
        voxel_size: edge length [m], positive.
        buffer_points: points held before they are merged into the voxels' sums.
    """

    def __init__(self, voxel_size: float, buffer_points: int = 1 << 18) -> None:
        if not voxel_size > 0:
            raise InputError(f"VoxelCentroids: voxel size must be positive, got {voxel_size}")
        self.voxel_size = voxel_size
        self.buffer_points = buffer_points
        self._cells = np.zeros((0, 3), dtype=np.int64)
        self._sums = np.zeros((0, 3))
        self._counts = np.zeros(0, dtype=np.int64)
        self._pending: list[np.ndarray] = []
        self._pending_points = 0

    def add(self, points: np.ndarray) -> None:
        """Take ``(N, 3)`` more points."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self._pending.append(points)
        self._pending_points += points.shape[0]
        if self._pending_points >= self.buffer_points:
            self._merge()

    def centroids(self) -> np.ndarray:
        """``(M, 3)`` float64 centroids of the occupied voxels, ordered by voxel index."""
        self._merge()
        return self._sums / self._counts[:, None]

    def _merge(self) -> None:
        if not self._pending:
            return
        points = np.concatenate(self._pending)
        self._pending, self._pending_points = [], 0
        cells = np.concatenate([self._cells, np.floor(points / self.voxel_size).astype(np.int64)])
        self._cells, inverse = unique_rows(cells)
        old = self._counts.size
        sums = np.zeros((self._cells.shape[0], 3))
        np.add.at(sums, inverse[:old], self._sums)
        np.add.at(sums, inverse[old:], points)
        self._sums = sums
        self._counts = np.bincount(
            inverse,
            weights=np.concatenate([self._counts, np.ones(points.shape[0], dtype=np.int64)]),
            minlength=self._cells.shape[0],
        ).astype(np.int64)


def unique_rows(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``cells (N, 3)`` int64 in lexicographic order and each row's
    index among them, as ``np.unique(cells, axis=0, return_inverse=True)`` gives, through
    one int64 key per row: 3-5x (19,200 points) to 5-9x (10^6) faster than the row-wise
    sort, in which the demo's evaluation spent 7 s (``benchmarks/store_speed.py``). Grids
    too large for one key take the row-wise sort."""
    if cells.shape[0] == 0:
        return cells, np.zeros(0, dtype=np.int64)
    low = cells.min(axis=0)
    extent = cells.max(axis=0) - low + 1
    if math.prod(int(n) for n in extent) >= 2**62:
        unique, inverse = np.unique(cells, axis=0, return_inverse=True)
        return unique, inverse.reshape(-1)
    shifted = cells - low
    keys = (shifted[:, 0] * extent[1] + shifted[:, 1]) * extent[2] + shifted[:, 2]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return cells[first], inverse.reshape(-1)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel of an axis-aligned grid.

    Args:
        points: ``(N, 3)``.
        voxel_size: edge length; ``<= 0`` returns the points unchanged.

    Returns:
        ``(M, 3)`` float64 centroids, ``M <= N``, ordered by voxel index.
    """
    points = np.asarray(points, dtype=np.float64)
    if voxel_size <= 0 or points.shape[0] == 0:
        return points
    voxels = VoxelCentroids(voxel_size, buffer_points=points.shape[0])
    voxels.add(points)
    return voxels.centroids()


def nearest_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``(N,)`` distance of each ``source`` point ``(N, 3)`` to its nearest ``target`` point."""
    distances, _ = cKDTree(target).query(source, k=1)
    return distances


def reconstruction_metrics(
    estimated: np.ndarray | Tensor,
    ground_truth: np.ndarray | Tensor,
    threshold: float = DEFAULT_THRESHOLD_M,
    alignment: Sim3Alignment | None = None,
    voxel_size: float = 0.0,
) -> ReconstructionMetrics:
    """Compare an estimated cloud with ground truth.

    Args:
        estimated: ``(N, 3)`` points in the estimate's world frame.
        ground_truth: ``(M, 3)`` points in the ground-truth frame.
        threshold: precision / recall distance [m], positive.
        alignment: maps the estimate into the ground-truth frame (the trajectory's Sim(3)
            alignment); None if it is already there.
        voxel_size: downsample both clouds to this voxel size [m] first; 0 keeps them.

    Raises:
        InputError: a cloud of the wrong shape, an empty cloud, a non-positive threshold.
    """
    if not (math.isfinite(threshold) and threshold > 0):
        raise InputError(f"reconstruction threshold must be a positive number, got {threshold}")
    estimated = _as_points(estimated, "estimated")
    ground_truth = _as_points(ground_truth, "ground-truth")
    if alignment is not None:
        estimated = alignment.apply(estimated)
    estimated = voxel_downsample(estimated, voxel_size)
    ground_truth = voxel_downsample(ground_truth, voxel_size)

    to_gt = nearest_distances(estimated, ground_truth)
    to_est = nearest_distances(ground_truth, estimated)
    accuracy, completeness = float(to_gt.mean()), float(to_est.mean())
    precision = float((to_gt < threshold).mean())
    recall = float((to_est < threshold).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return ReconstructionMetrics(
        accuracy=accuracy,
        completeness=completeness,
        chamfer=0.5 * (accuracy + completeness),
        precision=precision,
        recall=recall,
        fscore=fscore,
        threshold=float(threshold),
        num_estimated=int(estimated.shape[0]),
        num_ground_truth=int(ground_truth.shape[0]),
    )


def keyframe_cloud(
    pointmaps: Sequence[Tensor],
    confidences: Sequence[Tensor],
    poses: Tensor,
    min_confidence: float,
) -> np.ndarray:
    """The fused map of C-Sec. B.5: every keyframe's pointmap above a confidence, in world.

    Args:
        pointmaps: N canonical pointmaps ``(H_k, W_k, 3)``, each in its keyframe's camera.
        confidences: N per-frame confidences ``(H_k, W_k)``; points with ``C > min_confidence``
            are kept.
        poses: ``(N, 8)`` Sim(3) ``T_WC``.
        min_confidence: ``C_conf``.

    Returns:
        ``(M, 3)`` float64 world points.
    """
    if len(pointmaps) != len(confidences) or poses.shape != (len(pointmaps), 8):
        raise InputError(
            f"keyframe_cloud: {len(pointmaps)} pointmaps, {len(confidences)} "
            f"confidence maps and poses of shape {tuple(poses.shape)}"
        )
    clouds = []
    for X, C, T_WC in zip(pointmaps, confidences, poses):
        keep = (C > min_confidence) & torch.isfinite(X).all(dim=-1)
        points = X[keep].to(torch.float64)
        clouds.append(sim3_act(T_WC.to(torch.float64)[None], points).cpu().numpy())
    return np.concatenate(clouds) if clouds else np.zeros((0, 3))


def cloud_from_depth(
    depth: np.ndarray | Tensor,
    K: Tensor,
    T_WC: Tensor,
    pixel_stride: int = 1,
    max_depth: float | None = None,
) -> np.ndarray:
    """World points of one metric z-depth map.

    Args:
        depth: ``(H, W)`` depth along the optical axis [m]; 0 or non-finite = no depth.
        K: ``(3, 3)`` intrinsics of the depth map's pixels.
        T_WC: ``(8,)`` pose of the camera.
        pixel_stride: keep every ``pixel_stride``-th row and column.
        max_depth: drop depths beyond this [m]; None keeps all.

    Returns:
        ``(M, 3)`` float64 world points.
    """
    depth_t = torch.as_tensor(np.asarray(depth), dtype=torch.float64)
    points = unproject_depth(depth_t, K.to(torch.float64))[::pixel_stride, ::pixel_stride]
    z = depth_t[::pixel_stride, ::pixel_stride]
    keep = torch.isfinite(z) & (z > 0)
    if max_depth is not None:
        keep &= z <= max_depth
    return sim3_act(T_WC.to(torch.float64)[None], points[keep]).numpy()


def ground_truth_cloud(
    agents: Sequence[str | Path | AgentInput],
    frame_stride: int = 1,
    pixel_stride: int = 1,
    max_depth: float | None = None,
    voxel_size: float = 0.0,
) -> np.ndarray:
    """Reference cloud from the agents' ground-truth depth, poses and calibration.

    Every ``frame_stride``-th frame with a ground-truth pose contributes its depth map
    unprojected with ``calib.txt`` and lifted by its ground-truth pose.

    Args:
        agents: agent folders (or opened inputs) with ``depth/``, ``groundtruth.txt`` and
            ``calib.txt``.
        frame_stride, pixel_stride: subsampling of frames and of pixels.
        max_depth: drop depths beyond this [m].
        voxel_size: downsample each frame's points and the result to this voxel size [m]
            (the result's memory is then that of the occupied voxels, whatever the number
            of frames).

    Returns:
        ``(M, 3)`` float64 points in the ground-truth frame.

    Raises:
        InputError: an agent without depth, ground truth or calibration, or no usable frame.
    """
    if frame_stride < 1 or pixel_stride < 1:
        raise InputError(
            f"ground_truth_cloud: strides must be >= 1, got frame_stride="
            f"{frame_stride}, pixel_stride={pixel_stride}"
        )
    clouds: list[np.ndarray] = []
    voxels = VoxelCentroids(voxel_size) if voxel_size > 0 else None
    for agent in agents:
        agent = agent if isinstance(agent, AgentInput) else open_agent(agent)
        missing = [
            name
            for name, present in (
                ("depth/", agent.has_depth),
                ("groundtruth.txt", agent.groundtruth is not None),
                ("calib.txt", agent.calib is not None),
            )
            if not present
        ]
        if missing:
            raise InputError(f"{agent.root}: a ground-truth cloud needs {', '.join(missing)}")
        K = intrinsics_matrix(*agent.calib, dtype=torch.float64)
        frames = np.flatnonzero(agent.has_gt_pose)[::frame_stride]
        for index in frames:
            frame = agent.load_frame(int(index))
            points = cloud_from_depth(frame.depth, K, frame.T_WC_gt, pixel_stride, max_depth)
            if voxels is None:
                clouds.append(points)
            else:
                voxels.add(voxel_downsample(points, voxel_size))
    if voxels is not None:
        cloud = voxels.centroids()
    else:
        cloud = np.concatenate(clouds) if clouds else np.zeros((0, 3))
    if cloud.shape[0] == 0:
        raise InputError("ground_truth_cloud: no frame with ground truth and valid depth")
    return cloud


def median_ground_truth_depth(agents: Sequence[AgentInput], samples: int = 8) -> float:
    """Median valid ground-truth depth [m] over up to ``samples`` evenly spaced frames of
    each agent: the length a run's map metrics are relative to.

    Raises:
        InputError: no sampled frame has a valid depth.
    """
    depths = []
    for agent in agents:
        frames = np.flatnonzero(agent.has_gt_pose)
        for index in frames[np.linspace(0, len(frames) - 1, min(samples, len(frames))).astype(int)]:
            depth = np.asarray(agent.load_frame(int(index)).depth, dtype=np.float64)
            depths.append(depth[np.isfinite(depth) & (depth > 0)])
    valid = np.concatenate(depths) if depths else np.zeros(0)
    if valid.size == 0:
        raise InputError("median_ground_truth_depth: no frame with a valid ground-truth depth")
    return float(np.median(valid))


def evaluate_maps(
    agents: Sequence[AgentInput],
    clouds: Mapping[str, Iterable[np.ndarray]],
    alignment: Sim3Alignment,
    threshold_ratio: float = MAP_THRESHOLD_RATIO,
    voxel_ratio: float = MAP_VOXEL_RATIO,
) -> dict[str, ReconstructionMetrics]:
    """Metrics of several estimates of one component's map against one reference cloud.

    The reference is every ground-truth frame of ``agents``, pixel-strided to about
    :data:`GT_POINTS_PER_FRAME` points per frame; each estimate is mapped into the
    ground-truth frame by ``alignment`` (the component's trajectory alignment). Threshold
    and voxel size are fractions of the median ground-truth depth
    (:func:`median_ground_truth_depth`), so a scene scaled by any factor scores the same.
    Both clouds are reduced to voxels as they are read (:class:`VoxelCentroids`): memory
    follows the map's extent, not the number of frames and keyframes.

    Args:
        agents: the component's agent inputs (with depth, ground truth and calibration).
        clouds: name -> the estimate's points in the component's gauge, in pieces
            ``(N_k, 3)`` (one per keyframe, say); non-finite points are dropped.
        alignment: estimate -> ground truth.
        threshold_ratio: precision / recall distance over the median depth.
        voxel_ratio: voxel size over the median depth.

    Raises:
        InputError: no usable ground truth, or an empty estimate.
    """
    height, width = agents[0].image_size[1], agents[0].image_size[0]
    stride = max(1, math.ceil(math.sqrt(height * width / GT_POINTS_PER_FRAME)))
    depth = median_ground_truth_depth(agents)
    voxel_size = voxel_ratio * depth
    reference = ground_truth_cloud(agents, pixel_stride=stride, voxel_size=voxel_size)
    scores = {}
    for name, pieces in clouds.items():
        voxels = VoxelCentroids(voxel_size)
        for piece in pieces:
            piece = np.asarray(piece, dtype=np.float64).reshape(-1, 3)
            voxels.add(alignment.apply(piece[np.isfinite(piece).all(axis=1)]))
        scores[name] = reconstruction_metrics(
            voxels.centroids(), reference, threshold_ratio * depth
        )
    return scores
