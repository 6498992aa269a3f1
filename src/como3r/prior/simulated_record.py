"""What the simulated prior needs, besides a keyframe's image, to encode it again: its ground
truth at the precision the prior reads it (:class:`SimulatedTruthRecord`).

MASt3R's encoding is a function of the image alone, so a coordinator encodes a keyframe's
colours again and nothing else travels or is stored
(:meth:`~como3r.prior.base.Prior.can_reencode`). The simulated prior's encoding (about 110
bytes per pixel: 13.4 MB at 512x384) is made from the frame's ground truth (depth,
intrinsics, surface keys or pose), which a coordinator does not have in a networked run, a
resume, a saved map or a merge. What travels and is stored in its place is this record:
the ground truth, quantized, in integer codes a general-purpose compressor packs well; the
coordinator's prior makes the encoding from the keyframe's colours and the record
(:meth:`~como3r.prior.simulated.SimulatedPrior.encode_from_record`).

The prior always reads its ground truth through a record
(:meth:`~como3r.prior.simulated.SimulatedPrior.encode` quantizes first), so the encoding
made from a record is bit-identical to the one the agent made, on any machine:

* depth in log steps of :data:`DEPTH_LOG_STEP` (a relative error of at most 0.012 %, 40 times
  below the prior's own per-pixel range noise of 0.5 %), 0 where there is none;
* surface-key coordinates ``s, t`` in steps of a power of two metres, at most
  :data:`KEY_STEP_PER_FOOTPRINT` of the view's median pixel footprint (median depth over
  focal length): far below the key cell (two footprints) the prior matches keys in, and
  relative, so a scene scaled as a whole (``como3r synth --scale``) is quantized alike;
* texture ids, intrinsics ``K`` and the pose ``T_WC`` exactly.

Each integer map is stored as the second differences of its codes along image rows (the
first column as first differences down it), zigzag-mapped to non-negative numbers in the
smallest integer type that holds them: smooth surfaces give residuals of a few units, which
the codec's Zstandard (:mod:`como3r.transport.codec_arrays`) packs to a few bits a pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.errors import PriorError
from como3r.prior.base import EncodingRecord, View
from como3r.prior.ground_truth import GroundTruth

DEPTH_LOG_STEP = 2.0**-12
"""Step of the natural log of depth (relative depth resolution)."""

KEY_STEP_PER_FOOTPRINT = 2.0**-10
"""Largest step of the surface-key coordinates, as a fraction of the view's median pixel
footprint (rounded down to a power of two metres)."""


@dataclass(frozen=True)
class SimulatedTruthRecord(EncodingRecord):
    """A view's ground truth as the simulated prior reads it (module docstring).

    Every map is a residual code (:func:`pack_codes`) ``(H, W)`` or ``(H, W, 2)`` of int16,
    int32 or int64.

    Attributes:
        depth: codes of the depth: ``round(log(depth) / DEPTH_LOG_STEP) - depth_base + 1``,
            0 where there is none.
        depth_base: the smallest valid log-depth code.
        K: ``(3, 3)`` float32 true intrinsics at the view's resolution.
        surface_ids: codes of the rounded texture ids (-1 for every negative one), or None
            without a surface map.
        surface_st: codes of the key coordinates ``s, t`` in steps of ``2 ** key_step_log2``
            metres, or None without a surface map.
        key_step_log2: log2 of that step in metres.
        T_WC: ``(8,)`` ground-truth pose, only without a surface map (the keys are then
            world points, :func:`~como3r.prior.simulated_keys.keys_from_world`); else None.
    """

    depth: Tensor
    depth_base: int
    K: Tensor
    surface_ids: Tensor | None
    surface_st: Tensor | None
    key_step_log2: int
    T_WC: Tensor | None


def pack_codes(codes: Tensor) -> Tensor:
    """Integer codes ``(H, W, ...)`` as residuals of a second-order prediction along rows
    (the first column: first differences down it), zigzag-mapped, in the smallest of int16,
    int32 and int64 that holds them; :func:`unpack_codes` inverts it exactly."""
    codes = codes.to(torch.int64)
    first = torch.diff(codes, dim=1, prepend=torch.zeros_like(codes[:, :1]))
    residual = torch.diff(first, dim=1, prepend=torch.zeros_like(first[:, :1]))
    residual[:, 0] = torch.diff(residual[:, 0], dim=0, prepend=torch.zeros_like(residual[:1, 0]))
    zigzag = (residual << 1) ^ (residual >> 63)
    largest = int(zigzag.max()) if zigzag.numel() else 0
    for dtype in (torch.int16, torch.int32):
        if largest <= torch.iinfo(dtype).max:
            return zigzag.to(dtype)
    return zigzag


def unpack_codes(packed: Tensor) -> Tensor:
    """The int64 codes :func:`pack_codes` packed."""
    zigzag = packed.to(torch.int64)
    residual = (zigzag >> 1) ^ -(zigzag & 1)
    residual[:, 0] = torch.cumsum(residual[:, 0], dim=0)
    return torch.cumsum(torch.cumsum(residual, dim=1), dim=1)


def record_truth(view: View, truth: GroundTruth, depth: Tensor, K: Tensor) -> SimulatedTruthRecord:
    """The record of ``view``'s ground truth, whose depth and intrinsics were checked
    (:func:`~como3r.prior.simulated_encoding.validated_inputs`).

    Args:
        view: the view (agent, frame index).
        truth: its ground truth (surface map or pose).
        depth: ``(H, W)`` float32 metric z-depth; not finite or <= 0 where there is none.
        K: ``(3, 3)`` float32 intrinsics.
    """
    valid = torch.isfinite(depth) & (depth > 0)
    logs = torch.round(torch.log(depth.to(torch.float64).clamp_min(1e-300)) / DEPTH_LOG_STEP)
    logs = torch.where(valid, logs, torch.zeros_like(logs)).to(torch.int64)
    base = int(logs[valid].min()) if bool(valid.any()) else 0
    codes = torch.where(valid, logs - base + 1, torch.zeros_like(logs))
    surface_ids = surface_st = None
    step_log2 = 0
    if truth.surface is not None:
        surface = truth.surface.to(torch.float64)
        finite = torch.isfinite(surface)
        surface = torch.where(finite, surface, torch.zeros_like(surface))
        ids = torch.round(surface[..., 0]).to(torch.int64)
        step_log2 = _key_step_log2(logs[valid], K)
        st = torch.round(surface[..., 1:3] * 2.0**-step_log2)
        if bool((st.abs() >= 2.0**40).any()):
            raise PriorError(
                f"simulated prior: view (agent {view.agent}, frame {view.index}) has surface "
                "coordinates too large for its depth"
            )
        surface_ids = pack_codes(ids.clamp_min(-1))
        surface_st = pack_codes(st.to(torch.int64))
    return SimulatedTruthRecord(
        agent=view.agent,
        index=view.index,
        shape=view.shape,
        depth=pack_codes(codes),
        depth_base=base,
        K=K.to(torch.float32).clone(),
        surface_ids=surface_ids,
        surface_st=surface_st,
        key_step_log2=step_log2,
        # the pose only where the keys are made of it (world points)
        T_WC=None if truth.T_WC is None or surface_ids is not None else truth.T_WC.clone(),
    )


def _key_step_log2(log_codes: Tensor, K: Tensor) -> int:
    """log2 of the key-coordinate step: :data:`KEY_STEP_PER_FOOTPRINT` of the median pixel
    footprint, from the valid log-depth codes ``(N,)`` and ``K``, rounded down."""
    if log_codes.numel() == 0:
        return -30  # no geometry to scale by: about a nanometre
    median_depth = math.exp(int(log_codes.median()) * DEPTH_LOG_STEP)
    focal = 0.5 * (float(K[0, 0]) + float(K[1, 1]))
    footprint = median_depth / max(focal, 1e-9)
    return math.floor(math.log2(max(footprint * KEY_STEP_PER_FOOTPRINT, 1e-30)))


def truth_of_record(record: SimulatedTruthRecord) -> GroundTruth:
    """The ground truth a record holds: ``depth (H, W)`` float32 (0 where none), ``K``,
    ``surface (H, W, 3)`` float32 or None, ``T_WC`` or None.

    Raises:
        PriorError: the record's maps do not have its shape.
    """
    H, W = record.shape
    maps = [("depth", record.depth, (H, W))]
    if record.surface_ids is not None or record.surface_st is not None:
        if record.surface_ids is None or record.surface_st is None:
            raise PriorError("simulated prior: a record with half a surface map")
        maps += [("surface_ids", record.surface_ids, (H, W))]
        maps += [("surface_st", record.surface_st, (H, W, 2))]
    for name, value, shape in maps:
        if tuple(value.shape) != shape:
            raise PriorError(
                f"simulated prior: record of agent {record.agent}, frame {record.index} has "
                f"{name} of shape {tuple(value.shape)}, not {shape}"
            )
    codes = unpack_codes(record.depth)
    logs = (codes + (record.depth_base - 1)).to(torch.float64) * DEPTH_LOG_STEP
    depth = torch.where(codes > 0, torch.exp(logs), torch.zeros_like(logs)).to(torch.float32)
    surface = None
    if record.surface_ids is not None and record.surface_st is not None:
        st = unpack_codes(record.surface_st).to(torch.float64) * 2.0**record.key_step_log2
        ids = unpack_codes(record.surface_ids).to(torch.float64)
        surface = torch.cat([ids[..., None], st], dim=-1).to(torch.float32)
    return GroundTruth(depth=depth, K=record.K, surface=surface, T_WC=record.T_WC)
