"""The simulated prior's ground-truth record (prior/simulated_record.py): what travels and is
stored in place of its encoding, lossless, and the encoding made again from it, bit for bit.

A hand-made 24x32 view (a slanted textured plane, a box in front, some sky) keeps it fast.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from como3r.config import SimulatedPriorConfig
from como3r.errors import PriorError
from como3r.prior.base import EncodingRecord, view_from_colors
from como3r.prior.ground_truth import GroundTruth, InMemoryTruth
from como3r.prior.simulated import SimulatedPrior
from como3r.prior.simulated_record import (
    SimulatedTruthRecord,
    pack_floats,
    truth_of_record,
    unpack_floats,
)
from como3r.store.blobs import pack_object, unpack_object
from como3r.transport.codec import decode, encode

H, W = 24, 32


def _truth(surface: bool = True) -> GroundTruth:
    """A slanted plane 2-4 m away with a box at 1 m, sky in the top rows."""
    rows = torch.arange(H, dtype=torch.float64)[:, None].expand(H, W)
    cols = torch.arange(W, dtype=torch.float64)[None, :].expand(H, W)
    depth = 2.0 + 2.0 * rows / H + 0.01 * cols
    depth[8:14, 10:18] = 1.0
    depth[:3] = 0.0
    depth[3, 5] = float("nan")
    K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    ids = torch.where(depth > 0, 3.0, -1.0)
    ids[8:14, 10:18] = 7.0
    keys = torch.stack([ids, 0.0137 * cols * depth, 0.0211 * rows * depth - 1.5], dim=-1)
    return GroundTruth(
        depth=depth.to(torch.float32),
        K=K,
        surface=keys.to(torch.float32) if surface else None,
        T_WC=torch.tensor([0.1, -0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 1.0], dtype=torch.float64),
    )


def _colors(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _priors(truth: GroundTruth, model: str = "realistic") -> tuple[SimulatedPrior, SimulatedPrior]:
    """The agent's prior (it has the ground truth) and a coordinator's (it has none)."""
    source = InMemoryTruth()
    source.add(2, 5, truth)
    config = SimulatedPriorConfig(model=model)
    return SimulatedPrior(config, source), SimulatedPrior(config, None)


def _same(a: object, b: object) -> bool:
    """Equal, tensors bit for bit (nan included)."""
    if isinstance(a, torch.Tensor):
        return (
            isinstance(b, torch.Tensor)
            and (a.dtype, a.shape) == (b.dtype, b.shape)
            and torch.equal(a.contiguous().view(torch.uint8), b.contiguous().view(torch.uint8))
        )
    return a == b


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.float32).contiguous().view(torch.int32)


def test_floats_pack_to_small_residuals_and_unpack_bit_for_bit() -> None:
    gen = torch.Generator().manual_seed(0)
    ramp = torch.arange(H * W, dtype=torch.int32).reshape(H, W) * 7 + (1 << 29)
    packed = pack_floats(ramp.view(torch.float32))  # bit patterns linear along the rows
    assert int(packed[:, 2:].abs().max()) == 0 and int(packed[1:, 0].abs().max()) == 7 * W * 2
    special = [float("nan"), float("inf"), -float("inf"), -0.0, 0.0, 3.4e38, -1e-45]
    for values in (
        ramp.view(torch.float32),
        torch.randn(H, W, 3, generator=gen) * 1e30,
        torch.tensor([special]),
        torch.zeros(1, 1),
    ):
        assert torch.equal(_bits(unpack_floats(pack_floats(values))), _bits(values))
    assert pack_floats(torch.zeros(4, 5)).dtype == torch.int16


@pytest.mark.parametrize("model", ["realistic", "v2"])
@pytest.mark.parametrize("surface", [True, False])
def test_the_colours_and_the_record_give_the_agents_encoding_bit_for_bit(
    model: str, surface: bool
) -> None:
    agent_prior, coordinator_prior = _priors(_truth(surface), model)
    colors = _colors(1)
    made = agent_prior.encode(view_from_colors(colors, 2, 5))
    record = made.portable()
    assert isinstance(record, SimulatedTruthRecord) and record is made.record
    assert (record.T_WC is None) is surface  # the pose only where the keys are made of it
    # across a process boundary (bit-exact pipes or lossy links alike) and through a store
    for received in (
        decode(encode(record)),
        decode(encode(record, lossy=True)),
        unpack_object(pack_object(record), EncodingRecord, "record"),
    ):
        again = coordinator_prior.encode_from_record(view_from_colors(colors, 2, 5), received)
        for field in dataclasses.fields(made):
            if field.name != "record":
                assert _same(getattr(made, field.name), getattr(again, field.name)), field.name
    other = agent_prior.encode(view_from_colors(_colors(2), 2, 5))
    a, b = agent_prior.decode(made, other), coordinator_prior.decode(again, other)
    for name in ("X_ii", "X_ji", "C_ii", "C_ji", "D_ii", "D_ji", "Q_ii", "Q_ji"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    bare = made.for_decoding()  # what a robot that only decodes it is sent
    assert bare.record is None and torch.equal(coordinator_prior.decode(bare, other).X_ji, a.X_ji)


def test_the_record_is_the_truth_the_prior_reads_bit_for_bit_and_small() -> None:
    truth = _truth()
    agent_prior, _ = _priors(truth)
    made = agent_prior.encode(view_from_colors(_colors(1), 2, 5))
    back = truth_of_record(made.record)
    assert torch.equal(_bits(back.depth), _bits(truth.depth))  # the nan and the zeros too
    assert torch.equal(_bits(back.surface), _bits(truth.surface))
    assert torch.equal(back.K, truth.K.to(torch.float32))
    smooth = _truth(surface=False)  # the plane and the box are smooth along rows
    packed = pack_floats(smooth.depth)
    assert float((packed[:, 2:].abs() <= 4).float().mean()) > 0.8
    assert len(pack_object(made.record)) * 5 < len(
        pack_object(dataclasses.replace(made, record=None))
    )


def test_a_record_of_another_view_or_for_another_prior_is_refused() -> None:
    agent_prior, coordinator_prior = _priors(_truth())
    record = agent_prior.encode(view_from_colors(_colors(1), 2, 5)).portable()
    with pytest.raises(PriorError, match="not that of agent 2, frame 6"):
        coordinator_prior.encode_from_record(view_from_colors(_colors(1), 2, 6), record)
    with pytest.raises(PriorError, match="cannot decode a SimulatedTruthRecord"):
        coordinator_prior.decode(record, record)
    foreign = EncodingRecord(agent=2, index=5, shape=(H, W))
    with pytest.raises(PriorError, match="cannot encode agent 2's frame 5 from a EncodingRecord"):
        coordinator_prior.encode_from_record(view_from_colors(_colors(1), 2, 5), foreign)
