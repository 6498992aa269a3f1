"""Tiny MASt3R networks and checkpoints in the official format, for tests and examples.

The released weights cannot be bundled; these helpers write checkpoints with the official
file structure (``{'model': state_dict, 'args': Namespace(model=...)}``, the official key
set including the keys the network never uses) for any configuration the constructor
string expresses, so loaders and pipelines can be exercised without a download.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from como3r.prior.mast3r.config import MASt3RConfig, parse_model_string
from como3r.prior.mast3r.model import MASt3RNetwork

#: a tiny network the constructor string can express (fast on CPU)
TINY_MODEL_STRING = (
    "AsymmetricMASt3R(pos_embed='RoPE100', patch_embed_cls='ManyAR_PatchEmbed', "
    "img_size=(512, 512), head_type='catmlp+dpt', output_mode='pts3d+desc24', "
    "depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim=32, "
    "enc_depth=2, enc_num_heads=2, dec_embed_dim=32, dec_depth=2, dec_num_heads=2, "
    "two_confs=True, desc_conf_mode=('exp', 0, inf))"
)


def official_state_dict(network: MASt3RNetwork) -> dict[str, torch.Tensor]:
    """The network's state dict plus the keys the official one also holds (spec §6).

    Adds ``mask_token``, the ``scratch.layer_rn.k`` aliases (the same tensors) and the
    never-used ``refinenet4.resConfUnit1`` of both heads.
    """
    state = dict(network.state_dict())
    config = network.config
    generator = torch.Generator().manual_seed(7)
    state["mask_token"] = torch.randn(1, 1, config.dec_embed_dim, generator=generator)
    for head in ("downstream_head1", "downstream_head2"):
        scratch = f"{head}.dpt.scratch"
        for k in range(4):
            state[f"{scratch}.layer_rn.{k}.weight"] = state[f"{scratch}.layer{k + 1}_rn.weight"]
        for conv in ("conv1", "conv2"):
            prefix = f"{scratch}.refinenet4.resConfUnit1.{conv}"
            state[f"{prefix}.weight"] = torch.randn(256, 256, 3, 3, generator=generator)
            state[f"{prefix}.bias"] = torch.randn(256, generator=generator)
    return state


def seeded_network(config: MASt3RConfig, seed: int) -> MASt3RNetwork:
    """Seeded default initialisation, plus random LayerNorm weights and biases (eval mode)."""
    torch.manual_seed(seed)
    network = MASt3RNetwork(config)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in network.named_parameters():
            if parameter.dim() == 1:
                noise = 0.1 * torch.randn(parameter.shape, generator=generator)
                is_norm_weight = "norm" in name and name.endswith("weight")
                parameter.copy_(1 + noise if is_norm_weight else noise)
    return network.eval()


def write_checkpoint(
    path: str | Path, network: MASt3RNetwork, model_string: str = TINY_MODEL_STRING
) -> Path:
    """Write ``network`` as an official-format checkpoint; returns the path."""
    path = Path(path)
    torch.save(
        {
            "model": official_state_dict(network),
            "epoch": 3,
            "args": argparse.Namespace(model=model_string),
        },
        path,
    )
    return path


def tiny_network(seed: int = 0) -> MASt3RNetwork:
    """A seeded network of :data:`TINY_MODEL_STRING`."""
    return seeded_network(parse_model_string(TINY_MODEL_STRING), seed)
