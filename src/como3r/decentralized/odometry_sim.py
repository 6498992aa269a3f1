"""A visual-inertial-like odometry model for synthetic robots (``odometry.txt``).

FLOCC-SLAM assumes every robot brings a locally consistent metric odometry (F-Sec. III) and
observes that monocular VIO is off in scale where its online scale estimate has not yet
converged, at the start of a trajectory (F-Sec. IV-C). :func:`simulate_odometry` turns a
ground-truth trajectory into such an odometry by integrating the true displacements with

* a scale ``lambda(d) = (1 + e0 exp(-d / L_conv)) (1 + b(d))`` of the distance travelled
  ``d``: an unconverged start ``e0`` (random sign, magnitude ``initial_scale_error``) that
  decays over ``scale_convergence_m``, times a slowly varying error ``b`` (an
  Ornstein-Uhlenbeck process over distance, standard deviation ``scale_drift``, correlation
  length ``scale_correlation_m``);
* a heading drift ``psi(d)`` about the gravity axis (world z; roll and pitch are observable
  from gravity and do not drift): a constant rate of ``yaw_drift_deg_per_m`` with a random
  sign plus a random walk of ``yaw_walk_deg_per_sqrt_m``;
* a translation random walk of ``translation_walk_m_per_sqrt_m``.

The odometry is expressed in its own gravity-aligned frame: the world turned by a random
yaw about z and moved to the first camera position, so robots do not share a frame.

Two presets mirror the paper's two backbones (F-Tables II-III): ``vio`` (monocular VIO such
as VINS-Mono: 30 % scale error at the start, converged after about 2 m, drifting heading)
and ``lio`` (LiDAR-inertial odometry: near-perfect scale, little drift).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from como3r.errors import InputError
from como3r.io.tum import Trajectory, read_tum, write_tum

ODOMETRY_FILE = "odometry.txt"


@dataclass(frozen=True)
class OdometryNoise:
    """Parameters of the odometry model (module docstring); lengths in metres."""

    initial_scale_error: float = 0.3
    scale_convergence_m: float = 2.0
    scale_drift: float = 0.02
    scale_correlation_m: float = 5.0
    yaw_drift_deg_per_m: float = 0.3
    yaw_walk_deg_per_sqrt_m: float = 0.1
    translation_walk_m_per_sqrt_m: float = 0.005


ODOMETRY_PRESETS: dict[str, OdometryNoise] = {
    "vio": OdometryNoise(),
    "lio": OdometryNoise(initial_scale_error=0.0, scale_drift=0.005, yaw_drift_deg_per_m=0.05,
                         yaw_walk_deg_per_sqrt_m=0.02, translation_walk_m_per_sqrt_m=0.002),
}
"""Odometry models by name (module docstring)."""


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def simulate_odometry(groundtruth: Trajectory, seed: int,
                      noise: OdometryNoise | None = None) -> Trajectory:
    """Odometry of a robot that moved along ``groundtruth`` (module docstring).

    Args:
        groundtruth: ``N`` true camera poses ``T_WC`` (world z up).
        seed: random seed; the same seed gives the same odometry.
        noise: model parameters; the defaults when None.

    Returns:
        ``N`` odometry poses ``T_OC`` (scale 1) with the ground truth's timestamps.
    """
    noise = noise or OdometryNoise()
    rng = np.random.default_rng(seed)
    poses = groundtruth.T_WC.detach().cpu().double().numpy()
    positions = poses[:, :3]
    rotations = Rotation.from_quat(poses[:, 3:7]).as_matrix()
    steps = np.diff(positions, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(lengths)])

    start_error = noise.initial_scale_error * rng.choice([-1.0, 1.0])
    yaw_rate = np.radians(noise.yaw_drift_deg_per_m) * rng.choice([-1.0, 1.0])
    yaw_walk = np.radians(noise.yaw_walk_deg_per_sqrt_m)
    drift = 0.0
    heading = 0.0
    est_positions = np.zeros_like(positions)
    est_rotations = np.empty_like(rotations)
    est_positions[0], est_rotations[0] = positions[0], rotations[0]
    for k in range(1, len(positions)):
        length = lengths[k - 1]
        decay = np.exp(-length / noise.scale_correlation_m)
        drift = decay * drift + noise.scale_drift * np.sqrt(1.0 - decay**2) * rng.standard_normal()
        scale = (1.0 + start_error * np.exp(-travelled[k] / noise.scale_convergence_m)) * (1 + drift)
        heading += yaw_rate * length + yaw_walk * np.sqrt(length) * rng.standard_normal()
        turn = _yaw(heading)
        walk = noise.translation_walk_m_per_sqrt_m * np.sqrt(length) * rng.standard_normal(3)
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


def add_odometry(agent_dir: str | Path, seed: int,
                 params: OdometryNoise | str | None = None) -> Path:
    """Write ``odometry.txt`` (TUM) into an agent folder that has ``groundtruth.txt``.

    Args:
        agent_dir: an agent input folder, e.g. one written by ``como3r synth``.
        seed: random seed of the odometry errors (use a different one per robot).
        params: odometry model, or the name of one of :data:`ODOMETRY_PRESETS`; ``vio``
            when None.

    Returns:
        The written file.

    Raises:
        InputError: the folder or its ``groundtruth.txt`` is missing or malformed, or an
            unknown preset name.
    """
    if isinstance(params, str):
        if params not in ODOMETRY_PRESETS:
            raise InputError(f"unknown odometry model {params!r} (valid: "
                             f"{', '.join(ODOMETRY_PRESETS)})")
        params = ODOMETRY_PRESETS[params]
    agent_dir = Path(agent_dir)
    gt_file = agent_dir / "groundtruth.txt"
    if not gt_file.is_file():
        raise InputError(f"{agent_dir}: no groundtruth.txt to simulate odometry from")
    odometry = simulate_odometry(read_tum(gt_file), seed, params)
    path = agent_dir / ODOMETRY_FILE
    write_tum(path, odometry.timestamps, odometry.T_WC)
    return path
