"""MASt3R retrieval head and its "training-free" checkpoint (MAST3R_SPEC.md §8.1-8.2).

The head turns the encoder tokens of one image, ``(N, C)`` after ``enc_norm``, into the
local descriptors that ASMK indexes (:mod:`como3r.prior.retrieval`):

1. pre-whitening ``y = (x - m) p`` in float64 (PCA whitening learnt on encoder tokens);
2. projector: identity, or ``Linear -> LayerNorm(eps 1e-5) -> GELU`` per hidden dim and a
   final ``Linear``; with ``residual`` the pre-whitened tokens are added;
3. attention ``a_n = ||f_n||_2`` of the projector output (``featweights='l2norm'``);
4. post-whitening (identity, or a second whitener) of the projector output;
5. the ``nfeat`` tokens of highest attention are kept, in descending attention order.

The released checkpoint holds pre-whitening only (§8.1, inferred from its size), so the
descriptors have ``d = C = 1024``; the loader still accepts every layout the official
class can write, for any dimension. This is our own implementation from the spec.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from como3r.errors import CheckpointError, InputError

#: file name of the official retrieval checkpoint (MAST3R_SPEC.md §1.1)
RETRIEVAL_CHECKPOINT_NAME = (
    "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric_retrieval_trainingfree.pth"
)

#: ``nfeat`` of the official ``RetrievalModel`` when ``args`` does not say
DEFAULT_NFEAT = 300

#: LayerNorm epsilon inside the projector (torch default, unlike the ViT's 1e-6)
PROJECTOR_LN_EPS = 1e-5


def codebook_path_for(retrieval_ckpt_path: str | Path) -> Path:
    """Path of the ASMK codebook that belongs to a retrieval checkpoint (§1.1).

    The basename is split on ``_``, its last piece (``trainingfree.pth``) dropped and
    ``_codebook.pkl`` appended; the codebook sits in the same directory.
    """
    path = Path(retrieval_ckpt_path)
    pieces = path.name.split("_")
    if len(pieces) < 2:
        raise CheckpointError(
            f"{path}: cannot derive the codebook name (expected '<name>_trainingfree.pth')"
        )
    return path.with_name("_".join(pieces[:-1]) + "_codebook.pkl")


class Whitener(nn.Module):
    """Affine whitening ``y = (x - m) p`` computed in float64.

    Buffers ``m`` ``(1, dim)`` and ``p`` ``(dim, dim)`` are float64, as in the checkpoint.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("m", torch.zeros(1, dim, dtype=torch.float64))
        self.register_buffer("p", torch.eye(dim, dtype=torch.float64))

    def forward(self, x: Tensor) -> Tensor:
        """Whiten ``x`` ``(..., dim)``; the result has the dtype of ``x``."""
        # float64 on purpose: the whitening matrix scales small eigen-directions up by
        # orders of magnitude, and the official code disables autocast here (§8.2).
        flat = x.reshape(-1, x.shape[-1]).to(self.m.dtype)
        return ((flat - self.m) @ self.p).reshape(x.shape).to(x.dtype)


def _build_projector(in_dim: int, hdims: Sequence[int]) -> nn.Module:
    """Identity for no ``hdims``; else ``[Linear, LayerNorm, GELU] * (L-1) + [Linear]``.

    Module indices (hence state-dict keys ``projector.{0,1,3,4,...}``) follow that order.
    """
    if not hdims:
        return nn.Identity()
    layers: list[nn.Module] = []
    dim = in_dim
    for hidden in hdims[:-1]:
        layers += [nn.Linear(dim, hidden), nn.LayerNorm(hidden, eps=PROJECTOR_LN_EPS), nn.GELU()]
        dim = hidden
    layers.append(nn.Linear(dim, hdims[-1]))
    return nn.Sequential(*layers)


class RetrievalHead(nn.Module):
    """Local retrieval descriptors from MASt3R encoder tokens (§8.2).

    Args:
        in_dim: channels ``C`` of the encoder tokens (1024 for ViT-L).
        hdims: projector output dims; empty for an identity projector.
        prewhiten: whether a pre-whitener ``prewhiten.{m,p}`` is applied.
        postwhiten: whether a post-whitener ``postwhiten.{m,p}`` is applied.
        residual: add the pre-whitened tokens to the projector output.
        nfeat: tokens kept per image: ``nfeat`` if >= 1, else ``int(-nfeat * N)``.
    """

    def __init__(
        self,
        in_dim: int,
        hdims: Sequence[int] = (),
        prewhiten: bool = True,
        postwhiten: bool = False,
        residual: bool = False,
        nfeat: float = DEFAULT_NFEAT,
    ) -> None:
        super().__init__()
        self.in_dim = in_dim
        self.dim = hdims[-1] if hdims else in_dim
        if residual and self.dim != in_dim:
            raise ValueError(f"residual projector needs output dim {self.dim} == {in_dim}")
        self.residual = residual
        self.nfeat = nfeat
        self.prewhiten = Whitener(in_dim) if prewhiten else nn.Identity()
        self.projector = _build_projector(in_dim, hdims)
        self.postwhiten = Whitener(self.dim) if postwhiten else nn.Identity()

    def forward(self, tokens: Tensor) -> tuple[Tensor, Tensor]:
        """Per-token descriptors and attention.

        Args:
            tokens: ``(..., N, C)`` encoder tokens after ``enc_norm``; cast to float32.

        Returns:
            ``features (..., N, d)`` float32 (post-whitened) and ``attention (..., N)``,
            the L2 norm of each token's projector output before post-whitening.
        """
        whitened = self.prewhiten(tokens.to(torch.float32))
        projected = self.projector(whitened)
        if self.residual:
            projected = projected + whitened
        attention = projected.norm(dim=-1)
        return self.postwhiten(projected), attention

    def num_selected(self, n_tokens: int) -> int:
        """How many of ``n_tokens`` tokens :meth:`features` keeps."""
        wanted = int(-self.nfeat * n_tokens) if self.nfeat < 0 else int(self.nfeat)
        return min(wanted, n_tokens)

    @torch.no_grad()
    def features(self, tokens: Tensor) -> tuple[Tensor, Tensor]:
        """Top-attention local descriptors of one image (HOW's local selection).

        Args:
            tokens: ``(N, C)`` or ``(1, N, C)`` encoder tokens of one image.

        Returns:
            ``descriptors (K, d)`` float32 and ``attention (K,)``, sorted by descending
            attention, ``K = num_selected(N)``.
        """
        if tokens.ndim == 3 and tokens.shape[0] == 1:
            tokens = tokens[0]
        if tokens.ndim != 2:
            raise InputError(
                f"retrieval head: expected tokens (N, C) or (1, N, C), got {tuple(tokens.shape)}"
            )
        if tokens.shape[-1] != self.in_dim:
            raise InputError(
                f"retrieval head: tokens have {tokens.shape[-1]} channels, "
                f"the checkpoint expects {self.in_dim}"
            )
        features, attention = self(tokens)
        top_attention, top = torch.topk(attention, self.num_selected(tokens.shape[0]))
        return features[top], top_attention


# ---------------------------------------------------------------------------------------
# Loading the official checkpoint
# ---------------------------------------------------------------------------------------


def _namespace_allowed() -> contextlib.AbstractContextManager[Any]:
    """Let ``weights_only`` loading rebuild the ``argparse.Namespace`` under ``'args'``.

    A Namespace only holds attributes; it runs no code when unpickled.
    """
    if hasattr(torch.serialization, "safe_globals"):
        return torch.serialization.safe_globals([argparse.Namespace])
    torch.serialization.add_safe_globals([argparse.Namespace])  # torch 2.4
    return contextlib.nullcontext()


def _load_failure(exc: Exception) -> str:
    """One line saying why ``torch.load(weights_only=True)`` failed.

    torch's own message is several paragraphs and suggests ``weights_only=False``, which
    must never be followed for an untrusted file; keep only the refused global if any.
    """
    message = str(exc)
    refused = re.search(r"GLOBAL ([\w.]+)", message)
    if refused:
        return f"refused: it imports {refused.group(1)}, which a checkpoint never needs"
    if message.startswith("Weights only load failed"):
        return "refused: content not allowed in a weights-only checkpoint"
    lines = [line.strip() for line in message.splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def _read_checkpoint(path: Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """``(state_dict without backbone.*, args as a dict)`` of a retrieval checkpoint."""
    if not path.is_file():
        raise CheckpointError(f"{path}: retrieval checkpoint not found")
    try:
        with _namespace_allowed():
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any load failure means a bad or unsafe file
        raise CheckpointError(
            f"{path}: cannot load retrieval checkpoint ({_load_failure(exc)})"
        ) from None
    if not isinstance(ckpt, Mapping) or not isinstance(ckpt.get("model"), Mapping):
        raise CheckpointError(f"{path}: retrieval checkpoint has no 'model' state dict")
    state = {}
    for key, value in ckpt["model"].items():
        if not isinstance(key, str) or not isinstance(value, Tensor):
            raise CheckpointError(f"{path}: state-dict entry {key!r} is not a tensor")
        if key.startswith("backbone."):  # frozen backbone: the MASt3R network itself
            continue
        if not value.is_floating_point() or not torch.isfinite(value).all():
            raise CheckpointError(f"{path}: tensor {key} is not finite floating point")
        state[key] = value
    args = ckpt.get("args")
    if isinstance(args, argparse.Namespace):
        args = vars(args)
    if args is not None and not isinstance(args, Mapping):
        raise CheckpointError(f"{path}: 'args' is neither a Namespace nor a mapping")
    return state, dict(args or {})


def _parse_hdims(value: Any, path: Path) -> list[int]:
    """``args.hdims``: ints joined by ``_`` (``''`` for none) or a list of ints."""
    try:
        if isinstance(value, str):
            return [int(piece) for piece in value.split("_") if piece]
        return [int(v) for v in value]
    except (TypeError, ValueError):
        raise CheckpointError(f"{path}: args.hdims {value!r} is not a list of dims") from None


def _nfeat(args: Mapping[str, Any], path: Path) -> float:
    """``args.nfeat``: a count >= 1, or a fraction in [-1, 0) of the tokens."""
    nfeat = args.get("nfeat", DEFAULT_NFEAT)
    valid = isinstance(nfeat, (int, float)) and not isinstance(nfeat, bool)
    if not valid or not math.isfinite(nfeat) or not (nfeat >= 1 or -1 <= nfeat < 0):
        raise CheckpointError(f"{path}: args.nfeat {nfeat!r} is not >= 1 nor in [-1, 0)")
    return nfeat


def _head_from(state: Mapping[str, Tensor], args: Mapping[str, Any], path: Path) -> RetrievalHead:
    """Build the head the state dict and ``args`` describe (not yet loaded)."""
    featweights = args.get("featweights", "l2norm")
    if featweights != "l2norm":
        raise CheckpointError(f"{path}: args.featweights {featweights!r} is not supported")
    has_prewhiten = "prewhiten.m" in state
    if "prewhiten" in args and (args["prewhiten"] is not None) != has_prewhiten:
        raise CheckpointError(f"{path}: args.prewhiten disagrees with the prewhiten.* tensors")
    linear_weights = sorted(
        (int(key.split(".")[1]), value)
        for key, value in state.items()
        if key.startswith("projector.")
        and key.endswith(".weight")
        and value.ndim == 2
        and key.split(".")[1].isdigit()
    )
    hdims = [int(weight.shape[0]) for _, weight in linear_weights]
    if "hdims" in args and _parse_hdims(args["hdims"], path) != hdims:
        raise CheckpointError(
            f"{path}: args.hdims {args['hdims']!r} does not match the projector weights {hdims}"
        )
    if has_prewhiten:
        in_dim = int(state["prewhiten.m"].shape[-1])
    elif linear_weights:
        in_dim = int(linear_weights[0][1].shape[1])
    else:
        raise CheckpointError(f"{path}: no prewhiten or projector tensors to infer the input dim")
    out_dim = hdims[-1] if hdims else in_dim
    residual = bool(args.get("residual", False))
    if residual and out_dim != in_dim:
        raise CheckpointError(f"{path}: residual projector maps {in_dim} to {out_dim} channels")
    return RetrievalHead(
        in_dim,
        hdims,
        prewhiten=has_prewhiten,
        postwhiten="postwhiten.m" in state,
        residual=residual,
        nfeat=_nfeat(args, path),
    )


def _check_state(head: RetrievalHead, state: Mapping[str, Tensor], path: Path) -> None:
    """Same keys and shapes as the head expects, else a one-line :class:`CheckpointError`."""
    expected = head.state_dict()
    missing = sorted(set(expected) - set(state))
    if missing:
        raise CheckpointError(f"{path}: retrieval checkpoint lacks tensor {missing[0]}")
    unexpected = sorted(set(state) - set(expected))
    if unexpected:
        raise CheckpointError(f"{path}: unexpected tensor {unexpected[0]} in retrieval checkpoint")
    for key, value in expected.items():
        if state[key].shape != value.shape:
            raise CheckpointError(
                f"{path}: tensor {key} has shape {tuple(state[key].shape)}, "
                f"expected {tuple(value.shape)}"
            )


def load_retrieval_head(path: str | Path, device: str | torch.device = "cpu") -> RetrievalHead:
    """Load ``..._retrieval_trainingfree.pth`` safely (``weights_only=True``).

    The architecture is read from the tensors present (``prewhiten.*``, ``projector.*``,
    ``postwhiten.*``) and cross-checked with ``args`` (``prewhiten``, ``hdims``,
    ``residual``, ``featweights``, ``nfeat``) when the checkpoint has them. ``backbone.*``
    tensors are ignored: the backbone is the MASt3R network, loaded separately.

    Returns:
        The head in eval mode on ``device``.

    Raises:
        CheckpointError: missing, truncated, malformed or unsafe file (names the file).
    """
    path = Path(path)
    state, args = _read_checkpoint(path)
    head = _head_from(state, args, path)
    _check_state(head, state, path)
    head.load_state_dict(state)
    return head.to(device).eval()
