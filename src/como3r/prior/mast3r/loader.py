"""Safe, strict loading of the official MASt3R checkpoint (MAST3R_SPEC.md §1.4, §6).

* The file is read with ``torch.load(weights_only=True)``; the only Python class allowed besides
  tensors and containers is ``argparse.Namespace`` (the checkpoint's ``args``). A pickle that
  would import anything else (``os.system``, ...) is refused before it runs.
* ``args.model`` is parsed without eval (:func:`~como3r.prior.mast3r.config.parse_model_string`);
  a checkpoint without it gets the released configuration.
* Every checkpoint key is either loaded into the network or known-unused
  (:data:`KNOWN_UNUSED`); any missing, unexpected or mis-shaped key is a
  :class:`~como3r.errors.CheckpointError` naming the keys.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import pickle
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from como3r.errors import CheckpointError, ConfigError
from como3r.prior.mast3r.config import RELEASED_MODEL_STRING, MASt3RConfig, parse_model_string
from como3r.prior.mast3r.model import MASt3RNetwork

logger = logging.getLogger(__name__)

#: checkpoint keys that are deliberately not loaded (spec §6)
KNOWN_UNUSED = (
    # pre-training mask token, unused at inference
    re.compile(r"mask_token"),
    # alias of scratch.layer{k+1}_rn (the same tensor under a second name); checked equal
    re.compile(r"downstream_head[12]\.dpt\.scratch\.layer_rn\.[0-3]\.weight"),
    # refinenet4 receives a single input, so its first residual unit never runs
    re.compile(
        r"downstream_head[12]\.dpt\.scratch\.refinenet4\.resConfUnit1\.conv[12]\.(weight|bias)"
    ),
    # duplicates of act_postprocess.* and absolute position tables some exports carry
    re.compile(r"downstream_head[12]\.dpt\.act_[1-4]_postprocess\..+"),
    re.compile(r"(enc|dec)_pos_embed"),
)
_ALIAS = re.compile(r"(downstream_head[12]\.dpt\.scratch)\.layer_rn\.([0-3])\.weight")
_LIST_LIMIT = 8


def is_known_unused(key: str) -> bool:
    """True for a checkpoint key that is deliberately not loaded."""
    return any(pattern.fullmatch(key) for pattern in KNOWN_UNUSED)


@dataclass(frozen=True)
class Checkpoint:
    """Contents of a MASt3R checkpoint file.

    Attributes:
        path: the file.
        config: network configuration (from ``args.model``, else the released one).
        model_string: the constructor string it was parsed from.
        state_dict: key -> tensor as stored (float, CPU).
    """

    path: Path
    config: MASt3RConfig
    model_string: str
    state_dict: dict[str, Tensor]


def _names(keys: list[str]) -> str:
    shown = ", ".join(keys[:_LIST_LIMIT])
    more = len(keys) - _LIST_LIMIT
    return shown + (f" (and {more} more)" if more > 0 else "")


def _namespace_allowed() -> contextlib.AbstractContextManager[object]:
    """Let the weights-only unpickler rebuild ``argparse.Namespace`` (plain attributes, no code)."""
    if hasattr(torch.serialization, "safe_globals"):
        return torch.serialization.safe_globals([argparse.Namespace])
    torch.serialization.add_safe_globals([argparse.Namespace])  # torch 2.4: no context manager
    return contextlib.nullcontext()


def _torch_load(path: Path) -> object:
    """``torch.load`` with weights only; every failure becomes one CheckpointError."""
    if not path.is_file():
        raise CheckpointError(f"MASt3R checkpoint {path} does not exist or is not a file")
    if path.stat().st_size == 0:
        raise CheckpointError(f"MASt3R checkpoint {path} is empty")
    try:
        with _namespace_allowed():
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        unsupported = re.search(r"GLOBAL ([\w.]+)", str(error))
        if unsupported:
            name = unsupported.group(1)
            raise CheckpointError(
                f"refusing to load {path}: it would import the Python object '{name}', "
                "which is not tensor data (only tensors and argparse.Namespace are allowed)"
            ) from None
        raise CheckpointError(
            f"refusing to load {path}: it is not a weights-only PyTorch checkpoint "
            "(its pickle uses instructions outside the safe subset)"
        ) from None
    except Exception as error:  # noqa: BLE001 - any reader failure means a bad file
        reason = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise CheckpointError(
            f"cannot read MASt3R checkpoint {path}: not a PyTorch checkpoint, or truncated or "
            f"corrupt ({type(error).__name__}{': ' + reason if reason else ''})"
        ) from None


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read and validate a checkpoint file in the official format (spec §1.2).

    The file is a dict with ``'model'`` (the state dict) and optionally ``'args'`` (an
    ``argparse.Namespace`` whose ``model`` is the constructor string); other entries
    (``epoch``, ...) are ignored.

    Raises:
        CheckpointError: missing, empty, truncated, corrupt or unsafe file, or not a MASt3R
            checkpoint; the message names the file.
    """
    path = Path(path)
    content = _torch_load(path)
    if not isinstance(content, Mapping) or not isinstance(content.get("model"), Mapping):
        raise CheckpointError(f"{path} is not a MASt3R checkpoint: no 'model' state dict")
    state_dict = dict(content["model"])
    bad = [
        key
        for key, value in state_dict.items()
        if not isinstance(key, str)
        or not isinstance(value, Tensor)
        or not value.is_floating_point()
    ]
    if bad:
        names = _names([str(key) for key in bad])
        raise CheckpointError(f"{path}: state dict entries that are not float tensors: {names}")
    model_string = getattr(content.get("args"), "model", None)
    if model_string is None:
        logger.info("%s has no args.model; using the released MASt3R configuration", path)
        model_string = RELEASED_MODEL_STRING
    elif not isinstance(model_string, str):
        raise CheckpointError(f"{path}: args.model is not a string ({type(model_string).__name__})")
    try:
        config = parse_model_string(model_string)
    except (CheckpointError, ConfigError) as error:
        raise CheckpointError(f"{path}: {error}") from None
    return Checkpoint(path=path, config=config, model_string=model_string, state_dict=state_dict)


def select_state_dict(
    expected: Mapping[str, torch.Size], state_dict: Mapping[str, Tensor], source: str
) -> dict[str, Tensor]:
    """The entries of ``state_dict`` the network loads, after strict checks.

    Args:
        expected: the network's key -> shape.
        state_dict: the checkpoint's key -> tensor.
        source: what to name in error messages (the file).

    Returns:
        key -> float32 tensor for exactly the keys of ``expected``.

    Raises:
        CheckpointError: a missing key, an unexpected key (neither expected nor known-unused),
            a shape mismatch, or an alias that differs from the tensor it duplicates.
    """
    missing = [key for key in expected if key not in state_dict]
    unexpected = [key for key in state_dict if key not in expected and not is_known_unused(key)]
    problems = []
    if missing:
        problems.append(f"missing keys: {_names(missing)}")
    if unexpected:
        problems.append(f"unexpected keys: {_names(unexpected)}")
    mismatched = [
        f"{key} {list(state_dict[key].shape)} (expected {list(shape)})"
        for key, shape in expected.items()
        if key in state_dict and state_dict[key].shape != shape
    ]
    if mismatched:
        problems.append(f"shape mismatches: {_names(mismatched)}")
    if problems:
        raise CheckpointError(f"{source} does not fit the MASt3R network: " + "; ".join(problems))
    for key, tensor in state_dict.items():
        alias = _ALIAS.fullmatch(key)
        if alias is None:
            continue
        target = f"{alias.group(1)}.layer{int(alias.group(2)) + 1}_rn.weight"
        if target in state_dict and not torch.equal(tensor, state_dict[target]):
            raise CheckpointError(f"{source}: alias {key} differs from {target}")
    return {key: state_dict[key].float() for key in expected}


def build_network(checkpoint: Checkpoint) -> MASt3RNetwork:
    """The network of ``checkpoint`` with its weights (CPU, float32, strict).

    The modules are created on the meta device and the checkpoint tensors are assigned to
    them, so the random initialisation of ~700 M parameters is skipped.
    """
    with torch.device("meta"):
        network = MASt3RNetwork(checkpoint.config)
    expected = {key: value.shape for key, value in network.state_dict().items()}
    weights = select_state_dict(expected, checkpoint.state_dict, str(checkpoint.path))
    network.load_state_dict(weights, strict=True, assign=True)
    return network.requires_grad_(False)


def load_network(path: str | Path) -> tuple[MASt3RNetwork, str]:
    """Read ``path`` and build its network (CPU, float32); also return ``args.model``.

    The checkpoint dict is not kept: the network's parameters are its tensors.
    See :func:`read_checkpoint` for the errors.
    """
    checkpoint = read_checkpoint(path)
    logger.info("MASt3R checkpoint %s: %s", checkpoint.path, checkpoint.model_string)
    return build_network(checkpoint), checkpoint.model_string
