"""A visual-inertial-like odometry model for synthetic robots (``odometry.txt``).

FLOCC-SLAM assumes every robot brings a locally consistent metric odometry (F-Sec. III) and
observes that monocular VIO is off in scale where its online scale estimate has not yet
converged, at the start of a trajectory (F-Sec. IV-C). :func:`simulate_odometry` turns a
ground-truth trajectory into such an odometry by integrating the true displacements with

* a scale ``lambda(d) = (1 + e0 exp(-d / L_conv)) (1 + b(d))`` of the distance travelled
  ``d``: an unconverged start ``e0`` (random sign, magnitude ``initial_scale_error``) that
  decays over ``scale_convergence_depths``, times a slowly varying error ``b`` (an
  Ornstein-Uhlenbeck process over distance, standard deviation ``scale_drift``, correlation
  length ``scale_correlation_depths``);
* a heading drift ``psi(d)`` about the gravity axis (world z; roll and pitch are observable
  from gravity and do not drift): a constant rate of ``yaw_drift_deg_per_depth`` with a
  random sign plus a random walk of ``yaw_walk_deg_per_sqrt_depth``;
* a translation random walk of ``translation_walk_per_sqrt_depth``.

Lengths are in units of the robot's scene depth ``D`` (median depth of its first depth map,
:func:`add_odometry`), so the drift is a fraction of the distance travelled and a scene
scaled by any factor gets the same odometry scaled by that factor. The defaults keep the
former metric values at the default synthetic scene's median depth of about 6.5 m (e.g.
0.3 deg/m of heading drift -> 2 deg per D, 2 m of scale convergence -> 0.3 D).

The odometry is expressed in its own gravity-aligned frame: the world turned by a random
yaw about z and moved to the first camera position, so robots do not share a frame.

Two presets mirror the paper's two backbones (F-Tables II-III): ``vio`` (monocular VIO such
as VINS-Mono: 30 % scale error at the start, converged after 0.3 scene depths -- about 2 m
in the default scene --, drifting heading)
and ``lio`` (LiDAR-inertial odometry: near-perfect scale, little drift). :func:`add_odometry`
declares which beside the file (``odometry.json``: ``vio`` or ``metric``), as a real robot's
operator would.

Lengths at the paper's scale (GrAco, outdoors, depth of order 15 m): the ``vio`` scale
converges after 0.3 D = 4.5 m and its heading drifts 0.13 deg/m.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from como3r.data.agent import open_agent
from como3r.decentralized.odometry_kind import OdometryKind, write_odometry_kind
from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum, write_tum

ODOMETRY_FILE = "odometry.txt"


@dataclass(frozen=True)
class OdometryNoise:
    """Parameters of the odometry model (module docstring); lengths in scene depths D."""

    initial_scale_error: float = 0.3
    scale_convergence_depths: float = 0.3
    scale_drift: float = 0.02
    scale_correlation_depths: float = 0.8
    yaw_drift_deg_per_depth: float = 2.0
    yaw_walk_deg_per_sqrt_depth: float = 0.25
    translation_walk_per_sqrt_depth: float = 0.002


ODOMETRY_PRESETS: dict[str, OdometryNoise] = {
    "vio": OdometryNoise(),
    "lio": OdometryNoise(
        initial_scale_error=0.0,
        scale_drift=0.005,
        yaw_drift_deg_per_depth=0.3,
        yaw_walk_deg_per_sqrt_depth=0.05,
        translation_walk_per_sqrt_depth=0.0008,
    ),
}
"""Odometry models by name (module docstring)."""


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def simulate_odometry(
    groundtruth: Trajectory, seed: int, noise: OdometryNoise | None = None, *, scene_depth: float
) -> Trajectory:
    """Odometry of a robot that moved along ``groundtruth`` (module docstring).

    Args:
        groundtruth: ``N`` true camera poses ``T_WC`` (world z up).
        seed: random seed; the same seed gives the same odometry.
        noise: model parameters; the defaults when None.
        scene_depth: the length unit ``D`` of ``noise`` in the ground truth's units, > 0.

    Returns:
        ``N`` odometry poses ``T_OC`` (scale 1) with the ground truth's timestamps.
    """
    if not scene_depth > 0:
        raise InputError(f"odometry simulation: scene_depth must be > 0, got {scene_depth}")
    noise = noise or OdometryNoise()
    rng = np.random.default_rng(seed)
    poses = groundtruth.T_WC.detach().cpu().double().numpy()
    positions = poses[:, :3]
    rotations = Rotation.from_quat(poses[:, 3:7]).as_matrix()
    steps = np.diff(positions, axis=0)
    # Distances in scene depths: every error below is relative to the scene's scale.
    lengths = np.linalg.norm(steps, axis=1) / scene_depth
    travelled = np.concatenate([[0.0], np.cumsum(lengths)])

    start_error = noise.initial_scale_error * rng.choice([-1.0, 1.0])
    yaw_rate = np.radians(noise.yaw_drift_deg_per_depth) * rng.choice([-1.0, 1.0])
    yaw_walk = np.radians(noise.yaw_walk_deg_per_sqrt_depth)
    drift = 0.0
    heading = 0.0
    est_positions = np.zeros_like(positions)
    est_rotations = np.empty_like(rotations)
    est_positions[0], est_rotations[0] = positions[0], rotations[0]
    for k in range(1, len(positions)):
        length = lengths[k - 1]
        decay = np.exp(-length / noise.scale_correlation_depths)
        drift = decay * drift + noise.scale_drift * np.sqrt(1.0 - decay**2) * rng.standard_normal()
        scale = (1.0 + start_error * np.exp(-travelled[k] / noise.scale_convergence_depths)) * (
            1 + drift
        )
        heading += yaw_rate * length + yaw_walk * np.sqrt(length) * rng.standard_normal()
        turn = _yaw(heading)
        walk = (
            scene_depth
            * noise.translation_walk_per_sqrt_depth
            * np.sqrt(length)
            * rng.standard_normal(3)
        )
        est_positions[k] = est_positions[k - 1] + scale * turn @ steps[k - 1] + walk
        est_rotations[k] = turn @ rotations[k]

    # The odometry frame: gravity-aligned, turned by a random yaw, origin at the first camera.
    frame_rotation = _yaw(rng.uniform(0.0, 2.0 * np.pi))
    odom_positions = (est_positions - positions[0]) @ frame_rotation
    odom_rotations = frame_rotation.T @ est_rotations
    quat = Rotation.from_matrix(odom_rotations).as_quat()
    quat *= np.where(quat[:, 3:] < 0, -1.0, 1.0)
    T_OC = np.concatenate([odom_positions, quat, np.ones((len(quat), 1))], axis=1)
    return Trajectory(groundtruth.timestamps.copy(), torch.from_numpy(T_OC))


def scene_depth_of(agent_dir: Path) -> float:
    """Median valid depth of the first depth map of an agent folder (its unit of length).

    Raises:
        InputError: the folder has no depth maps, or the first has no valid depth.
    """
    agent = open_agent(agent_dir)
    if not agent.has_depth:
        raise InputError(
            f"{agent_dir}: no depth/ maps to measure the scene depth the odometry "
            "noise is relative to; pass scene_depth"
        )
    depth = agent.load_frame(0).depth
    depth = depth[np.isfinite(depth) & (depth > 0)]
    if depth.size == 0:
        raise InputError(f"{agent_dir}: the first depth map has no valid depth")
    return float(np.median(depth))


def declared_kind(noise: OdometryNoise) -> OdometryKind:
    """The declaration of a simulated odometry (:mod:`.odometry_kind`): ``vio`` when its
    start is off in scale, else ``metric``; the start's size is left to the configuration
    (``decentralized.vio_start_scale_error``, which the ``vio`` preset's start matches)."""
    return OdometryKind("vio" if noise.initial_scale_error > 0 else "metric")


def add_odometry(
    agent_dir: str | Path,
    seed: int,
    params: OdometryNoise | str | None = None,
    scene_depth: float | None = None,
) -> Path:
    """Write ``odometry.txt`` (TUM) into an agent folder that has ``groundtruth.txt``, and
    beside it ``odometry.json``, the declaration of its kind (:func:`declared_kind`).

    Args:
        agent_dir: an agent input folder, e.g. one written by ``como3r synth``.
        seed: random seed of the odometry errors (use a different one per robot).
        params: odometry model, or the name of one of :data:`ODOMETRY_PRESETS`; ``vio``
            when None.
        scene_depth: the model's unit of length (module docstring); when None, the median
            depth of the folder's first depth map (:func:`scene_depth_of`).

    Returns:
        The written file.

    Raises:
        InputError: the folder or its ``groundtruth.txt`` is missing or malformed, an
            unknown preset name, or no ``scene_depth`` and no depth map.
    """
    if isinstance(params, str):
        if params not in ODOMETRY_PRESETS:
            raise InputError(
                f"unknown odometry model {params!r} (valid: {', '.join(ODOMETRY_PRESETS)})"
            )
        params = ODOMETRY_PRESETS[params]
    agent_dir = Path(agent_dir)
    gt_file = agent_dir / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(f"{agent_dir}: no groundtruth.txt to simulate odometry from")
    if scene_depth is None:
        scene_depth = scene_depth_of(agent_dir)
    params = params or OdometryNoise()
    odometry = simulate_odometry(read_tum(gt_file), seed, params, scene_depth=scene_depth)
    path = agent_dir / ODOMETRY_FILE
    write_tum(path, odometry.timestamps, odometry.T_WC)
    write_odometry_kind(agent_dir, declared_kind(params))
    return path
