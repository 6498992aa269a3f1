"""The depth step of the terminal alternation over working sets of keyframes (issue 14,
bounded memory; C-Sec. A.7 steps 2b-2c, C-Eq. 19-24).

:func:`~como3r.backend.depth_refinement.refine_depths` flattens every keyframe's pixels and
every match of a map into one problem: about 0.6 MB per keyframe at 64x48, most of it the
matches, and a hundred times that at 512x384, all at once. The Newton step of C-Eq. 24 does
not need that problem whole. Its Hessian is diagonal (Jacobi decoupling) and its gradient
exact, so both are sums over matches, and the boundary (C-Eq. 22) and prior (C-Eq. 23)
terms stay inside each keyframe. :func:`refine_in_chunks` runs the same iterations as
``refine_depths`` and adds up the data term of C-Eq. 21 one :class:`Chunk` of edges at a
time. A chunk's keyframes and matches are read when the chunk is built and let go after it:
a paged-out keyframe is read back from the session store (or the cleanup's parking,
:class:`~como3r.frontend.paging.KeyframeParking`) and not kept. Nothing a chunk's problem
holds changes during the step (poses frozen, reads before writes), and building it costs
about ten times the pass's sums over it (store reads and decompression, norms, rays, match gathers,
median ranges): rebuilding every chunk at each of the step's ``inner_iters + 1`` passes made
a 14-keyframe map's depth steps 3.8x slower. So each chunk is built once per step, at the
first pass: one whose keyframes are all in memory anyway keeps its problem for the step
(``keep``) while the kept problems fit :data:`KEEP_PROBLEM_BYTES`, any other is written raw
to a :class:`ProblemSpill` and read back whole at the later passes, so that memory holds one
such problem at a time. Only the log-scales
``s (M,)``, their warm start and the boundary pairs stay in memory for the whole step. Each
keyframe holds a few hundred of them.

A keyframe's refined pointmap goes to a ``write`` callback (an unpaged keyframe takes it in
memory, a paged-out one is parked). Reads happen before writes: the data passes read the
pointmaps as they were when the step started, as the whole problem does.

The results equal ``refine_depths``'s up to the order in which the data term is summed
(float rounding). The chunks depend on the graph only (:data:`KEYFRAMES_PER_CHUNK`
consecutive keyframes by their largest endpoint), not on what is in memory, so a paged run
and an unpaged run give identical results.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from functools import partial
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from como3r.backend.cpu_kernels import MatchStreams, depth_normal_equations
from como3r.backend.depth_problem import Problem, build_problem, chunk_streams
from como3r.backend.depth_refinement import (
    HUBER_K,
    DepthRefinementReport,
    _check_inputs,
    _Refiner,
    damped_step,
    regularised,
    written_back,
)
from como3r.config import DepthRefinementConfig
from como3r.frontend.graph import Edge
from como3r.frontend.paging import KeyframeParking, KeyframeSpill
from como3r.geometry.units import median_range
from como3r.optim.relinearization import tensor_bytes

logger = logging.getLogger(__name__)

#: Keyframes per working set of the depth step: a chunk holds the edges whose later endpoint
#: is one of this many consecutive keyframes (the session's default resident count).
KEYFRAMES_PER_CHUNK = 8
#: Bytes of flattened chunk problems a depth step keeps in memory (chunks of resident
#: keyframes, first come); the others are spilled. Issue 41: a 16-agent team keeps 8
#: keyframes of each agent resident, 128 of its 190 at the end of a long mission, and the
#: step kept their problems (64 bytes a match, about 11 MB a link at 512x384): the
#: coordinator's peak memory rose 7.9 -> 12.1 GB in the terminal cleanup's depth step
KEEP_PROBLEM_BYTES = 256 * 2**20


@dataclass(frozen=True)
class Pointmaps:
    """What the depth step reads of a keyframe (:class:`~.depth_problem.RefinableKeyframe`).

    Attributes:
        X_hat: ``(H, W, 3)`` current canonical pointmap.
        X_init: ``(H, W, 3)`` the frozen base of C-Eq. 19.
    """

    X_hat: Tensor
    X_init: Tensor


@dataclass(frozen=True)
class Chunk:
    """The edges of one working set.

    Attributes:
        rows: the keyframes its edges touch (positions in the refined set), sorted.
        edges: makes its directed edges, their endpoints as rows. Called once per pass, so
            paged-out matches are read back then.
    """

    rows: tuple[int, ...]
    edges: Callable[[], list[Edge]]


def chunk_edges(
    ends: Sequence[tuple[int, int]], make: Callable[[Sequence[int]], list[Edge]]
) -> list[Chunk]:
    """Links grouped into chunks by their later endpoint, :data:`KEYFRAMES_PER_CHUNK`
    keyframes per chunk.

    Args:
        ends: each link's endpoint rows.
        make: the directed edges (endpoints as rows) of the links at the given positions
            in ``ends``.
    """
    groups: dict[int, list[int]] = {}
    for n, (i, j) in enumerate(ends):
        groups.setdefault(max(i, j) // KEYFRAMES_PER_CHUNK, []).append(n)
    return [
        Chunk(tuple(sorted({r for n in links for r in ends[n]})), lambda links=links: make(links))
        for _, links in sorted(groups.items())
    ]


#: a chunk's flattened data problem as kept: the problem, or on CPU the match streams
ChunkData = Problem | MatchStreams
#: a chunk's data term: ``(s, with_blocks) -> (H (M,), g (M,), cost)``
DataTerm = Callable[[Tensor, bool], tuple[Tensor, Tensor, float]]


def _data_problem(*args: object, **kwargs: object) -> Problem:
    """A chunk's data problem (not on a CPU: PyTorch's data term reads it); arguments as for
    :func:`~.depth_problem.chunk_streams`."""
    return build_problem(*args, data_only=True, **kwargs)[0]


def _stream_terms(
    s: Tensor, with_blocks: bool, streams: MatchStreams, huber_k: float
) -> tuple[Tensor, Tensor, float]:
    return depth_normal_equations(s, streams, huber_k, with_blocks)


def _problem_bytes(data: ChunkData) -> int:
    """Bytes of the tensors a chunk's problem holds (each storage once)."""
    return tensor_bytes(getattr(data, f.name) for f in fields(data))


class ProblemSpill:
    """Flattened chunk problems of a depth step in files, one per chunk: a
    :class:`~.depth_problem.Problem` (data term only) or, on CPU, the
    :class:`~como3r.backend.cpu_kernels.MatchStreams` the compiled data term reads. Raw: no
    compression, int64 indices (pixels, matches, log-scales; all below 2**31) as int32, what
    halves them. What is read back has the type and the tensors it was saved with, bit for
    bit (same dtypes and devices).

    The files live in a :class:`~como3r.frontend.paging.KeyframeSpill` folder (removed with
    it, or by a later spill when its process is gone) and are deleted by :meth:`close`.

    Args:
        parent: where the folder is made (None: the system's temporary folder).
    """

    def __init__(self, parent: Path | None = None) -> None:
        self._parent = parent
        self._spill: KeyframeSpill | None = None  # made when something is first saved
        # per chunk: its type, and (field, dtype, device, shape, stored numpy dtype) in file
        # order
        self._layout: dict[
            int, tuple[type, list[tuple[str, torch.dtype, torch.device, tuple[int, ...], np.dtype]]]
        ] = {}
        #: bytes written by the step (its disk use), a figure for the log and tests
        self.bytes = 0

    def __contains__(self, n: int) -> bool:
        return n in self._layout

    def save(self, n: int, problem: ChunkData) -> None:
        """Write chunk ``n``'s problem (a dataclass of tensors)."""
        if self._spill is None:
            self._spill = KeyframeSpill(self._parent)
        layout = []
        with open(self._path(n), "wb") as file:
            for f in fields(problem):
                tensor: Tensor = getattr(problem, f.name)
                array = tensor.detach().cpu().contiguous().numpy()
                if tensor.dtype == torch.int64 and (
                    not tensor.numel()
                    or (int(tensor.min()) >= -(2**31) and int(tensor.max()) < 2**31)
                ):
                    array = array.astype(np.int32)
                array.tofile(file)
                self.bytes += array.nbytes
                layout.append(
                    (f.name, tensor.dtype, tensor.device, tuple(tensor.shape), array.dtype)
                )
        self._layout[n] = (type(problem), layout)

    def load(self, n: int) -> ChunkData:
        """Chunk ``n``'s problem as it was saved."""
        kind, layout = self._layout[n]
        values = {}
        with open(self._path(n), "rb") as file:
            for name, dtype, device, shape, stored in layout:
                array = np.fromfile(file, dtype=stored, count=math.prod(shape))
                values[name] = torch.from_numpy(array).reshape(shape).to(dtype=dtype, device=device)
        return kind(**values)

    def close(self) -> None:
        """Delete the files (the folder goes with the spill)."""
        for n in self._layout:
            self._path(n).unlink(missing_ok=True)
        self._layout.clear()
        self._spill = None

    def _path(self, n: int) -> Path:
        return self._spill.folder / f"chunk{n}.bin"


class LabelMaps(Mapping[int, Tensor]):
    """Label maps (C-Sec. A.6) by keyframe key: in memory, or those of paged-out keyframes
    kept in a :class:`~como3r.frontend.paging.KeyframeParking` (read back when asked for).

    Args:
        park: where parked label maps go (None: all in memory).
    """

    def __init__(self, park: KeyframeParking | None = None) -> None:
        self._park = park
        self._labels: dict[int, Tensor | None] = {}  # None: in the park

    def keep(self, key: int, labels: Tensor, parked: bool) -> None:
        """Keep ``labels (H, W)`` of keyframe ``key``, in the park if ``parked``."""
        if parked and self._park is not None:
            self._park.put(key, "labels", {"labels": labels})
            self._labels[key] = None
        else:
            self._labels[key] = labels

    def __getitem__(self, key: int) -> Tensor:
        labels = self._labels[key]
        return self._park.get(key, "labels")["labels"] if labels is None else labels

    def __iter__(self) -> Iterator[int]:
        return iter(self._labels)

    def __len__(self) -> int:
        return len(self._labels)


def refine_in_chunks(
    count: int,
    read: Callable[[int], Pointmaps],
    poses: Tensor,
    chunks: Sequence[Chunk],
    labels: Callable[[int], Tensor],
    config: DepthRefinementConfig,
    write: Callable[[int, Tensor], None],
    pinned: Iterable[int] = (),
    huber_k: float = HUBER_K,
    keep: Callable[[Sequence[int]], bool] = lambda rows: False,
    spill_dir: Path | None = None,
    keep_bytes: int = KEEP_PROBLEM_BYTES,
) -> DepthRefinementReport:
    """One depth step (C-Eq. 19-24) at frozen poses, its data term summed chunk by chunk.

    Args:
        count: N, the keyframes refined (rows ``0 .. N-1``).
        read: a row's pointmaps, read when needed and not kept.
        poses: ``(N, 8)`` Sim(3) ``T_WC``, frozen.
        chunks: the edges in working sets (:func:`chunk_edges`); every edge in one.
        labels: a row's ``(H, W)`` int64 label map (``-1``: excluded).
        config: as for :func:`~.depth_refinement.refine_depths`.
        write: takes a free row's refined ``(H, W, 3)`` pointmap once every pass has read
            what it needs (pinned rows keep theirs and are not written).
        pinned: rows held fixed (the gauge anchor, a frozen map).
        huber_k: Huber breakpoint of the data term.
        keep: whether a chunk of these rows may keep its flattened problem in memory for
            the whole step (its keyframes stay in memory anyway); default: none may. The
            others, and those past ``keep_bytes``, are built at the first pass and read
            back from a :class:`ProblemSpill` at the later ones.
        spill_dir: where the spill's folder is made (None: the system's temporary folder);
            it takes about 56 bytes per match of the chunks not kept on CPU (their match
            streams), 20 per pixel and 36 per match elsewhere (their problems).
        keep_bytes: the most bytes of problems kept in memory (:data:`KEEP_PROBLEM_BYTES`);
            the results do not depend on it, only memory and disk use do.

    Returns:
        The report, as :func:`~.depth_refinement.refine_depths` makes it.

    Raises:
        InputError: inconsistent shapes, or an edge naming an unknown row.
        ConfigError: an unknown variant.
    """
    start = time.perf_counter()
    report = DepthRefinementReport(variant=config.variant)
    if count == 0:
        return report
    pinned_rows = {int(r) for r in pinned}
    # per row: its first log-scale and how many it has (pinned rows: none)
    offsets, sizes, s_parts, bnd_parts = [], [], [], []
    num_params = 0
    ranges = torch.zeros(count, dtype=torch.float64)
    for r in range(count):
        kf, lab = read(r), labels(r)
        ranges[r] = float(median_range(kf.X_hat))  # whitens C-Eq. 21 (edges out of r)
        _check_inputs([kf], poses[r : r + 1], [lab], config)
        alone, _, _ = build_problem(
            [kf],
            poses[r : r + 1],
            [],
            {}.__getitem__,
            [lab],
            config,
            {0} if r in pinned_rows else set(),
        )
        offsets.append(num_params)
        sizes.append(alone.s_start.numel())
        s_parts.append(alone.s_start)
        bnd_parts.append((alone.bnd_a + num_params, alone.bnd_b + num_params, alone.delta))
        num_params += sizes[-1]
    s_start = torch.cat(s_parts)
    bnd_a, bnd_b, delta = (torch.cat(parts) for parts in zip(*bnd_parts))

    spill = ProblemSpill(spill_dir)
    ready: dict[int, tuple[DataTerm, int]] = {}  # the kept chunks' terms, this step
    kept_bytes = 0

    def chunk_terms(n: int, chunk: Chunk) -> tuple[DataTerm, int]:
        """Chunk ``n``'s data term ``(s, with_blocks) -> (H, g, cost)`` and its number of
        matches: its problem built at its first pass, then kept where ``keep`` allows, else
        read back from the spill (the working set of a paged map); on CPU as the compiled
        loop's match streams."""
        nonlocal kept_bytes
        if n in ready:
            return ready[n]
        in_memory = False
        if n in spill:
            data = spill.load(n)
        else:
            position = {r: k for k, r in enumerate(chunk.rows)}
            keyframes = [read(r) for r in chunk.rows]
            build = chunk_streams if keyframes[0].X_init.device.type == "cpu" else _data_problem
            data = build(
                keyframes,
                poses[list(chunk.rows)],
                chunk.edges(),
                position.__getitem__,
                [labels(r) for r in chunk.rows],
                config,
                {position[r] for r in chunk.rows if r in pinned_rows},
                ranges=[float(ranges[r]) for r in chunk.rows],
            )
            size = _problem_bytes(data)
            in_memory = keep(chunk.rows) and kept_bytes + size <= keep_bytes
            kept_bytes += size if in_memory else 0
            if not in_memory and num_params and config.inner_iters > 0:  # read again later
                spill.save(n, data)
        if isinstance(data, MatchStreams):
            terms = (partial(_stream_terms, streams=data, huber_k=huber_k), data.num_matches)
        else:
            terms = (_Refiner(data, config, huber_k).data_terms, data.match_a.numel())
        if in_memory:
            ready[n] = terms
        return terms

    def data_term(s: Tensor, with_blocks: bool) -> tuple[Tensor, Tensor, float]:
        """C-Eq. 21 summed over the chunks: ``H (M,)``, ``g (M,)`` float64 and the cost."""
        H = torch.zeros(num_params, dtype=torch.float64, device=s.device)
        g = torch.zeros_like(H)
        cost, report.num_matches = 0.0, 0
        for n, chunk in enumerate(chunks):
            terms, matches = chunk_terms(n, chunk)
            report.num_matches += matches
            index = torch.cat(
                [
                    torch.arange(offsets[r], offsets[r] + sizes[r], device=s.device)
                    for r in chunk.rows
                ]
            )
            H_c, g_c, cost_c = terms(s[index], with_blocks)
            if with_blocks:
                H.index_add_(0, index, H_c.to(H))
                g.index_add_(0, index, g_c.to(g))
            cost += cost_c
        return H, g, cost

    s = s_start.clone()
    report.num_parameters = num_params
    report.num_boundary_pairs = bnd_a.numel()
    try:
        if num_params:
            for _ in range(config.inner_iters):
                H, g, energy = regularised(*data_term(s, True), s, bnd_a, bnd_b, delta, config)
                ds, clipped = damped_step(H, g, s, config)
                report.cost_history.append(energy)
                s = s + ds
                report.iterations += 1
                report.clipped_steps += clipped
                report.max_step = float(ds.abs().max())
            report.max_change = float((s - s_start).abs().max())
        H, g, cost = data_term(s, False)
    finally:
        spilled, kept_count = spill.bytes, len(ready)
        ready.clear()  # the write-back below reads keyframe by keyframe: let go first
        spill.close()
    report.cost_history.append(regularised(H, g, cost, s, bnd_a, bnd_b, delta, config)[2])

    for r in range(count):
        if r in pinned_rows:
            continue
        kf = read(r)
        alone, _, _ = build_problem(
            [kf], poses[r : r + 1], [], {}.__getitem__, [labels(r)], config, set(), data_only=True
        )
        depths = _Refiner(alone, config, huber_k).depths(s[offsets[r] : offsets[r] + sizes[r]])
        write(r, written_back(kf.X_hat, depths, alone.rays, alone.param))
    report.seconds = time.perf_counter() - start
    logger.debug(
        "depth refinement (%s) in %d chunk(s), %d kept, %.1f MB spilled: %d params, "
        "%d matches, cost %.4g -> %.4g, max |ds| %.3g",
        report.variant,
        len(chunks),
        kept_count,
        spilled / 2**20,
        report.num_parameters,
        report.num_matches,
        report.initial_cost,
        report.final_cost,
        report.max_change,
    )
    return report
