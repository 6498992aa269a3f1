"""A finished run folder's keyframe graph as the exports read it (:mod:`como3r.io.export`,
:mod:`como3r.io.ros2_bag`): ``graph.json``'s keyframes with their final Sim(3) ``T_WC``, its
accepted edges with their weights, its gauge components, and a keyframe's intrinsics and
depth from its keyframe data (:mod:`como3r.io.keyframe_data`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from como3r.errors import InputError
from como3r.geometry.camera import estimate_focal
from como3r.geometry.lie import quat_to_matrix
from como3r.io.colmap import Pinhole
from como3r.io.keyframe_data import KeyframeData


@dataclass(frozen=True)
class RunKeyframe:
    """One keyframe of ``graph.json``.

    Attributes:
        index: its position in ``graph.json``'s ``keyframes`` (the g2o vertex id).
        agent: agent id.
        kf_id: keyframe id within the agent.
        frame: frame index in the agent's stream.
        timestamp: seconds.
        T_WC: ``(8,)`` float64 Sim(3) pose ``(t, q_xyzw, s)``, quaternion normalised.
    """

    index: int
    agent: int
    kf_id: int
    frame: int
    timestamp: float
    T_WC: np.ndarray

    @property
    def name(self) -> str:
        """File stem of its exported image and depth: ``agent<a>_kf<k:06d>``."""
        return f"agent{self.agent}_kf{self.kf_id:06d}"

    @property
    def rigid(self) -> torch.Tensor:
        """``(7,)`` float64 SE(3) camera-to-world pose ``(t, q_xyzw)`` (the scale dropped)."""
        return torch.from_numpy(self.T_WC[:7].copy())

    def camera_to_world(self) -> np.ndarray:
        """``(4, 4)`` rigid camera-to-world matrix (OpenCV camera axes)."""
        M = np.eye(4)
        M[:3, :3] = quat_to_matrix(self.rigid[3:7]).numpy()
        M[:3, 3] = self.T_WC[:3]
        return M


@dataclass(frozen=True)
class RunEdge:
    """One edge of ``graph.json`` between keyframes ``i`` and ``j`` (their indices).

    Attributes:
        weight: :func:`edge_weight`.
    """

    i: int
    j: int
    kind: str
    weight: float


@dataclass(frozen=True)
class RunGraph:
    """What ``graph.json`` says: keyframes in file order, the edges between them (those
    marked ``"accepted": false`` left out), the gauge components (lists of agents)."""

    keyframes: list[RunKeyframe]
    edges: list[RunEdge]
    components: list[list[int]]


def read_run_graph(run: str | Path) -> RunGraph:
    """Read ``run/graph.json`` of a finished run folder.

    Raises:
        InputError: ``run`` is missing, not a folder, an unfinished run (``*.partial``), has no
            ``graph.json`` (a demo folder is pointed to its ``run``), or a malformed one.
    """
    run = Path(run)
    if not run.exists():
        raise InputError(f"{run}: no such run folder")
    if not run.is_dir():
        raise InputError(f"{run}: not a folder (give a run folder, como3r run --out)")
    if run.name.endswith(".partial"):
        raise InputError(
            f"{run}: an unfinished run (a run writes DIR.partial and renames it to "
            f"DIR when it is complete)"
        )
    path = run / "graph.json"
    if not path.is_file():
        hint = (
            f"; the run of this demo folder is {run / 'run'}"
            if (run / "run" / "graph.json").is_file()
            else ""
        )
        raise InputError(f"{run}: not a finished como3r run folder: no graph.json{hint}")
    try:
        document = json.loads(path.read_text())
        keyframes = [_keyframe(i, entry) for i, entry in enumerate(document["keyframes"])]
        index = {(k.agent, k.kf_id): k.index for k in keyframes}
        edges = [
            _edge(e, index)
            for e in document.get("edges", [])
            if e.get("accepted", True) is not False
        ]
        components = [[int(a) for a in c] for c in document.get("components", [])]
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"{path}: not a como3r graph ({type(exc).__name__}: {exc})") from None
    if not keyframes:
        raise InputError(f"{path}: no keyframes to export")
    return RunGraph(keyframes, edges, components)


def _keyframe(index: int, entry: dict[str, Any]) -> RunKeyframe:
    T_WC = np.asarray(entry["T_WC"], dtype=np.float64)
    if T_WC.shape != (8,) or not np.isfinite(T_WC).all() or T_WC[7] <= 0:
        raise ValueError(f"keyframe {index}: T_WC is not 8 finite numbers with scale > 0")
    q_norm = np.linalg.norm(T_WC[3:7])
    if abs(q_norm - 1.0) > 1e-2:
        raise ValueError(f"keyframe {index}: quaternion norm {q_norm:.4f} is not 1")
    T_WC[3:7] /= q_norm
    return RunKeyframe(
        index,
        int(entry["agent"]),
        int(entry["keyframe"]),
        int(entry["frame"]),
        float(entry["timestamp"]),
        T_WC,
    )


def _edge(entry: dict[str, Any], index: dict[tuple[int, int], int]) -> RunEdge:
    ends = []
    for end in (entry["from"], entry["to"]):
        agent, kf_id = (int(v) for v in end)
        if (agent, kf_id) not in index:
            raise ValueError(
                f"edge {entry['from']} -> {entry['to']}: no keyframe {kf_id} of "
                f"agent {agent} in the graph"
            )
        ends.append(index[agent, kf_id])
    return RunEdge(ends[0], ends[1], str(entry.get("type", "")), edge_weight(entry))


def keyframe_intrinsics(data: KeyframeData) -> Pinhole:
    """The keyframe's intrinsics: its ``K``, else the focal length its pointmap implies
    (:func:`~como3r.geometry.camera.estimate_focal`, confidence-weighted) with the principal
    point at the image centre.

    Raises:
        InputError: no ``K`` and no point in front of the camera to estimate one from.
    """
    H, W = data.shape
    if data.K is not None:
        K = data.K
        return Pinhole(W, H, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    focal = float(estimate_focal(torch.from_numpy(data.X), torch.from_numpy(data.C)))
    if not math.isfinite(focal) or focal <= 0:
        raise InputError(
            f"{data.source}: no intrinsics and no point in "
            f"front of the camera to estimate a focal length from"
        )
    return Pinhole(W, H, focal, focal, (W - 1) / 2.0, (H - 1) / 2.0)


def keyframe_depth(keyframe: RunKeyframe, data: KeyframeData) -> np.ndarray:
    """``(H, W)`` float32 depth along the optical axis in world units, ``s X_z``; 0 where the
    pointmap has no finite point in front of the camera."""
    depth = keyframe.T_WC[7] * data.X[..., 2].astype(np.float64)
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def edge_weight(edge: dict[str, Any]) -> float:
    """An edge's weight in the g2o information matrix: its match fraction (the smaller of
    ``nu_i``, ``nu_j`` for sequential and inter-agent edges, ``match_fraction`` for loop
    edges), 1 for an edge without one."""
    if "nu_i" in edge and "nu_j" in edge:
        return float(min(edge["nu_i"], edge["nu_j"]))
    return float(edge.get("match_fraction", 1.0))
