"""Tests of como3r/prior/mast3r/loader.py: safe, strict loading of official-format checkpoints."""

from __future__ import annotations

import argparse
import os
import pickle
from pathlib import Path

import pytest
import torch

from como3r.errors import CheckpointError
from como3r.prior.mast3r.config import MASt3RConfig
from como3r.prior.mast3r.loader import load_network, read_checkpoint


class RunsCommand:
    """Pickles to ``os.system(command)``: what a malicious checkpoint would contain."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


@pytest.mark.slow
def test_round_trip_is_strict_and_deterministic(tiny_network, write_checkpoint):
    path = write_checkpoint(tiny_network)
    network, model_string = load_network(path)
    assert network.config == tiny_network.config and "enc_embed_dim=32" in model_string
    loaded = network.state_dict()
    assert loaded.keys() == tiny_network.state_dict().keys()
    assert all(torch.equal(loaded[k], v) for k, v in tiny_network.state_dict().items())
    assert not any(p.requires_grad for p in network.parameters())
    images = torch.rand(2, 1, 3, 48, 80) * 2 - 1
    with torch.no_grad():
        expected = tiny_network(images[0], images[1])
        first = network(images[0], images[1])
        second = load_network(path)[0](images[0], images[1])
    for a, b, c in zip(expected, first, second):
        assert torch.equal(a.pts3d, b.pts3d) and torch.equal(b.pts3d, c.pts3d)
        assert torch.equal(a.desc, b.desc) and torch.equal(b.desc_conf, c.desc_conf)


def test_known_unused_keys_are_optional(tiny_network, write_checkpoint):
    path = write_checkpoint(tiny_network, state=dict(tiny_network.state_dict()))
    network, _ = load_network(path)
    assert torch.equal(network.enc_norm.weight, tiny_network.enc_norm.weight)


def test_checkpoint_without_args_gets_released_configuration(tiny_network, write_checkpoint):
    path = write_checkpoint(tiny_network, model_string=None)
    assert read_checkpoint(path).config == MASt3RConfig()
    # tiny weights do not fit the released network: shapes are named
    with pytest.raises(CheckpointError, match=r"shape mismatches: patch_embed\.proj\.weight"):
        load_network(path)


def test_unknown_constructor_argument_names_file_and_argument(
    tiny_network, write_checkpoint, tiny_model_string
):
    path = write_checkpoint(
        tiny_network, model_string=tiny_model_string.replace(")", ", use_magic=True)")
    )
    with pytest.raises(CheckpointError, match="use_magic") as error:
        read_checkpoint(path)
    assert str(path) in str(error.value)


def test_missing_key_is_named(tiny_network, write_checkpoint):
    state = dict(tiny_network.state_dict())
    del state["dec_blocks2.1.norm_y.bias"]
    with pytest.raises(CheckpointError, match=r"missing keys: dec_blocks2\.1\.norm_y\.bias"):
        load_network(write_checkpoint(tiny_network, state=state))


def test_unexpected_key_is_named(tiny_network, write_checkpoint):
    state = dict(tiny_network.state_dict())
    state["enc_blocks.0.attn.q_norm.weight"] = torch.ones(16)
    with pytest.raises(CheckpointError, match=r"unexpected keys: enc_blocks\.0\.attn\.q_norm"):
        load_network(write_checkpoint(tiny_network, state=state))


def test_shape_mismatch_is_named(tiny_network, write_checkpoint):
    state = dict(tiny_network.state_dict())
    state["decoder_embed.bias"] = torch.zeros(33)
    with pytest.raises(CheckpointError, match=r"decoder_embed\.bias \[33\] \(expected \[32\]\)"):
        load_network(write_checkpoint(tiny_network, state=state))


def test_alias_that_differs_is_refused(tiny_network, write_checkpoint, make_official_state):
    state = make_official_state(tiny_network)
    key = "downstream_head2.dpt.scratch.layer_rn.2.weight"
    state[key] = state[key].clone() + 1
    with pytest.raises(CheckpointError, match=r"alias .*layer_rn\.2\.weight differs"):
        load_network(write_checkpoint(tiny_network, state=state))


def test_malicious_torch_save_is_refused_without_running(tiny_network, tmp_path: Path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pth"
    torch.save(
        {"model": dict(tiny_network.state_dict()), "args": RunsCommand(f"touch {marker}")}, path
    )
    with pytest.raises(CheckpointError, match=r"refusing to load .*evil\.pth.*system"):
        read_checkpoint(path)
    assert not marker.exists()


def test_malicious_plain_pickle_is_refused_without_running(tmp_path: Path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"model": RunsCommand(f"touch {marker}")}, protocol=2))
    with pytest.raises(CheckpointError, match="refusing to load"):
        read_checkpoint(path)
    assert not marker.exists()


def test_truncated_file_is_one_clear_error(tiny_network, write_checkpoint, tmp_path: Path):
    data = write_checkpoint(tiny_network).read_bytes()
    truncated = tmp_path / "truncated.pth"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"truncated\.pth.*truncated or corrupt"):
        read_checkpoint(truncated)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("empty.pth", b"", "is empty"),
        ("text.pth", b"this is not a checkpoint\n", "not a PyTorch checkpoint"),
        ("absent.pth", None, "does not exist"),
    ],
)
def test_wrong_files_are_one_clear_error(tmp_path: Path, name, content, message):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError, match=message) as error:
        read_checkpoint(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ([1, 2, 3], "no 'model' state dict"),
        ({"state_dict": {}}, "no 'model' state dict"),
        ({"model": {"a": torch.zeros(2, dtype=torch.int64)}}, "not float tensors: a"),
        ({"model": {}, "args": argparse.Namespace(model=42)}, "args.model is not a string"),
    ],
)
def test_wrong_content_is_one_clear_error(tmp_path: Path, content, message):
    path = tmp_path / "other.pth"
    torch.save(content, path)
    with pytest.raises(CheckpointError, match=message) as error:
        read_checkpoint(path)
    assert str(path) in str(error.value)
