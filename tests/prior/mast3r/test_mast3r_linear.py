"""The network's Linear layer: oneDNN float32 path, fused GELU, bf16 weight copies."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from como3r.prior.mast3r.blocks import Linear
from como3r.prior.mast3r.testing import tiny_network


def _layer() -> tuple[Linear, torch.Tensor]:
    torch.manual_seed(0)
    layer = Linear(48, 80).requires_grad_(False)
    return layer, torch.randn(2, 7, 48)


def test_float32_inference_equals_f_linear_with_and_without_gelu():
    layer, x = _layer()
    with torch.no_grad():
        reference = F.linear(x, layer.weight, layer.bias)
        torch.testing.assert_close(layer(x), reference, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(layer(x, gelu=True), F.gelu(reference), rtol=1e-5, atol=1e-5)


def test_autograd_still_works():
    layer, x = _layer()
    layer.requires_grad_(True)
    layer(x, gelu=True).sum().backward()
    assert layer.weight.grad is not None and layer.weight.grad.shape == layer.weight.shape


def test_bf16_copies_are_used_under_autocast_and_not_saved():
    layer, x = _layer()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = layer(x)
    layer.set_low_precision(torch.bfloat16)
    assert layer.low_weight.dtype == torch.bfloat16
    assert set(layer.state_dict()) == {"weight", "bias"}
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        copied = layer(x)
    assert copied.dtype == torch.bfloat16
    torch.testing.assert_close(copied.float(), autocast.float(), rtol=2e-2, atol=2e-2)
    layer.set_low_precision(None)
    assert layer.low_weight is None


def test_network_compute_dtype_makes_and_drops_the_copies_of_encoder_and_decoders_only():
    network = tiny_network()
    network.set_compute_dtype(torch.bfloat16)
    assert network.enc_blocks[0].attn.qkv.low_weight.dtype == torch.bfloat16
    assert network.dec_blocks2[-1].mlp.fc2.low_weight.dtype == torch.bfloat16
    assert network.decoder_embed.low_weight is not None
    assert network.downstream_head1.head_local_features.fc1.low_weight is None
    network.set_compute_dtype(torch.float32)
    assert network.enc_blocks[0].attn.qkv.low_weight is None
