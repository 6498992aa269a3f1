"""Binary PLY point clouds with colour and a per-point agent id (README, "Run output").

The header declares ``x y z`` (float32), ``red green blue`` (uchar) and ``agent_id``
(int32), binary little-endian, which Open3D, CloudCompare and MeshLab read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from como3r.errors import InputError

_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                    ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("agent_id", "<i4")])


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray, agent_id: np.ndarray) -> None:
    """Write ``xyz (N, 3)`` float, ``rgb (N, 3)`` uint8 and ``agent_id (N,)`` int."""
    n = xyz.shape[0]
    if xyz.shape != (n, 3) or rgb.shape != (n, 3) or agent_id.shape != (n,):
        raise ValueError(f"write_ply: shapes {xyz.shape}, {rgb.shape}, {agent_id.shape} "
                         f"are not (N, 3), (N, 3), (N,)")
    vertices = np.empty(n, dtype=_VERTEX)
    for axis, name in enumerate("xyz"):
        vertices[name] = xyz[:, axis]
    for channel, name in enumerate(("red", "green", "blue")):
        vertices[name] = rgb[:, channel]
    vertices["agent_id"] = agent_id
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property int agent_id\nend_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertices.tobytes())


def read_ply(path: str | Path) -> np.ndarray:
    """Read a PLY written by :func:`write_ply` as a structured array."""
    data = Path(path).read_bytes()
    marker = b"end_header\n"
    end = data.find(marker)
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    count = next((int(line.split()[2]) for line in header if line.startswith("element vertex")),
                 None)
    if count is None or "format binary_little_endian 1.0" not in header:
        raise InputError(f"{path}: not a binary little-endian PLY with vertices")
    body = data[end + len(marker):]
    if len(body) != count * _VERTEX.itemsize:
        raise InputError(f"{path}: truncated PLY ({len(body)} bytes for {count} vertices)")
    return np.frombuffer(body, dtype=_VERTEX)
