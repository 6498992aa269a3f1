"""Fixtures for the MASt3R tests: a tiny configuration and checkpoints in the official format."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

import pytest
import torch

from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, parse_model_string

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


@pytest.fixture
def tiny_config() -> MASt3RConfig:
    """The configuration of :data:`TINY_MODEL_STRING`."""
    return parse_model_string(TINY_MODEL_STRING)


@pytest.fixture(autouse=True)
def _one_thread():
    """Run each test on one intra-op thread, then restore the setting.

    Tiny networks gain little from a second thread, and OpenMP barriers slow down many-fold
    when the cores are shared with other processes (a test run then takes minutes).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def _tiny_state() -> dict[str, torch.Tensor]:
    """Weights of the tiny network, built once (random initialisation of ~40 M head weights
    is the slow part)."""
    return seeded_network(parse_model_string(TINY_MODEL_STRING), seed=0).state_dict()


def network_from_state(config: MASt3RConfig, state: dict[str, torch.Tensor]) -> MASt3RNetwork:
    """A network (eval) holding copies of ``state``; no random initialisation."""
    with torch.device("meta"):
        network = MASt3RNetwork(config)
    network.load_state_dict({key: value.clone() for key, value in state.items()}, assign=True)
    return network.eval()


@pytest.fixture
def tiny_network(tiny_config: MASt3RConfig, _tiny_state) -> MASt3RNetwork:
    """A tiny network with seeded random weights (CPU, float32, eval); a fresh copy per test."""
    return network_from_state(tiny_config, _tiny_state)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory, _tiny_state) -> Path:
    """The tiny network's checkpoint in the official format, written once (read-only use)."""
    network = network_from_state(parse_model_string(TINY_MODEL_STRING), _tiny_state)
    path = tmp_path_factory.mktemp("mast3r") / "tiny.pth"
    torch.save({"model": official_state_dict(network), "epoch": 3,
                "args": argparse.Namespace(model=TINY_MODEL_STRING)}, path)
    return path


@pytest.fixture
def write_checkpoint(tmp_path: Path) -> Callable[..., Path]:
    """Writer of checkpoints in the official format: ``{'model', 'args', 'epoch'}``."""

    def write(
        network: MASt3RNetwork,
        name: str = "tiny.pth",
        model_string: str | None = TINY_MODEL_STRING,
        state: dict[str, torch.Tensor] | None = None,
    ) -> Path:
        content: dict[str, object] = {
            "model": official_state_dict(network) if state is None else state,
            "epoch": 3,
        }
        if model_string is not None:
            content["args"] = argparse.Namespace(model=model_string, lr=1e-4)
        path = tmp_path / name
        torch.save(content, path)
        return path

    return write


@pytest.fixture
def tiny_model_string() -> str:
    """:data:`TINY_MODEL_STRING`."""
    return TINY_MODEL_STRING


@pytest.fixture
def make_network() -> Callable[[MASt3RConfig, int], MASt3RNetwork]:
    """:func:`seeded_network`."""
    return seeded_network


@pytest.fixture
def make_official_state() -> Callable[[MASt3RNetwork], dict[str, torch.Tensor]]:
    """:func:`official_state_dict`."""
    return official_state_dict
