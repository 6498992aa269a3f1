"""Tests of the MASt3R network modules (model.py, blocks.py, heads.py) on tiny configurations."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from como3r.prior.mast3r.blocks import SelfAttention
from como3r.prior.mast3r.config import MASt3RConfig
from como3r.prior.mast3r.heads import CatMlpDptHead
from como3r.prior.mast3r.loader import is_known_unused
from como3r.prior.mast3r.model import MASt3RNetwork
from como3r.prior.mast3r.rope import RoPE2D

KEYS_TSV = Path(__file__).resolve().parent / "data" / "mast3r_state_dict_keys.tsv"


def read_keys_tsv() -> dict[str, list[int]]:
    """The 1017 official keys and shapes (spec §6), a copy of ../shared/ kept as test data."""
    assert KEYS_TSV.is_file(), f"test data {KEYS_TSV} is missing (copy of the spec's key list)"
    shapes = {}
    for line in KEYS_TSV.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        key, shape, dtype = line.split("\t")
        assert dtype == "float32"
        shapes[key] = [int(size) for size in shape.strip("[]").split(",") if size.strip()]
    return shapes


def images(batch: int, height: int, width: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 3, height, width, generator=generator) * 2 - 1


def test_full_configuration_has_the_official_keys_and_shapes():
    official = read_keys_tsv()
    assert len(official) == 1017
    with torch.device("meta"):
        network = MASt3RNetwork(MASt3RConfig())
    ours = {key: list(value.shape) for key, value in network.state_dict().items()}
    unused = sorted(key for key in official if is_known_unused(key))
    expected = {key: shape for key, shape in official.items() if not is_known_unused(key)}
    assert ours == expected
    # known-unused: mask_token, 2 x 4 layer_rn aliases, 2 x 4 tensors of refinenet4's first RCU
    assert len(unused) == 17 and "mask_token" in unused
    assert sum("layer_rn." in key for key in unused) == 8
    assert sum("refinenet4.resConfUnit1" in key for key in unused) == 8


def test_self_attention_equals_explicit_softmax_with_head_major_layout():
    torch.manual_seed(0)
    dim, heads, grid = 32, 2, (3, 4)
    rope = RoPE2D(100.0)
    attention = SelfAttention(dim, heads, rope).double()
    x = torch.randn(2, 12, dim, dtype=torch.float64)
    qkv = x @ attention.qkv.weight.T + attention.qkv.bias
    outputs = []
    for h in range(heads):
        q = qkv[..., h * 16 : (h + 1) * 16]
        k = qkv[..., dim + h * 16 : dim + (h + 1) * 16]
        v = qkv[..., 2 * dim + h * 16 : 2 * dim + (h + 1) * 16]
        q = rope.apply(q[:, None], grid)[:, 0]
        k = rope.apply(k[:, None], grid)[:, 0]
        weights = torch.softmax(q @ k.transpose(1, 2) / math.sqrt(16), dim=-1)
        outputs.append(weights @ v)
    expected = torch.cat(outputs, dim=-1) @ attention.proj.weight.T + attention.proj.bias
    torch.testing.assert_close(attention(x, grid), expected)


def test_decoders_advance_simultaneously(tiny_network):
    """With decoder 2 and head 2 equal to decoder 1 and head 1, swapping views swaps outputs.

    This holds only if block i of each decoder reads the other's layer i-1 (spec §4.3).
    """
    network = tiny_network
    network.dec_blocks2.load_state_dict(network.dec_blocks.state_dict())
    tokens_a = torch.randn(1, 6, 32)
    tokens_b = torch.randn(1, 6, 32)
    with torch.no_grad():
        a1, b2 = network.decode(tokens_a, (2, 3), tokens_b, (2, 3))
        b1, a2 = network.decode(tokens_b, (2, 3), tokens_a, (2, 3))
    assert set(a1) == {0, 1, 2}
    for index in a1:
        torch.testing.assert_close(a1[index], a2[index])
        torch.testing.assert_close(b1[index], b2[index])


def test_local_features_pixel_layout(tiny_network):
    """Pixel (16y + i, 16x + j) of channel c is element c*256 + i*16 + j of token (y, x)."""
    head = tiny_network.downstream_head1
    grid = (2, 3)
    layers = {k: torch.randn(1, 6, 32) for k in (0, 1, 2)}
    with torch.no_grad():
        out = head(layers, grid)
        raw = head.head_local_features(torch.cat([layers[0], layers[2]], dim=-1))[0]
    for y, x, i, j in [(0, 0, 0, 0), (1, 2, 15, 3), (0, 1, 7, 15), (1, 0, 9, 9)]:
        token = raw[y * 3 + x]
        descriptor = torch.stack([token[c * 256 + i * 16 + j] for c in range(24)])
        torch.testing.assert_close(
            out.desc[0, 16 * y + i, 16 * x + j], descriptor / descriptor.norm()
        )
        torch.testing.assert_close(
            out.desc_conf[0, 16 * y + i, 16 * x + j], token[24 * 256 + i * 16 + j].exp()
        )


def _reference_dpt(dpt, layers: list[torch.Tensor], grid: tuple[int, int]) -> torch.Tensor:
    """The DPT adapter as spec §5.1 writes it: NCHW, one operation at a time."""

    def rcu(unit, z):
        return z + unit.conv2(F.relu(unit.conv1(F.relu(z))))

    def fusion(block, path, skip=None):
        if skip is not None:
            path = path + rcu(block.resConfUnit1, skip)
        up = F.interpolate(
            rcu(block.resConfUnit2, path), scale_factor=2, mode="bilinear", align_corners=True
        )
        return block.out_conv(up)

    levels = [
        post(tokens.transpose(1, 2).unflatten(-1, grid).contiguous())
        for post, tokens in zip(dpt.act_postprocess, layers)
    ]
    scratch = dpt.scratch
    l1, l2, l3, l4 = (getattr(scratch, f"layer{k}_rn")(x) for k, x in enumerate(levels, 1))
    path = fusion(scratch.refinenet4, l4)[:, :, : l3.shape[2], : l3.shape[3]]
    path = fusion(
        scratch.refinenet1, fusion(scratch.refinenet2, fusion(scratch.refinenet3, path, l3), l2), l1
    )
    conv1, _, conv2, _, conv3 = dpt.head
    up = F.interpolate(conv1(path), scale_factor=2, mode="bilinear", align_corners=True)
    return conv3(F.relu(conv2(up)))


@pytest.mark.parametrize("grad", [False, True], ids=["inference", "autograd"])
def test_channels_last_dpt_equals_the_nchw_reference(tiny_network, grad):
    """Channels-last DPT with fused ReLU/residual convolutions (oneDNN for inference, F.conv2d
    under autograd) and out_conv before the up-sampling = the plain NCHW formulation."""
    dpt = tiny_network.downstream_head1.dpt
    grid = (3, 5)  # odd: the stride-2 level is cropped
    torch.manual_seed(0)
    layers = [torch.randn(2, 15, 32) for _ in range(4)]
    with torch.no_grad():
        expected = _reference_dpt(dpt, layers, grid)
    with torch.set_grad_enabled(grad):
        out = dpt(layers, grid)
    assert out.shape == (2, 4, 48, 80)
    assert out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out.detach(), expected, rtol=1e-5, atol=1e-5)


def test_postprocessing_formulas(tiny_config):
    head = CatMlpDptHead(tiny_config)
    fmap = torch.randn(2, 4, 5, 29, dtype=torch.float64)
    out = head.postprocess(fmap)
    xyz = fmap[..., :3]
    distance = xyz.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(out.pts3d, xyz / distance * torch.expm1(distance))
    torch.testing.assert_close(out.conf, 1 + fmap[..., 3].exp())
    torch.testing.assert_close(out.desc, F.normalize(fmap[..., 4:28], dim=-1))
    torch.testing.assert_close(out.desc_conf, fmap[..., 28].exp())


def test_single_confidence_configuration_copies_conf():
    config = MASt3RConfig(
        enc_embed_dim=32,
        enc_depth=1,
        enc_num_heads=2,
        dec_embed_dim=32,
        dec_depth=2,
        dec_num_heads=2,
        two_confs=False,
        conf_max=3.0,
    )
    head = CatMlpDptHead(config)
    assert head.head_local_features.fc2.out_features == 24 * 256
    out = head.postprocess(torch.randn(1, 2, 2, 28) * 3)
    assert torch.equal(out.desc_conf, out.conf)
    assert float(out.conf.max()) <= 3.0 and float(out.conf.min()) >= 1.0


@pytest.mark.parametrize(("height", "width"), [(48, 80), (80, 48), (32, 32), (16, 48)])
def test_network_on_odd_grids_and_portrait(tiny_network, height, width):
    with torch.no_grad():
        out1, out2 = tiny_network(images(1, height, width), images(1, height, width, seed=1))
    for out in (out1, out2):
        assert out.pts3d.shape == (1, height, width, 3)
        assert out.conf.shape == out.desc_conf.shape == (1, height, width)
        assert out.desc.shape == (1, height, width, 24)
        assert all(
            t.dtype == torch.float32 and torch.isfinite(t).all()
            for t in (out.pts3d, out.conf, out.desc, out.desc_conf)
        )
        assert float(out.conf.min()) >= 1.0 and float(out.desc_conf.min()) > 0.0
        torch.testing.assert_close(out.desc.norm(dim=-1), torch.ones(1, height, width))


@pytest.mark.parametrize("dec_depth", [1, 3])
def test_other_decoder_depths_run(make_network, dec_depth):
    config = MASt3RConfig(
        enc_embed_dim=32,
        enc_depth=1,
        enc_num_heads=2,
        dec_embed_dim=16,
        dec_depth=dec_depth,
        dec_num_heads=1,
    )
    network = make_network(config, 0)
    with torch.no_grad():
        out1, _ = network(images(1, 32, 48), images(1, 32, 48, seed=1))
    assert out1.pts3d.shape == (1, 32, 48, 3) and torch.isfinite(out1.pts3d).all()


def test_encoder_output_is_layer_normalised(tiny_network):
    with torch.no_grad():
        tiny_network.enc_norm.weight.fill_(1.0)
        tiny_network.enc_norm.bias.zero_()
        tokens, grid = tiny_network.encode(images(2, 48, 64))
    assert grid == (3, 4) and tokens.shape == (2, 12, 32) and tokens.dtype == torch.float32
    torch.testing.assert_close(tokens.mean(-1), torch.zeros(2, 12), atol=1e-5, rtol=0)
    torch.testing.assert_close(tokens.var(-1, unbiased=False), torch.ones(2, 12), atol=1e-3, rtol=0)


def test_bfloat16_runs_encoder_and_decoder_in_bf16_heads_in_float32(tiny_network):
    pair = (images(1, 32, 32), images(1, 32, 32, seed=1))
    with torch.no_grad():
        reference = tiny_network(*pair)
        tiny_network.set_compute_dtype(torch.bfloat16)
        tokens, _ = tiny_network.encode(pair[0])
        low = tiny_network(*pair)
    assert tokens.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in tiny_network.parameters())
    for ref, out in zip(reference, low):
        assert out.pts3d.dtype == torch.float32
        assert not torch.equal(out.pts3d, ref.pts3d)  # bf16 did change the computation
        error = (out.pts3d - ref.pts3d).norm() / ref.pts3d.norm()
        assert float(error) < 0.05
