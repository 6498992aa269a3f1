"""The keyframe pose graph of a finished run as a g2o file (``como3r export --g2o``; manual:
docs/commands/export.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from como3r.geometry.lie import se3_compose, se3_inverse
from como3r.io.run_graph import RunGraph

#: the first line of every g2o file como3r writes (``--overwrite`` replaces only such a file)
G2O_HEADER = "# como3r keyframe pose graph"


def write_g2o(graph: RunGraph, path: Path) -> dict[str, int]:
    """The keyframe pose graph as a g2o file (3-D, ``types_slam3d``).

    ``VERTEX_SE3:QUAT id tx ty tz qx qy qz qw`` per keyframe (id = its index in
    ``graph.json``'s ``keyframes``; the rigid camera-to-world pose, world units); ``FIX id``
    for the first keyframe of each gauge component; ``EDGE_SE3:QUAT i j`` and the relative
    pose ``T_i^-1 T_j`` per edge ``graph.json`` lists (sequential, inter-agent, loop; an edge
    marked ``"accepted": false`` is left out), then the upper triangle of its 6x6 information
    matrix in g2o's order (translation, then rotation), row by row.

    ``graph.json`` stores the final poses but not the pairwise measurements the solver used,
    so each measurement is the relative pose of the final estimates (a graph at rest), and
    the information matrix is ``w I_6`` with ``w`` = :func:`~como3r.io.run_graph.edge_weight`: a relative weight by
    how much of the pair matched, not a calibrated covariance. Lines starting with ``#`` are
    comments (g2o and GTSAM's ``readG2o`` skip them).

    Returns:
        counts: ``vertices``, ``edges``.
    """
    lines = [
        G2O_HEADER,
        "# vertices: keyframes in graph.json order (agent, keyframe id in the comment above "
        "each); poses: rigid camera-to-world, world units; information: w I_6, w = the "
        "edge's match fraction",
    ]
    for kf in graph.keyframes:
        lines.append(
            f"# agent {kf.agent} keyframe {kf.kf_id} frame {kf.frame} "
            f"timestamp {kf.timestamp!r} scale {float(kf.T_WC[7])!r}"
        )
        lines.append(f"VERTEX_SE3:QUAT {kf.index} " + _numbers(kf.T_WC[:7]))
    for component in graph.components:
        first = next((k for k in graph.keyframes if k.agent in component), None)
        if first is not None:
            lines.append(f"FIX {first.index}")
    for edge in graph.edges:
        i, j = graph.keyframes[edge.i], graph.keyframes[edge.j]
        relative = se3_compose(se3_inverse(i.rigid), j.rigid).numpy()
        information = edge.weight * np.eye(6)
        lines.append(
            f"EDGE_SE3:QUAT {i.index} {j.index} "
            + _numbers(relative)
            + " "
            + _numbers(information[np.triu_indices(6)])
        )
    path.write_text("\n".join(lines) + "\n")
    return {"vertices": len(graph.keyframes), "edges": len(graph.edges)}


def _numbers(values: np.ndarray) -> str:
    return " ".join(repr(float(v) + 0.0) for v in values)  # + 0.0: no "-0.0"
