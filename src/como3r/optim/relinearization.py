"""Dense edges linearized again only where their relative pose moved (a relinearization
threshold, as iSAM2's; Kaess et al., IJRR 2012, Sec. 5).

A Gauss-Newton solve over dense pointmap edges (C-Eq. 5) linearizes every match of every
edge at every iteration, while most edges' relative poses hardly move between iterations:
on the dashboard's 4-agent scene two thirds of the global BA's edge linearizations were at
a relative pose within 1e-3 (radians, nepers, scene depths) of the edge's previous one.
:class:`ThresholdRelinearized` keeps, per edge, the Gauss-Newton blocks of its last dense
linearization as a quadratic model in its relative pose
(:class:`~como3r.optim.factors.QuadraticEdges`: IRLS weights held, gradient moved by ``H
delta``) and linearizes an edge's matches again only when its relative pose is more than
``tol`` from the model's. Not in the paper; ``tol = 0`` is its dense solve.
"""

from __future__ import annotations

import torch

from como3r.errors import InputError
from como3r.optim.factors import QuadraticEdges, RelativePoseFactors, endpoint_blocks
from como3r.optim.linear import EdgeBlocks


class ThresholdRelinearized:
    """A dense factor batch whose edges are linearized again only past a motion threshold
    (a Factor).

    Args:
        factors: the dense edges.
        tol: an edge is linearized again when its relative pose ``T_ij`` is more than this
            from the one of its model: rotation and log-scale in radians and nepers,
            translation in units of ``length``; 0 linearizes every edge that moved.
        length: the scene's length unit (e.g. its median keyframe depth), so the
            threshold holds at every scale.
    """

    def __init__(self, factors: RelativePoseFactors, tol: float, length: float) -> None:
        if not (tol >= 0 and length > 0):
            raise InputError(f"ThresholdRelinearized: tol ({tol}) must be >= 0 and length "
                             f"({length}) positive")
        self.factors, self.tol, self.length = factors, float(tol), float(length)
        self._model: QuadraticEdges | None = None
        self.linearized = 0  # edge linearizations over the matches, so far

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to."""
        return self.factors.max_pose_index

    def linearize(self, poses: torch.Tensor) -> EdgeBlocks:
        """Per-edge blocks at ``poses`` ``(N, 8)``: the matches' for the edges that moved
        past the threshold (their models made again), the models' for the others."""
        stale = self._stale(poses)
        model = self._model
        for chunk in self.factors.chunks(poses):
            for run in _runs(stale[chunk]):
                edges = slice(chunk.start + run.start, chunk.start + run.stop)
                model.T0[edges], model.H[edges], model.g[edges] = (
                    self.factors.relative_blocks(poses, edges))
                self.linearized += edges.stop - edges.start
        delta = model.motion(poses)
        delta[stale] = 0.0  # just linearized there: the dense blocks exactly
        g_rel = model.g + (model.H @ delta[..., None])[..., 0]
        return endpoint_blocks(model.i, model.j, model.H, g_rel, poses[model.i])

    def cost(self, poses: torch.Tensor) -> torch.Tensor:
        """The dense edges' robust energy at ``poses`` ``(N, 8)`` (no model), float64."""
        return self.factors.cost(poses)

    def _stale(self, poses: torch.Tensor) -> torch.Tensor:
        """``(E,)`` bool: the edges to linearize again at ``poses`` (all, at the first call)."""
        E = self.factors.num_edges
        if self._model is None:
            zeros = torch.zeros(E, dtype=torch.float64, device=poses.device)
            self._model = QuadraticEdges(
                self.factors.i, self.factors.j, zeros.new_zeros(E, 8), zeros.new_zeros(E, 7, 7),
                zeros.new_zeros(E, 7), zeros)
            return torch.ones(E, dtype=torch.bool, device=poses.device)
        moved = self._model.motion(poses).abs()
        moved[:, :3] /= self.length
        return (moved > self.tol).any(1)


def _runs(mask: torch.Tensor) -> list[slice]:
    """The maximal runs of True in a 1-D bool ``mask``, as slices."""
    flags = mask.tolist()
    runs, start = [], None
    for k, flag in enumerate(flags + [False]):
        if flag and start is None:
            start = k
        elif not flag and start is not None:
            runs.append(slice(start, k))
            start = None
    return runs
