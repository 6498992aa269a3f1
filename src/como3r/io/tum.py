"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

Poses are returned in como3r's Sim(3) layout ``(N, 8)``: translation, unit quaternion
(x, y, z, w), scale (1 for a TUM file). Writing drops the scale: TUM stores the camera
position and orientation, which is what a Sim(3) camera pose ``T_WC`` gives directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from como3r.errors import InputError


@dataclass(frozen=True)
class Trajectory:
    """Timestamped camera poses.

    Attributes:
        timestamps: ``(N,)`` float64 seconds, strictly increasing.
        T_WC: ``(N, 8)`` float64 poses (t, q_xyzw, s).
    """

    timestamps: np.ndarray
    T_WC: Tensor

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame."""
        return self.T_WC[:, :3].cpu().numpy()


def parse_tum_line(line: str, path: Path, line_no: int) -> list[float] | None:
    """Eight finite numbers of one TUM line, or None for a blank or comment line."""
    text = line.split("#", 1)[0].strip()
    if not text:
        return None
    parts = text.replace(",", " ").split()
    if len(parts) != 8:
        raise InputError(
            f"{path}:{line_no}: expected 8 numbers (timestamp tx ty tz qx qy qz qw), "
            f"got {len(parts)}"
        )
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{path}:{line_no}: not a number in {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{path}:{line_no}: non-finite value in {text!r}")
    q_norm = math.sqrt(sum(v * v for v in values[4:8]))
    if abs(q_norm - 1.0) > 1e-2:
        raise InputError(f"{path}:{line_no}: quaternion norm {q_norm:.4f} is not 1")
    return values


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; malformed lines raise :class:`InputError` naming the line."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise InputError(f"{path}: cannot read trajectory ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    rows = [r for i, line in enumerate(lines, 1) if (r := parse_tum_line(line, path, i))]
    if not rows:
        raise InputError(f"{path}: no poses in trajectory file")
    data = np.asarray(rows, dtype=np.float64)
    stamps = data[:, 0]
    if np.any(np.diff(stamps) <= 0):
        bad = int(np.argmax(np.diff(stamps) <= 0)) + 1
        raise InputError(f"{path}: timestamps are not strictly increasing (pose {bad + 1})")
    q = data[:, 4:8] / np.linalg.norm(data[:, 4:8], axis=1, keepdims=True)
    T_WC = np.concatenate([data[:, 1:4], q, np.ones((len(data), 1))], axis=1)
    return Trajectory(timestamps=stamps, T_WC=torch.from_numpy(T_WC))


def write_tum(path: str | Path, timestamps: np.ndarray, T_WC: Tensor) -> None:
    """Write ``(N,)`` timestamps and ``(N, 8)`` (or ``(N, 7)``) poses as a TUM file."""
    poses = T_WC.detach().to("cpu", torch.float64).numpy()
    stamps = np.asarray(timestamps, dtype=np.float64)
    if poses.shape[0] != stamps.shape[0]:
        raise ValueError(f"{poses.shape[0]} poses but {stamps.shape[0]} timestamps")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for stamp, pose in zip(stamps, poses):
            f.write(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in pose[:7]) + "\n")
