"""Tests of the MASt3R retrieval head and its checkpoint loader (MAST3R_SPEC.md §8.1-8.2).

Checkpoints are synthetic but in the official format: ``{'args': Namespace, 'model': ...}``
written by ``torch.save``, with tiny dimensions. Expected outputs are computed here from the
spec's formulas with plain torch functions, independently of the module's layers.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from como3r.errors import CheckpointError, InputError
from como3r.prior.mast3r.retrieval import (
    RETRIEVAL_CHECKPOINT_NAME,
    codebook_path_for,
    load_retrieval_head,
)

C = 32  # token channels of the tiny "encoder"


def _whitener(dim: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """A PCA-like whitening ``m (1, dim)``, ``p (dim, dim)`` in float64."""
    basis, _ = torch.linalg.qr(torch.randn(dim, dim, generator=generator, dtype=torch.float64))
    scales = torch.rand(dim, generator=generator, dtype=torch.float64) * 3 + 0.2
    return {"m": torch.randn(1, dim, generator=generator, dtype=torch.float64), "p": basis * scales}


def _state(
    hdims: list[int], prewhiten: bool = True, postwhiten: bool = False, seed: int = 0
) -> dict[str, torch.Tensor]:
    """Official-layout retrieval state dict: prewhiten.*, projector.{0,1,3,...}, postwhiten.*."""
    g = torch.Generator().manual_seed(seed)
    state: dict[str, torch.Tensor] = {}
    if prewhiten:
        state.update({f"prewhiten.{k}": v for k, v in _whitener(C, g).items()})
    dim = C
    for i, hidden in enumerate(hdims):
        state[f"projector.{3 * i}.weight"] = torch.randn(hidden, dim, generator=g) / dim**0.5
        state[f"projector.{3 * i}.bias"] = torch.randn(hidden, generator=g) * 0.1
        if i < len(hdims) - 1:
            state[f"projector.{3 * i + 1}.weight"] = 1 + 0.1 * torch.randn(hidden, generator=g)
            state[f"projector.{3 * i + 1}.bias"] = 0.1 * torch.randn(hidden, generator=g)
        dim = hidden
    if postwhiten:
        state.update({f"postwhiten.{k}": v for k, v in _whitener(dim, g).items()})
    return state


def _save(path: Path, state: dict, **args) -> Path:
    """Write a checkpoint in the official format (an argparse Namespace under 'args')."""
    namespace = argparse.Namespace(freeze_backbone=1, imsize=512, nclusters="64k", **args)
    torch.save({"args": namespace, "model": state, "epoch": 0}, path)
    return path


def _reference(
    tokens: torch.Tensor, state: dict, hdims: list[int], residual: bool, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Spec §8.2 formulas written out with torch.nn.functional."""
    x = tokens.to(torch.float32)
    if "prewhiten.m" in state:
        x = ((x.double() - state["prewhiten.m"]) @ state["prewhiten.p"]).float()
    h = x
    for i in range(len(hdims)):
        h = F.linear(h, state[f"projector.{3 * i}.weight"], state[f"projector.{3 * i}.bias"])
        if i < len(hdims) - 1:
            ln = f"projector.{3 * i + 1}"
            h = F.layer_norm(h, (h.shape[-1],), state[f"{ln}.weight"], state[f"{ln}.bias"], 1e-5)
            h = F.gelu(h, approximate="none")
    if residual:
        h = h + x
    attention = torch.linalg.vector_norm(h, dim=-1)
    if "postwhiten.m" in state:
        h = ((h.double() - state["postwhiten.m"]) @ state["postwhiten.p"]).float()
    order = torch.argsort(attention, descending=True)[:k]
    return h[order], attention[order]


@pytest.mark.parametrize(
    "hdims, postwhiten, residual",
    [([], False, False), ([24, 16], True, False), ([C], False, True), ([48, C], True, True)],
    ids=["prewhiten-only", "mlp-postwhiten", "residual", "mlp-residual-postwhiten"],
)
def test_features_follow_spec_formulas(tmp_path, device, hdims, postwhiten, residual):
    state = _state(hdims, postwhiten=postwhiten)
    hdims_arg = "_".join(map(str, hdims))
    path = _save(
        tmp_path / "r.pth",
        state,
        prewhiten=1,
        hdims=hdims_arg,
        residual=residual,
        postwhiten=1 if postwhiten else None,
        featweights="l2norm",
        nfeat=10,
    )
    head = load_retrieval_head(path, device=device)
    tokens = torch.randn(60, C, generator=torch.Generator().manual_seed(1))

    desc, attn = head.features(tokens.to(device))
    want_desc, want_attn = _reference(tokens, state, hdims, residual, k=10)

    assert desc.shape == (10, hdims[-1] if hdims else C) and attn.shape == (10,)
    assert desc.dtype == torch.float32 and desc.device.type == device.type
    torch.testing.assert_close(attn.cpu(), want_attn, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(desc.cpu(), want_desc, rtol=1e-5, atol=1e-5)
    assert torch.all(attn[:-1] >= attn[1:])


def test_batched_and_flat_tokens_agree(tmp_path):
    head = load_retrieval_head(_save(tmp_path / "r.pth", _state([]), prewhiten=1, nfeat=7))
    tokens = torch.randn(1, 20, C)
    desc_b, attn_b = head.features(tokens)
    desc_f, attn_f = head.features(tokens[0])
    torch.testing.assert_close(desc_b, desc_f)
    torch.testing.assert_close(attn_b, attn_f)


@pytest.mark.parametrize(
    "nfeat, n_tokens, expected", [(-0.25, 40, 10), (-1, 13, 13), (300, 12, 12)]
)
def test_number_of_selected_tokens(tmp_path, nfeat, n_tokens, expected):
    head = load_retrieval_head(_save(tmp_path / "r.pth", _state([]), prewhiten=1, nfeat=nfeat))
    desc, attn = head.features(torch.randn(n_tokens, C))
    assert desc.shape[0] == attn.shape[0] == expected


def test_backbone_tensors_ignored_and_args_optional(tmp_path):
    state = _state([16]) | {"backbone.enc_norm.weight": torch.ones(C)}
    path = tmp_path / "r.pth"
    torch.save({"model": state}, path)
    head = load_retrieval_head(path)
    assert head.nfeat == 300 and head.dim == 16
    tokens = torch.randn(50, C)
    desc, _ = head.features(tokens)
    torch.testing.assert_close(desc, _reference(tokens, state, [16], False, k=50)[0])


def test_bad_tokens_raise_input_error(tmp_path):
    head = load_retrieval_head(_save(tmp_path / "r.pth", _state([]), prewhiten=1))
    with pytest.raises(InputError, match="channels"):
        head.features(torch.randn(10, C + 1))
    with pytest.raises(InputError, match="tokens"):
        head.features(torch.randn(2, 10, C))


def _truncated(path: Path) -> None:
    _save(path, _state([]), prewhiten=1)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _bad_shape(path: Path) -> None:
    state = _state([])
    state["prewhiten.p"] = torch.zeros(C, C + 1, dtype=torch.float64)
    _save(path, state, prewhiten=1)


def _non_finite(path: Path) -> None:
    state = _state([])
    state["prewhiten.m"][0, 3] = float("nan")
    _save(path, state, prewhiten=1)


MALFORMED = {
    "missing file": (lambda p: None, "not found"),
    "garbage": (lambda p: p.write_bytes(os.urandom(256)), "cannot load"),
    "truncated": (_truncated, "cannot load"),
    "no model": (lambda p: torch.save({"args": argparse.Namespace()}, p), "no 'model'"),
    "empty model": (lambda p: torch.save({"model": {}}, p), "infer the input dim"),
    "misplaced linear": (
        lambda p: _save(p, _state([]) | {"projector.2.weight": torch.zeros(4, C)}, prewhiten=1),
        "lacks tensor projector.0.bias",
    ),
    "stray tensor": (
        lambda p: _save(p, _state([]) | {"whatever.weight": torch.zeros(3)}, prewhiten=1),
        "unexpected tensor whatever.weight",
    ),
    "missing prewhiten": (
        lambda p: _save(p, _state([16], prewhiten=False), prewhiten=1, hdims="16"),
        "args.prewhiten",
    ),
    "missing projector bias": (
        lambda p: torch.save(
            {"model": {k: v for k, v in _state([16]).items() if k != "projector.0.bias"}}, p
        ),
        "lacks tensor projector.0.bias",
    ),
    "shape mismatch": (_bad_shape, "prewhiten.p has shape"),
    "hdims mismatch": (lambda p: _save(p, _state([16]), prewhiten=1, hdims="8"), "hdims"),
    "featweights": (
        lambda p: _save(p, _state([]), prewhiten=1, featweights="softplus"),
        "featweights",
    ),
    "nfeat": (lambda p: _save(p, _state([]), prewhiten=1, nfeat=-2), "nfeat"),
    "non-finite": (_non_finite, "not finite"),
    "residual dims": (
        lambda p: _save(p, _state([16]), prewhiten=1, hdims="16", residual=True),
        "residual",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_checkpoints_raise_one_line_error(tmp_path, case):
    write, message = MALFORMED[case]
    path = tmp_path / "bad_retrieval_trainingfree.pth"
    write(path)
    with pytest.raises(CheckpointError) as info:
        load_retrieval_head(path)
    text = str(info.value)
    assert str(path) in text and message in text and "\n" not in text


class _Payload:
    """Unpickling this object would run ``function(argument)``."""

    def __init__(self, function, argument):
        self.function, self.argument = function, argument

    def __reduce__(self):
        return self.function, (self.argument,)


@pytest.mark.parametrize(
    "target, refused", [("os.system", "posix.system"), ("builtins.eval", "eval")]
)
def test_malicious_checkpoint_is_refused_without_running(tmp_path, target, refused):
    marker = tmp_path / "pwned"
    if target == "os.system":
        payload = _Payload(os.system, f"touch {marker}")
    else:
        payload = _Payload(eval, f"open({str(marker)!r}, 'w').close()")
    path = tmp_path / "evil.pth"
    torch.save({"args": argparse.Namespace(nfeat=1), "model": _state([]) | {"x": payload}}, path)

    with pytest.raises(CheckpointError) as info:
        load_retrieval_head(path)
    assert str(path) in str(info.value) and refused in str(info.value)
    assert "weights_only" not in str(info.value)  # never suggest the unsafe fallback
    assert not marker.exists()


def test_codebook_path_for_official_name(tmp_path):
    ckpt = tmp_path / "checkpoints" / RETRIEVAL_CHECKPOINT_NAME
    assert codebook_path_for(ckpt) == ckpt.with_name(
        "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric_retrieval_codebook.pkl"
    )
    assert codebook_path_for("a/b/x_y_z.pth") == Path("a/b/x_y_codebook.pkl")
    with pytest.raises(CheckpointError, match="plain.pth"):
        codebook_path_for("plain.pth")
