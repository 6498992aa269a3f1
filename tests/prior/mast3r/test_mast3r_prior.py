"""Tests of como3r/prior/mast3r/prior.py: MASt3R behind the Prior interface."""

from __future__ import annotations

import argparse
from dataclasses import fields
from pathlib import Path

import pytest
import torch

from como3r.errors import CheckpointError, PriorError
from como3r.prior.base import Encoding, PairPrediction, View
from como3r.prior.mast3r import MASt3REncoding, MASt3RPrior, load_mast3r
from como3r.transport import codec


def image(height: int, width: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(3, height, width, generator=generator) * 2 - 1


@pytest.fixture
def prior(tiny_checkpoint) -> MASt3RPrior:
    return load_mast3r(tiny_checkpoint)


def assert_valid_prediction(pred: PairPrediction, shape_i, shape_j) -> None:
    assert pred.X_ii.shape == (*shape_i, 3) and pred.X_ji.shape == (*shape_j, 3)
    assert pred.C_ii.shape == pred.Q_ii.shape == shape_i
    assert pred.C_ji.shape == pred.Q_ji.shape == shape_j
    assert pred.D_ii.shape == (*shape_i, 24) and pred.D_ji.shape == (*shape_j, 24)
    for f in fields(pred):
        value = getattr(pred, f.name)
        assert value.dtype == torch.float32 and torch.isfinite(value).all(), f.name
    assert float(pred.C_ii.min()) >= 1 and float(pred.C_ji.min()) >= 1
    assert float(pred.Q_ii.min()) > 0 and float(pred.Q_ji.min()) > 0
    for desc in (pred.D_ii, pred.D_ji):
        torch.testing.assert_close(desc.norm(dim=-1), torch.ones(desc.shape[:-1]))


def test_encode_holds_tokens_positions_and_shape(prior, tiny_network):
    view = View(image=image(48, 80, 0), agent=2, index=7)
    enc = prior.encode(view)
    assert isinstance(enc, MASt3REncoding) and isinstance(enc, Encoding)
    assert (enc.agent, enc.index, enc.shape, enc.grid) == (2, 7, (48, 80), (3, 5))
    assert enc.tokens.shape == (15, 32) and enc.tokens.dtype == torch.float32
    assert enc.pos.tolist()[:6] == [[0, 0], [0, 1], [0, 2], [0, 3], [0, 4], [1, 0]]
    with torch.no_grad():
        tokens, _ = tiny_network.encode(view.image[None])
    torch.testing.assert_close(enc.tokens, tokens[0])


def test_encode_accepts_tensors_batches_and_view_lists(prior):
    single = prior.encode(image(32, 48, 0)[None])
    assert isinstance(single, MASt3REncoding)
    batch = prior.encode(torch.stack([image(32, 48, 0), image(32, 48, 1)]), agent=1, index=10)
    assert [(e.agent, e.index) for e in batch] == [(1, 10), (1, 11)]
    torch.testing.assert_close(batch[0].tokens, single.tokens, atol=1e-5, rtol=1e-5)
    views = [
        View(image(32, 48, 0), index=0),
        View(image(48, 32, 2), index=1),
        View(image(32, 48, 1), index=2),
    ]
    encodings = prior.encode(views)
    assert [e.index for e in encodings] == [0, 1, 2]
    assert [e.shape for e in encodings] == [(32, 48), (48, 32), (32, 48)]
    torch.testing.assert_close(encodings[2].tokens, batch[1].tokens, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (torch.zeros(1, 4, 32, 32), r"\(B, 3, H, W\)"),
        (torch.zeros(1, 3, 40, 32), "multiple of 16"),
        (torch.full((1, 3, 32, 32), 255.0), r"normalised to \[-1, 1\]"),
        (torch.zeros(1, 3, 32, 32, dtype=torch.uint8), "must be float"),
        (torch.full((1, 3, 32, 32), float("nan")), r"\[-1, 1\]"),
        (torch.zeros(2, 1, 3, 32, 32), r"\(B, 3, H, W\)"),
    ],
)
def test_malformed_images_raise_prior_error(prior, bad, message):
    with pytest.raises(PriorError, match=message):
        prior.encode(bad)


def test_decode_matches_network_and_has_documented_ranges(prior, tiny_network):
    img_i, img_j = image(48, 80, 0), image(48, 80, 1)
    pred = prior.decode(prior.encode(View(img_i)), prior.encode(View(img_j)))
    assert_valid_prediction(pred, (48, 80), (48, 80))
    with torch.no_grad():
        out1, out2 = tiny_network(img_i[None], img_j[None])
    torch.testing.assert_close(pred.X_ii, out1.pts3d[0])
    torch.testing.assert_close(pred.X_ji, out2.pts3d[0])
    torch.testing.assert_close(pred.Q_ji, out2.desc_conf[0])
    again = prior.decode(prior.encode(View(img_i)), prior.encode(View(img_j)))
    assert torch.equal(again.X_ji, pred.X_ji) and torch.equal(again.D_ii, pred.D_ii)


def test_portrait_and_differently_sized_pair(prior):
    landscape = prior.encode(View(image(32, 48, 0)))
    portrait = prior.encode(View(image(48, 32, 1)))
    assert landscape.grid == (2, 3) and portrait.grid == (3, 2)
    assert_valid_prediction(prior.decode(portrait, portrait), (48, 32), (48, 32))
    assert_valid_prediction(prior.decode(landscape, portrait), (32, 48), (48, 32))


def _count_decoder_calls(prior, monkeypatch) -> list:
    """``(batch, grid1, grid2)`` of every decoder call the prior makes from now on."""
    calls = []
    decode = prior.network.decode

    def counting_decode(tokens1, grid1, tokens2, grid2):
        calls.append((tokens1.shape[0], grid1, grid2))
        return decode(tokens1, grid1, tokens2, grid2)

    monkeypatch.setattr(prior.network, "decode", counting_decode)
    return calls


def _assert_as_decoded_alone(prior, pred, a, b) -> None:
    """``pred`` is what ``prior.decode(a, b)`` gives on its own (batching changes nothing)."""
    expected = prior.decode(a, b)
    assert_valid_prediction(pred, a.shape, b.shape)
    for f in fields(pred):
        torch.testing.assert_close(
            getattr(pred, f.name), getattr(expected, f.name), atol=1e-4, rtol=1e-4
        )


def _encodings(prior):
    """Three square 32x32 encodings and a landscape/portrait pair."""
    encs = prior.encode([View(image(32, 32, s), index=s) for s in range(3)])
    mixed = prior.encode([View(image(48, 32, 5), index=5), View(image(32, 48, 6), index=6)])
    return encs, mixed


@pytest.mark.slow
def test_decode_symmetric_batches_one_decoder_call_per_size(prior, monkeypatch):
    encs, mixed = _encodings(prior)
    pairs = [(encs[0], encs[1]), (mixed[0], mixed[1]), (encs[2], encs[0])]
    calls = _count_decoder_calls(prior, monkeypatch)
    results = prior.decode_symmetric(pairs)
    # 2 same-size pairs: one call of 4 ordered pairs; the mixed-size pair: one call per order
    assert sorted(calls) == sorted([(4, (2, 2), (2, 2)), (1, (3, 2), (2, 3)), (1, (2, 3), (3, 2))])
    monkeypatch.undo()
    assert len(results) == len(pairs)
    for (enc_i, enc_j), (forward, backward) in zip(pairs, results):
        _assert_as_decoded_alone(prior, forward, enc_i, enc_j)
        _assert_as_decoded_alone(prior, backward, enc_j, enc_i)


@pytest.mark.slow
def test_decode_pairs_batches_one_decoder_call_per_pair_of_sizes(prior, monkeypatch):
    encs, mixed = _encodings(prior)
    pairs = [(encs[0], encs[1]), (mixed[0], mixed[1]), (encs[2], encs[0]), (mixed[1], encs[1])]
    calls = _count_decoder_calls(prior, monkeypatch)
    results = prior.decode_pairs(pairs)
    assert sorted(calls) == sorted([(2, (2, 2), (2, 2)), (1, (3, 2), (2, 3)), (1, (2, 3), (2, 2))])
    monkeypatch.undo()
    assert len(results) == len(pairs)
    for (a, b), pred in zip(pairs, results):
        _assert_as_decoded_alone(prior, pred, a, b)


def test_decode_refuses_foreign_encodings(prior):
    enc = prior.encode(View(image(32, 32, 0)))
    with pytest.raises(PriorError, match="MASt3RPrior.encode"):
        prior.decode(enc, Encoding(agent=0, index=0, shape=(32, 32)))


def test_retrieval_features_need_retrieval_weights(prior):
    enc = prior.encode(View(image(32, 32, 0)))
    with pytest.raises(PriorError, match="retrieval weights were not loaded"):
        prior.retrieval_features(enc)

    class TopTwo:
        def features(self, tokens):
            attention = tokens.norm(dim=-1)
            top = attention.topk(2).indices
            return tokens[top], attention[top]

    prior.retrieval = TopTwo()
    descriptors, attention = prior.retrieval_features(enc)
    assert descriptors.shape == (2, 32) and attention.shape == (2,)
    assert prior.describe()["retrieval"] is True


def whitening_checkpoint(path: Path, dim: int) -> Path:
    """A retrieval checkpoint in the official layout: pre-whitening only (spec §8.1)."""
    model = {
        "prewhiten.m": torch.zeros(1, dim, dtype=torch.float64),
        "prewhiten.p": torch.eye(dim, dtype=torch.float64),
    }
    torch.save({"model": model, "args": argparse.Namespace(nfeat=5, hdims="")}, path)
    return path


def test_load_mast3r_attaches_retrieval_head(tiny_checkpoint, tmp_path: Path):
    checkpoint = tiny_checkpoint
    retrieval = whitening_checkpoint(tmp_path / "r.pth", 32)
    prior = load_mast3r(checkpoint, retrieval_checkpoint=retrieval)
    descriptors, attention = prior.retrieval_features(prior.encode(View(image(48, 48, 0))))
    assert descriptors.shape == (5, 32) and attention.shape == (5,)
    with pytest.raises(CheckpointError, match="1024-d tokens"):
        load_mast3r(checkpoint, retrieval_checkpoint=whitening_checkpoint(tmp_path / "b.pth", 1024))


def test_cuda_without_cuda_is_a_prior_error(monkeypatch, tmp_path: Path):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    # the device is checked before the (missing) file is read
    with pytest.raises(PriorError, match="CUDA is not available"):
        load_mast3r(tmp_path / "absent.pth", device="cuda")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"device": "tpu"}, "device"),
        ({"device": "quantum:0"}, "device"),
        ({"dtype": torch.float16}, "dtype"),
    ],
)
def test_bad_device_or_dtype_is_a_prior_error(tmp_path: Path, kwargs, message):
    with pytest.raises(PriorError, match=message):
        load_mast3r(tmp_path / "absent.pth", **kwargs)


@pytest.mark.slow
def test_bfloat16_prior_outputs_float32_close_to_float32(tiny_checkpoint):
    full = load_mast3r(tiny_checkpoint)
    half = load_mast3r(tiny_checkpoint, dtype=torch.bfloat16)
    views = [View(image(32, 32, 0)), View(image(32, 32, 1))]
    reference = full.decode(*full.encode(views))
    pred = half.decode(*half.encode(views))
    assert_valid_prediction(pred, (32, 32), (32, 32))
    error = (pred.X_ji - reference.X_ji).norm() / reference.X_ji.norm()
    assert 0 < float(error) < 0.05
    assert half.describe()["dtype"] == "bfloat16" and half.describe()["device"] == "cpu"


def test_tokens_received_across_machines_decode_as_the_exact_ones(prior):
    """Encoder tokens travel in float16 in lossy encodes (zenoh); the pair a receiver decodes
    from them stays within 1e-3 of the exact tokens' (measured here 6e-5 at most per pixel;
    the full-size network: benchmarks/token_precision.py)."""
    exact = [prior.encode(View(image(64, 96, seed), index=seed)) for seed in (0, 1)]
    received = [codec.decode(codec.encode(e, lossy=True)) for e in exact]
    assert all(r.tokens.dtype == torch.float32 for r in received)
    assert not torch.equal(received[0].tokens, exact[0].tokens)  # rounded on the way
    torch.testing.assert_close(received[0].tokens, exact[0].tokens, rtol=2**-11, atol=2**-24)
    assert torch.equal(codec.decode(codec.encode(exact[0])).tokens, exact[0].tokens)  # pipes
    reference, pred = prior.decode(*exact), prior.decode(*received)
    for name in ("X_ii", "X_ji"):
        x, y = getattr(reference, name), getattr(pred, name)
        error = (x - y).norm(dim=-1) / x.norm(dim=-1)
        assert 0 < float(error.max()) < 1e-3, name
    for name in ("C_ii", "C_ji", "Q_ii", "Q_ji"):
        x, y = getattr(reference, name), getattr(pred, name)
        assert float(((x - y).abs() / x).max()) < 1e-3, name
