"""MASt3R behind como3r's :class:`~como3r.prior.base.Prior` interface (MAST3R_SPEC.md §7).

``encode`` runs the encoder once per image and keeps its tokens; ``decode`` runs both
decoders and both heads on an ordered pair; ``decode_symmetric`` decodes (i, j) and (j, i) of
many pairs in one batched decoder call per image size, as SLAM's back-end needs.

Example::

    prior = load_mast3r("MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth", device="cuda")
    enc_i, enc_j = prior.encode(view_i), prior.encode(view_j)
    pred = prior.decode(enc_i, enc_j)      # pred.X_ji: view j's pointmap in camera i
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

from como3r.errors import CheckpointError, PriorError
from como3r.prior.base import Encoding, PairPrediction, Prior, View
from como3r.prior.mast3r.heads import HeadOutput
from como3r.prior.mast3r.loader import load_network
from como3r.prior.mast3r.model import MASt3RNetwork
from como3r.prior.mast3r.precision import choose_dtype
from como3r.prior.mast3r.rope import grid_positions

SUPPORTED_DTYPES = (torch.float32, torch.bfloat16, torch.float16)
#: tolerance on the [-1, 1] input range (rounding of the normalisation)
_RANGE_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class MASt3REncoding(Encoding):
    """Encoder output of one image (spec §3.5); what SLAM caches per frame.

    Attributes:
        tokens: ``(N, enc_embed_dim)`` float32 encoder tokens after ``enc_norm``, on the
            prior's device. Token ``n`` covers patch ``(n // w, n % w)``.
        pos: ``(N, 2)`` int64 patch positions ``(row, col)``.
        grid: ``(h, w)`` token grid, ``(H / 16, W / 16)``.

    ``shape`` (inherited) is the true image shape ``(H, W)``. Encodings compare by identity.
    """

    tokens: Tensor
    pos: Tensor
    grid: tuple[int, int]

    __eq__ = object.__eq__
    __hash__ = object.__hash__


class SupportsRetrievalFeatures(Protocol):
    """What :meth:`MASt3RPrior.retrieval_features` delegates to.

    :class:`como3r.prior.mast3r.retrieval.RetrievalHead` is one (spec §8.2).
    """

    def features(self, tokens: Tensor) -> tuple[Tensor, Tensor]:
        """Encoder tokens ``(N, C)`` -> local descriptors ``(k, d_r)`` and attention ``(k,)``."""


def resolve_device(device: str | torch.device) -> torch.device:
    """``"cpu"`` or ``"cuda[:k]"`` as a torch device, checked to exist.

    Raises:
        PriorError: unknown device, or CUDA requested on a machine without it.
    """
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise PriorError(f"invalid device {device!r} for MASt3R (use 'cpu' or 'cuda')") from error
    if resolved.type == "cpu":
        return resolved
    if resolved.type != "cuda":
        raise PriorError(f"unsupported device {device!r} for MASt3R (use 'cpu' or 'cuda')")
    if not torch.cuda.is_available():
        raise PriorError(
            f"device {device!r} requested but CUDA is not available "
            f"(torch {torch.__version__}, CUDA build: {torch.version.cuda or 'no'})"
        )
    if resolved.index is not None and resolved.index >= torch.cuda.device_count():
        raise PriorError(
            f"device {device!r} requested but only {torch.cuda.device_count()} GPU(s) exist"
        )
    return resolved


def _check_dtype(dtype: torch.dtype) -> torch.dtype:
    if dtype not in SUPPORTED_DTYPES:
        raise PriorError(
            f"unsupported MASt3R dtype {dtype} (use torch.float32, torch.bfloat16 "
            "or, on CUDA, torch.float16)"
        )
    return dtype


class MASt3RPrior(Prior):
    """The MASt3R network as a :class:`Prior`.

    Args:
        network: the network (its weights define the device it runs on).
        dtype: ``torch.float32``, or ``torch.bfloat16`` / ``torch.float16`` (CUDA) for encoder
            and decoders (heads are always float32).
        precision: the requested setting ``dtype`` was chosen from (``"auto"``, ...), reported
            by :meth:`describe`; empty when ``dtype`` was given directly.
        source: where the weights came from (reported by :meth:`describe`).
        model_string: the checkpoint's constructor string (reported by :meth:`describe`).

    Attributes:
        retrieval: optional :class:`SupportsRetrievalFeatures`; :meth:`retrieval_features`
            needs it.
    """

    def __init__(
        self,
        network: MASt3RNetwork,
        dtype: torch.dtype = torch.float32,
        source: str = "",
        model_string: str = "",
        precision: str = "",
    ) -> None:
        # channels-last convolution weights: the DPT's inputs already are (tokens are
        # (B, N, C)), and oneDNN/cuDNN convolutions are faster in that layout
        self.network = network.eval().requires_grad_(False).to(memory_format=torch.channels_last)
        self.network.set_compute_dtype(_check_dtype(dtype))
        self.device = next(network.parameters()).device
        self.dtype = dtype
        self.precision = precision
        self.source = source
        self.model_string = model_string
        self.descriptor_dim = network.config.desc_dim
        self.retrieval: SupportsRetrievalFeatures | None = None

    # ------------------------------------------------------------------ encode
    def encode(
        self, image_or_view: Tensor | View | Sequence[View], *, agent: int = 0, index: int = 0
    ) -> MASt3REncoding | list[MASt3REncoding]:
        """Encoder tokens of one image or a batch.

        Args:
            image_or_view: a :class:`View` (image ``(3, H, W)``); a sequence of views (encoded
                in batches of equal size); or a tensor ``(3, H, W)``, ``(1, 3, H, W)`` or
                ``(B, 3, H, W)``, float in [-1, 1], H and W multiples of 16.
            agent, index: identity recorded for tensor inputs (batch item ``b`` gets
                ``index + b``); views carry their own.

        Returns:
            One :class:`MASt3REncoding` for a view or a single image, else a list in input
            order.

        Raises:
            PriorError: malformed image (shape, size, dtype, range).
        """
        if isinstance(image_or_view, View):
            return self._encode_views([image_or_view])[0]
        if isinstance(image_or_view, Tensor):
            images = image_or_view[None] if image_or_view.dim() == 3 else image_or_view
            ids = [(agent, index + b) for b in range(images.shape[0])] if images.dim() == 4 else []
            encodings = self._encode_batch(images, ids)
            return encodings[0] if len(encodings) == 1 else encodings
        views = list(image_or_view)
        if not all(isinstance(view, View) for view in views):
            raise PriorError("MASt3R encode expects a tensor, a View or a sequence of Views")
        return self._encode_views(views)

    def _encode_views(self, views: list[View]) -> list[MASt3REncoding]:
        by_shape: dict[tuple[int, ...], list[int]] = defaultdict(list)
        for position, view in enumerate(views):
            by_shape[tuple(view.image.shape)].append(position)
        encodings: list[MASt3REncoding | None] = [None] * len(views)
        for positions in by_shape.values():
            group = [views[p] for p in positions]
            if group[0].image.dim() != 3:
                raise PriorError(f"View.image must be (3, H, W), got {tuple(group[0].image.shape)}")
            images = torch.stack([view.image for view in group])
            ids = [(view.agent, view.index) for view in group]
            for position, encoding in zip(positions, self._encode_batch(images, ids)):
                encodings[position] = encoding
        return encodings  # type: ignore[return-value]

    def _check_images(self, images: Tensor) -> None:
        if images.dim() != 4 or images.shape[1] != 3 or images.shape[0] == 0:
            raise PriorError(
                f"MASt3R images must be (B, 3, H, W) or (3, H, W), got {tuple(images.shape)}"
            )
        height, width = images.shape[-2:]
        patch = self.network.config.patch_size
        if height == 0 or width == 0 or height % patch or width % patch:
            raise PriorError(
                f"MASt3R image size {height}x{width} (HxW) is not a positive "
                f"multiple of {patch} (resize, then centre-crop to multiples of {patch})"
            )
        if not images.is_floating_point():
            raise PriorError(f"MASt3R images must be float in [-1, 1], got dtype {images.dtype}")
        low, high = torch.aminmax(images)
        if not (low >= -1 - _RANGE_TOLERANCE and high <= 1 + _RANGE_TOLERANCE):
            raise PriorError(
                f"MASt3R images must be normalised to [-1, 1] (2 * rgb / 255 - 1), got values "
                f"in [{float(low):.3g}, {float(high):.3g}]"
            )

    def _encode_batch(self, images: Tensor, ids: list[tuple[int, int]]) -> list[MASt3REncoding]:
        self._check_images(images)
        shape = (int(images.shape[-2]), int(images.shape[-1]))
        with torch.no_grad():
            tokens, grid = self.network.encode(images.to(self.device, torch.float32))
        pos = grid_positions(grid, self.device)
        return [
            MASt3REncoding(
                agent=agent, index=index, shape=shape, tokens=tokens[b], pos=pos, grid=grid
            )
            for b, (agent, index) in enumerate(ids)
        ]

    # ------------------------------------------------------------------ decode
    def _check_encoding(self, enc: Encoding) -> MASt3REncoding:
        if not isinstance(enc, MASt3REncoding):
            raise PriorError(
                "MASt3R can only decode encodings from MASt3RPrior.encode, "
                f"got {type(enc).__name__}"
            )
        if enc.tokens.shape[-1] != self.network.config.enc_embed_dim:
            raise PriorError(
                f"encoding has {enc.tokens.shape[-1]}-d tokens but this network expects "
                f"{self.network.config.enc_embed_dim}-d (encoded by another network?)"
            )
        return enc

    def _run(
        self, first: list[MASt3REncoding], second: list[MASt3REncoding]
    ) -> tuple[HeadOutput, HeadOutput]:
        """Decoders and heads on the ordered pairs ``(first[b], second[b])``, one batch."""
        tokens1 = torch.stack([enc.tokens for enc in first]).to(self.device)
        tokens2 = torch.stack([enc.tokens for enc in second]).to(self.device)
        grid1, grid2 = first[0].grid, second[0].grid
        with torch.no_grad():
            layers1, layers2 = self.network.decode(tokens1, grid1, tokens2, grid2)
            return self.network.predict(layers1, grid1, layers2, grid2)

    @staticmethod
    def _prediction(out1: HeadOutput, out2: HeadOutput, b: int) -> PairPrediction:
        return PairPrediction(
            X_ii=out1.pts3d[b],
            X_ji=out2.pts3d[b],
            C_ii=out1.conf[b],
            C_ji=out2.conf[b],
            D_ii=out1.desc[b],
            D_ji=out2.desc[b],
            Q_ii=out1.desc_conf[b],
            Q_ji=out2.desc_conf[b],
        )

    def decode(self, enc_i: Encoding, enc_j: Encoding) -> PairPrediction:
        """Predict the ordered pair (i, j); everything in camera i's frame, float32.

        Returns:
            ``X_ii, X_ji`` ``(H, W, 3)``; ``C_ii, C_ji`` ``(H, W)`` >= 1; ``D_ii, D_ji``
            ``(H, W, 24)`` unit norm; ``Q_ii, Q_ji`` ``(H, W)`` > 0 (``ji`` maps have view
            j's size).
        """
        out1, out2 = self._run([self._check_encoding(enc_i)], [self._check_encoding(enc_j)])
        return self._prediction(out1, out2, 0)

    def decode_pairs(self, pairs: Sequence[tuple[Encoding, Encoding]]) -> list[PairPrediction]:
        """Decode every ordered pair (i, j), one decoder call per pair of image sizes.

        Returns:
            ``[pred_ij, ...]`` in the order of ``pairs``.
        """
        checked = [(self._check_encoding(a), self._check_encoding(b)) for a, b in pairs]
        groups: dict[tuple[tuple[int, int], tuple[int, int]], list[int]] = defaultdict(list)
        for n, (enc_i, enc_j) in enumerate(checked):
            groups[(enc_i.grid, enc_j.grid)].append(n)
        results: list[PairPrediction | None] = [None] * len(checked)
        for members in groups.values():
            out1, out2 = self._run(
                [checked[n][0] for n in members], [checked[n][1] for n in members]
            )
            for m, n in enumerate(members):
                results[n] = self._prediction(out1, out2, m)
        return results  # type: ignore[return-value]

    def decode_symmetric(
        self, pairs: Sequence[tuple[Encoding, Encoding]]
    ) -> list[tuple[PairPrediction, PairPrediction]]:
        """Decode (i, j) and (j, i) of every pair, batched.

        The pairs and their reverses go through :meth:`decode_pairs` together: pairs whose two
        images share a size are decoded with their reverses in one decoder call per size (the
        first decoder gets ``[i_1..i_B, j_1..j_B]``, the second ``[j_1..j_B, i_1..i_B]``);
        pairs of differently sized images take one call per order.

        Returns:
            ``[(pred_ij, pred_ji), ...]`` in the order of ``pairs``.
        """
        both = self.decode_pairs([*pairs, *((b, a) for a, b in pairs)])
        return list(zip(both[: len(pairs)], both[len(pairs) :]))

    def can_reencode(self, agent: int) -> bool:
        """Yes: the tokens are a function of the image alone, which a keyframe's colours
        are (bit-identical on one device and dtype; another device or dtype re-encodes to
        within its rounding)."""
        return True

    # --------------------------------------------------------------- retrieval
    def retrieval_features(self, enc: Encoding) -> tuple[Tensor, Tensor]:
        """Local retrieval descriptors and attention of ``enc`` (spec §8.2).

        Raises:
            PriorError: no retrieval head is attached (retrieval weights not loaded).
        """
        encoding = self._check_encoding(enc)
        if self.retrieval is None:
            raise PriorError(
                "MASt3R retrieval weights were not loaded: pass retrieval_checkpoint= to "
                "load_mast3r (the *_retrieval_trainingfree.pth file) or set prior.retrieval"
            )
        return self.retrieval.features(encoding.tokens)

    def describe(self) -> dict[str, object]:
        """Checkpoint, configuration, device and precision of this prior."""
        return {
            "name": type(self).__name__,
            "checkpoint": self.source,
            "model": self.model_string,
            "device": str(self.device),
            "dtype": str(self.dtype).removeprefix("torch."),
            "precision": self.precision or str(self.dtype).removeprefix("torch."),
            "retrieval": self.retrieval is not None,
        }


def load_mast3r(
    checkpoint_path: str | Path,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | str = torch.float32,
    retrieval_checkpoint: str | Path | None = None,
) -> MASt3RPrior:
    """Load the official MASt3R checkpoint (or one in its format) as a :class:`MASt3RPrior`.

    Args:
        checkpoint_path: the ``.pth`` file (e.g.
            ``MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth``).
        device: ``"cpu"`` or ``"cuda[:k]"``.
        dtype: ``torch.float32``, ``torch.bfloat16`` or (CUDA) ``torch.float16`` for the
            encoder and decoders (heads stay float32), or a precision name ``"auto"``,
            ``"fp32"``, ``"bf16"``, ``"fp16"`` resolved by
            :func:`~como3r.prior.mast3r.precision.choose_dtype` (``auto``: bf16 where the
            hardware multiplies it natively, else fp32).
        retrieval_checkpoint: optional ``..._retrieval_trainingfree.pth``; attaches the
            retrieval head that :meth:`MASt3RPrior.retrieval_features` uses.

    Raises:
        PriorError: bad device (e.g. CUDA unavailable) or dtype; checked before reading.
        ConfigError: unknown precision name, or fp16 on CPU; checked before reading.
        CheckpointError: unreadable, unsafe or mismatching checkpoint (names the file/keys).
    """
    resolved = resolve_device(device)
    precision = dtype if isinstance(dtype, str) else ""
    compute_dtype = _check_dtype(choose_dtype(resolved, dtype) if precision else dtype)
    if compute_dtype == torch.float16 and resolved.type == "cpu":
        raise PriorError(
            "MASt3R dtype torch.float16 is not supported on CPU (use torch.float32 "
            "or torch.bfloat16)"
        )
    network, model_string = load_network(checkpoint_path)
    prior = MASt3RPrior(
        network.to(resolved),
        dtype=compute_dtype,
        source=str(checkpoint_path),
        model_string=model_string,
        precision=precision,
    )
    if retrieval_checkpoint is not None:
        # imported here: the retrieval head is optional and lives in its own module
        from como3r.prior.mast3r.retrieval import load_retrieval_head

        head = load_retrieval_head(retrieval_checkpoint, device=resolved)
        if head.in_dim != network.config.enc_embed_dim:
            raise CheckpointError(
                f"{retrieval_checkpoint}: retrieval head expects {head.in_dim}-d tokens, the "
                f"MASt3R encoder of {checkpoint_path} gives {network.config.enc_embed_dim}-d"
            )
        prior.retrieval = head
    return prior
