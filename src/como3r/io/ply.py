"""Binary PLY point clouds with colour and a per-point agent id (manual: docs/outputs.md,
"Run output").

The header declares ``x y z`` (float32), ``red green blue`` (uchar) and ``agent_id``
(ushort), binary little-endian, which Open3D, CloudCompare and MeshLab read: 17 bytes a
point. Files written before, with an ``int`` agent id (19 bytes a point), are read as well.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from como3r.errors import InputError

_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("agent_id", "<u2"),
    ]
)
#: the vertex layout of earlier files (agent id as int32)
_OLD_VERTEX = np.dtype(
    [*((n, _VERTEX.fields[n][0]) for n in _VERTEX.names[:-1]), ("agent_id", "<i4")]
)
#: the agent ids a file can hold
MAX_AGENT_ID = int(np.iinfo(np.uint16).max)
#: the header :func:`write_ply` writes is about 250 bytes
_MAX_HEADER = 4096


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray, agent_id: np.ndarray) -> None:
    """Write ``xyz (N, 3)`` float, ``rgb (N, 3)`` uint8 and ``agent_id (N,)`` int."""
    write_ply_pieces(path, [(xyz, rgb, agent_id)])


def write_ply_pieces(
    path: str | Path, pieces: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> int:
    """Write the vertices of ``pieces`` (each ``xyz (N_k, 3)``, ``rgb (N_k, 3)``,
    ``agent_id (N_k,)`` as in :func:`write_ply`) one after the other, each let go once
    written: a map of any size is written in the memory of its largest piece. The vertices
    go to a temporary file next to ``path`` first (the header holds their count). Returns
    the number of vertices."""
    path = Path(path)
    body = path.with_name(path.name + ".body")
    count = 0
    try:
        with open(body, "wb") as f:
            for xyz, rgb, agent_id in pieces:
                f.write(_vertices(xyz, rgb, agent_id).tobytes())
                count += xyz.shape[0]
        header = (
            "ply\nformat binary_little_endian 1.0\n"
            f"element vertex {count}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            "property ushort agent_id\nend_header\n"
        )
        with open(path, "wb") as f, open(body, "rb") as vertices:
            f.write(header.encode("ascii"))
            shutil.copyfileobj(vertices, f)
    finally:
        body.unlink(missing_ok=True)
    return count


def _vertices(xyz: np.ndarray, rgb: np.ndarray, agent_id: np.ndarray) -> np.ndarray:
    n = xyz.shape[0]
    if xyz.shape != (n, 3) or rgb.shape != (n, 3) or agent_id.shape != (n,):
        raise ValueError(
            f"write_ply: shapes {xyz.shape}, {rgb.shape}, {agent_id.shape} "
            f"are not (N, 3), (N, 3), (N,)"
        )
    vertices = np.empty(n, dtype=_VERTEX)
    for axis, name in enumerate("xyz"):
        vertices[name] = xyz[:, axis]
    for channel, name in enumerate(("red", "green", "blue")):
        vertices[name] = rgb[:, channel]
    if n and (int(np.min(agent_id)) < 0 or int(np.max(agent_id)) > MAX_AGENT_ID):
        raise ValueError(f"write_ply: agent ids must be in [0, {MAX_AGENT_ID}]")
    vertices["agent_id"] = agent_id
    return vertices


def read_ply(path: str | Path) -> np.ndarray:
    """Read a PLY written by :func:`write_ply` (or an earlier one, with int32 agent ids) as a
    structured array of this version's vertex layout."""
    count, offset, dtype = _layout(path)
    with open(path, "rb") as f:
        f.seek(offset)
        return _current(np.fromfile(f, dtype=dtype, count=count))


def iter_ply(path: str | Path, chunk: int = 1 << 20) -> Iterator[np.ndarray]:
    """The vertices of a PLY written by :func:`write_ply`, ``chunk`` at a time, in file
    order (a map of any size is read in constant memory)."""
    count, offset, dtype = _layout(path)
    with open(path, "rb") as f:
        f.seek(offset)
        for start in range(0, count, chunk):
            yield _current(np.fromfile(f, dtype=dtype, count=min(chunk, count - start)))


def _current(vertices: np.ndarray) -> np.ndarray:
    """``vertices`` in :data:`_VERTEX`'s layout (earlier files' int32 agent ids narrowed)."""
    if vertices.dtype == _VERTEX:
        return vertices
    return vertices.astype(_VERTEX)


def _layout(path: str | Path) -> tuple[int, int, np.dtype]:
    """``(vertex count, byte offset of the first vertex, vertex dtype)`` of a
    :func:`write_ply` file, this version's or an earlier one's.

    Raises:
        InputError: not such a file, or one whose size disagrees with its header.
    """
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
    marker = b"end_header\n"
    end = head.find(marker)
    if not head.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    header = head[:end].decode("ascii", errors="replace").splitlines()
    count = next(
        (int(line.split()[2]) for line in header if line.startswith("element vertex")), None
    )
    if count is None or "format binary_little_endian 1.0" not in header:
        raise InputError(f"{path}: not a binary little-endian PLY with vertices")
    kind = next((line.split()[1] for line in header if line.endswith(" agent_id")), None)
    dtype = {"ushort": _VERTEX, "int": _OLD_VERTEX}.get(str(kind))
    if dtype is None:
        raise InputError(f"{path}: not a como3r map (no ushort or int agent_id property)")
    offset = end + len(marker)
    size = Path(path).stat().st_size - offset
    if size != count * dtype.itemsize:
        raise InputError(f"{path}: truncated PLY ({size} bytes for {count} vertices)")
    return count, offset, dtype
