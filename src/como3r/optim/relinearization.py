"""Dense edges linearized again only where their relative pose moved (a relinearization
threshold, as iSAM2's; Kaess et al., IJRR 2012, Sec. 5).

A Gauss-Newton solve over dense pointmap edges (C-Eq. 5) linearizes every match of every
edge at every iteration, and the coordinator solves its whole graph again after every new
inter-agent edge, while most edges' relative poses hardly move: on the dashboard's
4-agent scene two thirds of the global BA's edge linearizations within one solve were at a
relative pose within 1e-3 (radians, nepers, scene depths) of the edge's previous one.

:class:`EdgeModels` keeps, per edge, the Gauss-Newton blocks of its last dense
linearization as a quadratic model in its relative pose
(:class:`~como3r.optim.factors.QuadraticEdges`: IRLS weights held, gradient moved by ``H
delta``), stamped with the versions of the endpoints' pointmaps it was made from, between
solves. A solve's :class:`ThresholdRelinearized` factor takes an edge's blocks from its
model while the stamp holds and the relative pose is within ``tol`` of the model's, and
otherwise builds the edge's dense factors (once per solve, for the edges that need them)
and linearizes its matches again. Not in the paper; ``tol = 0`` is its dense solve.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import torch

from como3r.errors import InputError
from como3r.geometry.lie import sim3_identity
from como3r.optim.factors import QuadraticEdges, RelativePoseFactors, endpoint_blocks
from como3r.optim.system import EdgeBlocks

#: builds the dense factors of some of a solve's edges (positions in its edge list) as
#: factor batches, each with the positions of its edges in batch order; each batch's pose
#: indices are the solve's rows
DenseBuilder = Callable[[Sequence[int]], Sequence[tuple[RelativePoseFactors, Sequence[int]]]]

#: bytes of dense factors a solve keeps for its later linearizations; the edges built past
#: them are built again when they are linearized again. Issue 41: kept for every edge, the
#: in-stream global BA of a 16-agent map held 93 / 688 / 1988 MB of them at 41 / 100 / 190
#: keyframes (2.4-5 MB an edge at 512x384), the peak memory of its batch growing with the map
KEEP_DENSE_BYTES = 256 * 2**20
#: stale edges built and linearized together: what a linearization holds beyond the kept
#: factors (at most this many edges' dense factors)
BUILD_GROUP = 32


@dataclass(frozen=True)
class _Model:
    """One edge's blocks in the tangent of its relative pose ``T0`` (float64)."""

    T0: torch.Tensor  # (8,)
    H: torch.Tensor  # (7, 7)
    g: torch.Tensor  # (7,)
    stamp: Hashable  # the endpoints' pointmap versions it was made from


class EdgeModels:
    """Quadratic models of edges kept between solves, by the caller's edge key (65 floats
    per edge, whatever its matches)."""

    def __init__(self) -> None:
        self._models: dict[Hashable, _Model] = {}

    def __len__(self) -> int:
        return len(self._models)

    def get(self, key: Hashable, stamp: Hashable) -> _Model | None:
        """The model of edge ``key`` if it was made at ``stamp``."""
        model = self._models.get(key)
        return model if model is not None and model.stamp == stamp else None

    def put(self, key: Hashable, model: _Model) -> None:
        self._models[key] = model


class ThresholdRelinearized:
    """A solve's dense edges, linearized over their matches only past a motion threshold
    (a Factor).

    Args:
        i, j: ``(E,)`` pose indices (rows of the solve) of the edges.
        keys: the edges' keys in ``models``; stamps: their endpoints' pointmap versions.
        models: the kept models (updated as edges are linearized again).
        build: makes the dense factors of edges by position (:data:`DenseBuilder`).
        tol: an edge is linearized again when its relative pose ``T_ij`` is more than this
            from its model's: rotation and log-scale in radians and nepers, translation in
            units of ``length``; 0 linearizes every edge that moved.
        length: the scene's length unit (e.g. its median keyframe depth), so the
            threshold holds at every scale.
        keep_bytes: dense factors kept between linearizations (:data:`KEEP_DENSE_BYTES`);
            the results do not depend on it, only memory and time do.
    """

    def __init__(
        self,
        i: torch.Tensor,
        j: torch.Tensor,
        keys: Sequence[Hashable],
        stamps: Sequence[Hashable],
        models: EdgeModels,
        build: DenseBuilder,
        tol: float,
        length: float,
        keep_bytes: int = KEEP_DENSE_BYTES,
    ) -> None:
        if not (tol >= 0 and length > 0):
            raise InputError(
                f"ThresholdRelinearized: tol ({tol}) must be >= 0 and length ({length}) positive"
            )
        if not (len(i) == len(j) == len(keys) == len(stamps)):
            raise InputError(
                "ThresholdRelinearized: i, j, keys and stamps must have one entry per edge"
            )
        self.keys, self.stamps, self.models, self.build = list(keys), list(stamps), models, build
        self.tol, self.length = float(tol), float(length)
        E, device = len(self.keys), i.device
        kept = [models.get(k, s) for k, s in zip(self.keys, self.stamps)]
        self._known = torch.tensor([m is not None for m in kept], dtype=torch.bool, device=device)

        def stacked(name: str, empty: torch.Tensor) -> torch.Tensor:
            rows = [(getattr(m, name) if m is not None else empty).to(device) for m in kept]
            return torch.stack(rows) if rows else empty[None][:0].to(device)

        self._quadratic = QuadraticEdges(
            i.to(torch.int64),
            j.to(torch.int64),
            stacked("T0", sim3_identity(dtype=torch.float64)),
            stacked("H", torch.zeros(7, 7, dtype=torch.float64)),
            stacked("g", torch.zeros(7, dtype=torch.float64)),
            torch.zeros(E, dtype=torch.float64, device=device),
        )
        # edge position -> (its dense batch, its row there); built when first needed, kept
        # while the kept batches' bytes stay within keep_bytes
        self._dense: dict[int, tuple[RelativePoseFactors, int]] = {}
        self.keep_bytes, self._kept_bytes = keep_bytes, 0
        self.linearized = 0  # edge linearizations over the matches, so far
        self.reused = int(self._known.sum())  # edges that came with a model

    @property
    def max_pose_index(self) -> int:
        """The largest pose index any edge refers to."""
        return self._quadratic.max_pose_index

    @property
    def num_edges(self) -> int:
        """E, the number of edges."""
        return len(self.keys)

    def linearize(self, poses: torch.Tensor) -> EdgeBlocks:
        """Per-edge blocks at ``poses`` ``(N, 8)``: the matches' for the edges without a
        model or moved past the threshold (their models made again), the models' for the
        others."""
        model = self._quadratic
        delta = model.motion(poses)
        moved = delta.abs()
        moved[:, :3] /= self.length
        stale = ~self._known | (moved > self.tol).any(1)
        for batch, rows, positions in self._groups(torch.nonzero(stale).flatten().tolist()):
            for first, last in _runs(rows, batch.chunks(poses)):
                edges = slice(rows[first], rows[last - 1] + 1)
                at = positions[first:last]
                model.T0[at], model.H[at], model.g[at] = batch.relative_blocks(poses, edges)
            for p in positions:
                self.models.put(
                    self.keys[p],
                    _Model(
                        model.T0[p].clone(), model.H[p].clone(), model.g[p].clone(), self.stamps[p]
                    ),
                )
            self.linearized += len(positions)
        self._known[stale] = True
        # the others kept their T0, so their motion is still delta; the stale ones were
        # just linearized at these poses: the dense blocks exactly
        delta[stale] = 0.0
        g_rel = model.g + (model.H @ delta[..., None])[..., 0]
        return endpoint_blocks(model.i, model.j, model.H, g_rel, poses[model.i])

    def cost(self, poses: torch.Tensor) -> torch.Tensor:
        """The dense edges' robust energy at ``poses`` ``(N, 8)`` (no model), float64."""
        total = torch.zeros((), dtype=torch.float64, device=poses.device)
        for batch, rows, _ in self._groups(list(range(self.num_edges))):
            # a batch (kept from an earlier linearization) may hold edges of other groups
            for first, last in _runs(rows, batch.chunks(poses)):
                total = (
                    total + batch.edge_costs(poses, slice(rows[first], rows[last - 1] + 1)).sum()
                )
        return total

    def _groups(
        self, positions: list[int]
    ) -> Iterator[tuple[RelativePoseFactors, list[int], list[int]]]:
        """:meth:`_batches` of ``positions`` :data:`BUILD_GROUP` at a time, so that the
        factors built past ``keep_bytes`` are let go of group by group."""
        for start in range(0, len(positions), BUILD_GROUP):
            yield from self._batches(positions[start : start + BUILD_GROUP])

    def _batches(
        self, positions: list[int]
    ) -> list[tuple[RelativePoseFactors, list[int], list[int]]]:
        """``positions`` grouped by dense batch (built for those that have none, and kept
        while the kept batches fit ``keep_bytes``), each group's rows in its batch
        ascending: ``(batch, rows, positions)``."""
        groups: dict[int, tuple[RelativePoseFactors, list[tuple[int, int]]]] = {}

        def add(batch: RelativePoseFactors, row: int, p: int) -> None:
            groups.setdefault(id(batch), (batch, []))[1].append((row, p))

        missing = [p for p in positions if p not in self._dense]
        for p in positions:
            if p in self._dense:
                add(*self._dense[p], p)
        wanted = set(missing)
        for batch, built in self.build(missing) if missing else ():
            size = tensor_bytes(vars(batch).values())
            keep = self._kept_bytes + size <= self.keep_bytes
            self._kept_bytes += size if keep else 0
            for row, p in enumerate(built):
                if keep:
                    self._dense[p] = (batch, row)
                if p in wanted:
                    add(batch, row, p)
        result = []
        for batch, pairs in groups.values():
            pairs.sort()
            result.append((batch, [r for r, _ in pairs], [p for _, p in pairs]))
        return result


def tensor_bytes(values: Iterable[object]) -> int:
    """Bytes of the tensors among ``values`` (each storage once; other values ignored)."""
    storages = {
        t.untyped_storage().data_ptr(): t.untyped_storage().nbytes()
        for t in values
        if isinstance(t, torch.Tensor)
    }
    return sum(storages.values())


def _runs(rows: list[int], chunks: list[slice]) -> list[tuple[int, int]]:
    """Ascending ``rows`` cut into runs of consecutive rows within one of ``chunks``, as
    ``(first, last)`` index ranges into ``rows``."""
    chunk_of = {r: n for n, c in enumerate(chunks) for r in range(c.start, c.stop)}
    runs: list[tuple[int, int]] = []
    for k, r in enumerate(rows):
        if runs and rows[k - 1] == r - 1 and chunk_of[r] == chunk_of[r - 1]:
            runs[-1] = (runs[-1][0], k + 1)
        else:
            runs.append((k, k + 1))
    return runs
