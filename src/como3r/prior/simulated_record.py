"""What the simulated prior needs, besides a keyframe's image, to encode it again: its ground
truth exactly as the prior reads it (:class:`SimulatedTruthRecord`), compactly.

MASt3R's encoding is a function of the image alone, so a coordinator encodes a keyframe's
colours again and nothing else travels or is stored
(:meth:`~como3r.prior.base.Prior.can_reencode`). The simulated prior's encoding (about 110
bytes per pixel: 13.4 MB at 512x384) is made from the frame's ground truth (depth,
intrinsics, surface keys or pose), which a coordinator does not have in a networked run, a
resume, a saved map or a merge. What travels and is stored in its place is this record, from
which the coordinator's prior makes the encoding with the keyframe's colours
(:meth:`~como3r.prior.simulated.SimulatedPrior.encode_from_record`), bit-identical to the
agent's on any machine: :meth:`~como3r.prior.simulated.SimulatedPrior.encode` reads its
ground truth through the same record.

The record is lossless: depth and surface maps are the float32 values the prior reads, bit
for bit, intrinsics float32 and the pose as given. Quantizing them even 40 times below the
prior's own range noise would change its predictions by as little, but not its outputs
by as little: which key cells two views share, and so how many random numbers the robust
fit draws before a pair's noise, would change, and with it every later draw of the pair (on
the demo scene, per-pixel differences of 3 % in the pointmaps and merged ATE 10.0 mm instead
of 7.9 mm). Each map is stored as the float32 bit patterns' residuals of a second-order
prediction along image rows (the first column: first differences down it), modulo 2**32 and
zigzag-mapped, so that smooth surfaces give small non-negative integers the codec's
Zstandard (:mod:`como3r.transport.codec_arrays`) packs well: about 0.7-0.9 MB per 512x384
keyframe of the demo scene (depth 0.2 MB, surface 0.5-0.6 MB), where MASt3R's tokens would
be 1.57 MB in float16.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from como3r.errors import PriorError
from como3r.prior.base import EncodingRecord, View
from como3r.prior.ground_truth import GroundTruth

_MASK32 = (1 << 32) - 1


@dataclass(frozen=True)
class SimulatedTruthRecord(EncodingRecord):
    """A view's ground truth as the simulated prior reads it (module docstring).

    Attributes:
        depth: :func:`pack_floats` of the ``(H, W)`` float32 metric z-depth (anything not
            finite or <= 0 where there is none).
        K: ``(3, 3)`` float32 true intrinsics at the view's resolution.
        surface: :func:`pack_floats` of the ``(H, W, 3)`` float32 surface map (texture id,
            s, t), or None without one.
        T_WC: ``(8,)`` ground-truth pose, only without a surface map (the keys are then
            world points, :func:`~como3r.prior.simulated_keys.keys_from_world`); else None.
    """

    depth: Tensor
    K: Tensor
    surface: Tensor | None
    T_WC: Tensor | None


def _wrap32(x: Tensor) -> Tensor:
    """int64 ``x`` modulo 2**32, as a signed 32-bit value (still int64)."""
    return ((x + (1 << 31)) & _MASK32) - (1 << 31)


def pack_floats(values: Tensor) -> Tensor:
    """``(H, W, ...)`` float32 values as the residuals of a second-order prediction of their
    bit patterns along rows (the first column: first differences down it), modulo 2**32,
    zigzag-mapped: int16 where they all fit, else int32; :func:`unpack_floats` inverts it
    bit for bit."""
    bits = values.to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    first = torch.diff(bits, dim=1, prepend=torch.zeros_like(bits[:, :1]))
    residual = torch.diff(first, dim=1, prepend=torch.zeros_like(first[:, :1]))
    residual[:, 0] = torch.diff(residual[:, 0], dim=0, prepend=torch.zeros_like(residual[:1, 0]))
    residual = _wrap32(residual)
    zigzag = (residual << 1) ^ (residual >> 31)  # in [0, 2**32): small for small residuals
    if zigzag.numel() == 0 or int(zigzag.max()) <= torch.iinfo(torch.int16).max:
        return zigzag.to(torch.int16)
    return _wrap32(zigzag).to(torch.int32)


def unpack_floats(packed: Tensor) -> Tensor:
    """The float32 values :func:`pack_floats` packed."""
    zigzag = packed.to(torch.int64) & _MASK32
    residual = (zigzag >> 1) ^ -(zigzag & 1)
    residual[:, 0] = torch.cumsum(residual[:, 0], dim=0)
    bits = _wrap32(torch.cumsum(torch.cumsum(residual, dim=1), dim=1))
    return bits.to(torch.int32).view(torch.float32)


def record_truth(view: View, truth: GroundTruth, depth: Tensor, K: Tensor) -> SimulatedTruthRecord:
    """The record of ``view``'s ground truth, whose depth and intrinsics were checked
    (:func:`~como3r.prior.simulated_encoding.validated_inputs`).

    Args:
        view: the view (agent, frame index, size).
        truth: its ground truth (surface map or pose).
        depth: ``(H, W)`` float32 metric z-depth.
        K: ``(3, 3)`` float32 intrinsics.
    """
    surface = None if truth.surface is None else pack_floats(truth.surface)
    return SimulatedTruthRecord(
        agent=view.agent,
        index=view.index,
        shape=view.shape,
        depth=pack_floats(depth),
        K=K.to(torch.float32).clone(),
        surface=surface,
        # the pose only where the keys are made of it (world points)
        T_WC=None if truth.T_WC is None or surface is not None else truth.T_WC.clone(),
    )


def checked_record(view: View, record: SimulatedTruthRecord) -> SimulatedTruthRecord:
    """``record`` if it is of ``view`` (agent, frame, size).

    Raises:
        PriorError: it is another view's.
    """
    if (record.agent, record.index, tuple(record.shape)) != (view.agent, view.index, view.shape):
        raise PriorError(
            f"simulated prior: the record of agent {record.agent}, frame {record.index} "
            f"({record.shape[1]}x{record.shape[0]}) is not that of agent {view.agent}, "
            f"frame {view.index} ({view.shape[1]}x{view.shape[0]})"
        )
    return record


def truth_of_record(record: SimulatedTruthRecord) -> GroundTruth:
    """The ground truth a record holds: ``depth (H, W)`` and ``surface (H, W, 3)`` (or None)
    float32, ``K``, ``T_WC`` (or None).

    Raises:
        PriorError: the record's maps do not have its shape.
    """
    H, W = record.shape
    maps = [("depth", record.depth, (H, W))]
    if record.surface is not None:
        maps.append(("surface", record.surface, (H, W, 3)))
    for name, value, shape in maps:
        if tuple(value.shape) != shape:
            raise PriorError(
                f"simulated prior: record of agent {record.agent}, frame {record.index} has "
                f"{name} of shape {tuple(value.shape)}, not {shape}"
            )
    return GroundTruth(
        depth=unpack_floats(record.depth),
        K=record.K,
        surface=None if record.surface is None else unpack_floats(record.surface),
        T_WC=record.T_WC,
    )
