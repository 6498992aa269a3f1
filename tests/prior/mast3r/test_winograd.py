"""Winograd F(4x4, 3x3) convolution of the DPT (como3r.prior.mast3r.winograd) and its use."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from como3r.prior.mast3r import winograd
from como3r.prior.mast3r.heads import Conv3x3, conv2d


def _relative(value: torch.Tensor, reference: torch.Tensor) -> float:
    return float((value.double() - reference).norm() / reference.norm())


def _reference(x, weight, bias, add, relu):
    """Direct convolution in float64."""
    y = F.conv2d(x.double(), weight.double(), None if bias is None else bias.double(), padding=1)
    if add is not None:
        y = y + add.double()
    return y.relu() if relu else y


@pytest.mark.parametrize(
    ("batch", "c_in", "c_out", "height", "width"),
    [(1, 3, 5, 4, 4), (2, 16, 8, 12, 20), (1, 64, 64, 32, 24), (1, 8, 40, 4, 36)],
)
@pytest.mark.parametrize(
    ("with_bias", "with_add", "relu"),
    [(True, False, False), (False, True, False), (True, True, True)],
)
@pytest.mark.parametrize("threads", [1, 2])
def test_equals_a_direct_convolution(
    batch, c_in, c_out, height, width, with_bias, with_add, relu, threads
):
    generator = torch.Generator().manual_seed(c_in + height)
    x = torch.randn(batch, c_in, height, width, generator=generator)
    x = x.contiguous(memory_format=torch.channels_last)
    weight = torch.randn(c_out, c_in, 3, 3, generator=generator) / (3 * c_in**0.5)
    bias = torch.randn(c_out, generator=generator) if with_bias else None
    add = torch.randn(batch, c_out, height, width, generator=generator) if with_add else None
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        out = winograd.winograd_conv3x3(x, winograd.filter_transform(weight), bias, add, relu)
    finally:
        torch.set_num_threads(previous)
    assert out.shape == (batch, c_out, height, width)
    assert out.is_contiguous(memory_format=torch.channels_last)
    # F(4x4, 3x3) rounds about 4x more than a direct float32 convolution (~5e-7)
    assert _relative(out, _reference(x, weight, bias, add, relu)) < 1e-5


def test_refuses_sides_that_are_not_multiples_of_4():
    x = torch.randn(1, 4, 6, 8)
    with pytest.raises(ValueError, match="multiples of 4"):
        winograd.winograd_conv3x3(x, winograd.filter_transform(torch.randn(4, 4, 3, 3)), None)


def test_filter_transform_of_a_centre_tap_is_the_identity_tile():
    """A kernel with one 1 in the centre: U = G e G^T holds G's middle column products."""
    weight = torch.zeros(1, 1, 3, 3, dtype=torch.float64)
    weight[0, 0, 1, 1] = 1.0
    U = winograd.filter_transform(weight).reshape(6, 6)
    middle = torch.from_numpy(winograd.G[:, 1])
    torch.testing.assert_close(U, torch.outer(middle, middle))


def test_conv3x3_runs_winograd_on_multiples_of_4_and_onednn_otherwise(monkeypatch):
    conv = Conv3x3(8, 8).requires_grad_(False)
    calls = []
    original = winograd.winograd_conv3x3

    def spy(*args, **kwargs):
        calls.append(args[0].shape)
        return original(*args, **kwargs)

    monkeypatch.setattr("como3r.prior.mast3r.heads.winograd_conv3x3", spy)
    for height, width in ((8, 12), (6, 12)):
        x = torch.randn(1, 8, height, width).contiguous(memory_format=torch.channels_last)
        with torch.no_grad():
            out = conv2d(conv, x, relu=True)
        expected = _reference(x, conv.weight, conv.bias, None, True)
        assert _relative(out, expected) < 1e-5
    assert calls == [(1, 8, 8, 12)]


def test_conv3x3_transform_follows_new_weights():
    conv = Conv3x3(4, 4).requires_grad_(False)
    x = torch.randn(1, 4, 8, 8).contiguous(memory_format=torch.channels_last)
    with torch.no_grad():
        conv2d(conv, x)
        conv.load_state_dict({"weight": torch.randn(4, 4, 3, 3), "bias": torch.zeros(4)})
        out = conv2d(conv, x)
    assert _relative(out, _reference(x, conv.weight, conv.bias, None, False)) < 1e-5


def test_zero_padding_does_not_depend_on_what_memory_held():
    """The padded input is allocated uninitialised: its border must be written, not assumed
    zero (freed NaN-filled blocks of the same size are what the allocator hands back)."""
    x = torch.randn(1, 8, 8, 12).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(5, 8, 3, 3)
    for _ in range(3):
        poison = torch.full((1, 10, 14, 8), float("nan"))
        del poison
    out = winograd.winograd_conv3x3(x, winograd.filter_transform(weight), None)
    assert torch.isfinite(out).all()
    assert _relative(out, _reference(x, weight, None, None, False)) < 1e-5
