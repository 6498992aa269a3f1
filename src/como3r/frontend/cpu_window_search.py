"""The compiled CPU loop of matching's descriptor window search (C-Eq. 1; the other loops of
dense matching are in :mod:`como3r.frontend.cpu_kernels`, whose docstring says why they are
compiled and what they measured).

The window search scores 8 candidates of a window row at once in explicit 8-lane vectors
(:func:`_window_best`, LLVM IR through a numba intrinsic): written as a loop over the 24
floats of one descriptor, LLVM vectorised each dot product 16 wide, left the 24 to an 8-wide
remainder and summed it horizontally, about 14 cycles per candidate; the pixels were
compute bound (the same speed with all of them reading one cached descriptor).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import torch
from llvmlite import ir
from numba import prange, types
from numba.core import cgutils
from numba.extending import intrinsic
from torch import Tensor

from como3r.jit import compiled

#: query pixels per parallel task of the window search (each task allocates its scratch once)
_SEARCH_BLOCK = 64
#: window offsets are packed as ``j << 16 | i`` (window row j, column i): the smallest key is the
#: first candidate in row-major order
_KEY_SHIFT = 16
#: the key of a lane that kept no candidate (larger than any window key)
_NO_KEY = 2**31 - 1

_F32, _I32, _I64 = ir.FloatType(), ir.IntType(32), ir.IntType(64)
_V8F, _V8I = ir.VectorType(_F32, 8), ir.VectorType(_I32, 8)
#: lane swaps of a 3-step reduction over 8 lanes (halves, pairs of a half, neighbours)
_SWAPS = ([4, 5, 6, 7, 0, 1, 2, 3], [2, 3, 0, 1, 6, 7, 4, 5], [1, 0, 3, 2, 5, 4, 7, 6])


def _shuffle(builder: ir.IRBuilder, a: ir.Value, b: ir.Value, lanes: list[int]) -> ir.Value:
    return builder.shuffle_vector(a, b, ir.Constant(ir.VectorType(_I32, len(lanes)), lanes))


def _splat(builder: ir.IRBuilder, value: ir.Value, vector: ir.VectorType) -> ir.Value:
    one = builder.insert_element(ir.Constant(vector, ir.Undefined), value, ir.Constant(_I32, 0))
    return _shuffle(builder, one, one, [0] * vector.count)


def _lane_sums(builder: ir.IRBuilder, vectors: list[ir.Value]) -> ir.Value:
    """The 8 lane sums of 8 vectors of 8 floats as one vector (lane l: the sum of
    ``vectors[l]``), by pairwise sums of neighbouring lanes (x86 ``vhaddps``): 7 shuffle-adds
    for 8 dot products, where one horizontal sum each takes 3 (and a scalar compare)."""

    def pairwise(a: ir.Value, b: ir.Value) -> ir.Value:  # per 128-bit half: a01 a23 b01 b23
        even = _shuffle(builder, a, b, [0, 2, 8, 10, 4, 6, 12, 14])
        odd = _shuffle(builder, a, b, [1, 3, 9, 11, 5, 7, 13, 15])
        return builder.fadd(even, odd)

    quads = [
        pairwise(pairwise(vectors[k], vectors[k + 1]), pairwise(vectors[k + 2], vectors[k + 3]))
        for k in (0, 4)
    ]  # lane sums 0-3 (4-7) in each half of quads[0] (quads[1])
    low = _shuffle(builder, quads[0], quads[1], [0, 1, 2, 3, 8, 9, 10, 11])
    high = _shuffle(builder, quads[0], quads[1], [4, 5, 6, 7, 12, 13, 14, 15])
    return builder.fadd(low, high)


def _reduce(builder: ir.IRBuilder, vector: ir.Value, keep_other: Callable) -> ir.Value:
    """Lane 0 of ``vector`` reduced over its 8 lanes by ``keep_other(other, mine)`` (a mask)."""
    for swap in _SWAPS:
        other = _shuffle(builder, vector, vector, swap)
        vector = builder.select(keep_other(other, vector), other, vector)
    return builder.extract_element(vector, ir.Constant(_I32, 0))


@intrinsic
def _window_best(typingctx, table, lines, columns, side, query, query_start, dim):
    """Key ``j << 16 | i`` of the first maximum, in row-major window order, of the descriptor
    scores ``table[lines[j] + columns[i]:][:dim] . query[query_start:][:dim]`` (float32) over
    ``j, i < side``; -1 when no score is a number. ``dim`` (a compile-time constant, a multiple
    of 8) floats per descriptor; ``columns`` holds ``side`` rounded up to a multiple of 8
    entries (the ones past ``side`` are read, never chosen).

    Explicit 8-lane vectors: each lane scores one candidate of a window row (the descriptor
    read as ``dim / 8`` vectors and fused multiply-adds), 8 scores leave by one transposing
    sum, and each lane keeps its own first maximum, so the row loop carries no scalar compare;
    one reduction per window picks the largest score, the smallest key among equals.
    """
    if not isinstance(dim, types.IntegerLiteral) or dim.literal_value % 8:
        return None
    chunks_per_descriptor = dim.literal_value // 8
    signature = types.int64(table, lines, columns, side, query, query_start, dim)

    def codegen(context, builder, sig, args):
        data = [
            context.make_array(sig.args[k])(context, builder, args[k]).data for k in (0, 1, 2, 4)
        ]
        table_data, line_data, column_data, query_data = data
        side_64, query_start = args[3], args[5]
        fmuladd = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(_V8F, [_V8F] * 3), "llvm.fmuladd.v8f32"
        )

        def load8(pointer: ir.Value, offset: int) -> ir.Value:
            at = builder.gep(pointer, [ir.Constant(_I64, offset)])
            return builder.load(builder.bitcast(at, _V8F.as_pointer()), align=4)

        q_base = builder.gep(query_data, [query_start])
        q = [load8(q_base, 8 * c) for c in range(chunks_per_descriptor)]
        side_32 = builder.trunc(side_64, _I32)
        side_lanes = _splat(builder, side_32, _V8I)
        lane_ids = ir.Constant(_V8I, list(range(8)))
        no_key = ir.Constant(_V8I, [_NO_KEY] * 8)
        best = cgutils.alloca_once_value(builder, ir.Constant(_V8F, [float("-inf")] * 8))
        best_key = cgutils.alloca_once_value(builder, no_key)
        groups = builder.udiv(builder.add(side_64, ir.Constant(_I64, 7)), ir.Constant(_I64, 8))
        # window rows outside, groups of 8 columns inside: each lane meets its candidates in
        # increasing key order, so a strict '>' keeps the lane's first maximum
        with cgutils.for_range(builder, side_64) as row:
            line = builder.gep(table_data, [builder.load(builder.gep(line_data, [row.index]))])
            row_key = builder.shl(builder.trunc(row.index, _I32), ir.Constant(_I32, _KEY_SHIFT))
            with cgutils.for_range(builder, groups) as group:
                first = builder.mul(group.index, ir.Constant(_I64, 8))
                products = []
                for lane in range(8):
                    column = builder.load(
                        builder.gep(column_data, [builder.add(first, ir.Constant(_I64, lane))])
                    )
                    candidate = builder.gep(line, [column])
                    acc = builder.fmul(load8(candidate, 0), q[0])
                    for c in range(1, chunks_per_descriptor):
                        acc = builder.call(fmuladd, [load8(candidate, 8 * c), q[c], acc])
                    products.append(acc)
                scores = _lane_sums(builder, products)
                i = builder.add(_splat(builder, builder.trunc(first, _I32), _V8I), lane_ids)
                key = builder.or_(_splat(builder, row_key, _V8I), i)
                kept, kept_key = builder.load(best), builder.load(best_key)
                better = builder.and_(
                    builder.fcmp_ordered(">", scores, kept), builder.icmp_signed("<", i, side_lanes)
                )
                builder.store(builder.select(better, scores, kept), best)
                builder.store(builder.select(better, key, kept_key), best_key)
        kept, kept_key = builder.load(best), builder.load(best_key)
        top = _splat(
            builder, _reduce(builder, kept, lambda o, m: builder.fcmp_ordered(">", o, m)), _V8F
        )
        tied = builder.select(builder.fcmp_ordered("==", kept, top), kept_key, no_key)
        key = _reduce(builder, tied, lambda o, m: builder.icmp_signed("<", o, m))
        found = builder.icmp_signed("!=", key, ir.Constant(_I32, _NO_KEY))
        return builder.select(found, builder.sext(key, _I64), ir.Constant(_I64, -1))

    return signature, codegen


@functools.cache
def _window_search(dim: int) -> Callable:
    """The window search over descriptors of ``dim`` floats (a multiple of 8)."""

    def _refine_windows(
        table: np.ndarray,
        height: int,
        width: int,
        query: np.ndarray,
        pixel: np.ndarray,
        rows: np.ndarray,
        per_image: int,
        radius: int,
        dilation_max: int,
        out: np.ndarray,
    ) -> None:  # pragma: no cover
        side = 2 * radius + 1
        padded = (side + 7) // 8 * 8
        mask = (1 << _KEY_SHIFT) - 1
        for block in prange((rows.shape[0] + _SEARCH_BLOCK - 1) // _SEARCH_BLOCK):
            columns = np.empty(padded, np.int64)  # per window: element offsets in a row
            lines = np.empty(side, np.int64)  # per window: element offsets of its rows
            for k in range(block * _SEARCH_BLOCK, min((block + 1) * _SEARCH_BLOCK, rows.shape[0])):
                row = rows[k]
                first = (row // per_image) * height
                u, v = pixel[row, 0], pixel[row, 1]
                for dil in range(dilation_max, 0, -1):
                    for a in range(padded):  # window pixels outside: the nearest border pixel
                        columns[a] = (
                            min(max(u + dil * (min(a, side - 1) - radius), 0), width - 1) * dim
                        )
                    for a in range(side):
                        lines[a] = (
                            (first + min(max(v + dil * (a - radius), 0), height - 1)) * width * dim
                        )
                    key = _window_best(table, lines, columns, side, query, row * dim, dim)
                    if key >= 0:
                        u = min(max(u + dil * ((key & mask) - radius), 0), width - 1)
                        v = min(max(v + dil * ((key >> _KEY_SHIFT) - radius), 0), height - 1)
                out[row, 0], out[row, 1] = u, v

    return _refine_windows


def refine_windows(
    D_search: Tensor,
    D_query: Tensor,
    pixel: Tensor,
    radius: int,
    dilation_max: int,
    active: Tensor | None,
) -> Tensor:
    """:func:`como3r.frontend.matching.refine_with_descriptors` on CPU tensors.

    Scores in float32 like the PyTorch path; window pixels outside the image count as the
    nearest border pixel. Shapes as there: ``D_search (B, H, W, d)``, ``D_query (B, P, d)``,
    ``pixel (B, P, 2)`` int64, ``active (B, P)`` bool or None; returns ``(B, P, 2)`` int64.
    Descriptors whose ``d`` is not a multiple of 8 are padded with zeros (a copy).
    """
    B, H, W, d = D_search.shape
    P = pixel.shape[1]
    if 2 * radius + 1 >= 1 << _KEY_SHIFT:
        raise ValueError(f"window radius {radius} too large")
    table = D_search.detach().to(torch.float32).reshape(B * H * W, d)
    query = D_query.detach().to(torch.float32).reshape(B * P, d)
    dim = -(-d // 8) * 8
    if dim != d:  # zero lanes add nothing to a score
        table = torch.nn.functional.pad(table, (0, dim - d))
        query = torch.nn.functional.pad(query, (0, dim - d))
    start = pixel.detach().reshape(B * P, 2).to(torch.int64).contiguous().numpy()
    refined = start.copy()
    rows = (
        np.arange(B * P, dtype=np.int64)
        if active is None
        else np.flatnonzero(active.detach().reshape(-1).numpy()).astype(np.int64)
    )
    if rows.size:
        search = compiled(_window_search(dim))
        search(
            table.contiguous().reshape(-1).numpy(),
            H,
            W,
            query.contiguous().reshape(-1).numpy(),
            start,
            rows,
            P,
            radius,
            dilation_max,
            refined,
        )
    return torch.from_numpy(refined).reshape(B, P, 2)
