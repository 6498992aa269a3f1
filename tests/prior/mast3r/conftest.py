"""Fixtures for the MASt3R tests: a tiny configuration and checkpoints in the official format."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from como3r.prior.mast3r import MASt3RConfig, MASt3RNetwork, parse_model_string
from como3r.prior.mast3r.testing import TINY_MODEL_STRING, official_state_dict, seeded_network


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
    torch.save(
        {
            "model": official_state_dict(network),
            "epoch": 3,
            "args": argparse.Namespace(model=TINY_MODEL_STRING),
        },
        path,
    )
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
