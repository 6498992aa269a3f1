"""The MASt3R network: patch embedding, ViT encoder, two asymmetric decoders, two heads.

Written from MAST3R_SPEC.md §3-5; module names equal the official state-dict keys (§6) so the
released checkpoint loads strictly. The work is split as SLAM uses it (spec §7):

* :meth:`MASt3RNetwork.encode`: once per image -> encoder tokens after ``enc_norm``;
* :meth:`MASt3RNetwork.decode`: per ordered pair -> the decoder layers the heads read;
* :meth:`MASt3RNetwork.predict`: the two heads (float32) -> pointmaps, confidences, descriptors.

Precision: with ``compute_dtype=torch.bfloat16`` (or float16, CUDA) the encoder and decoders
run under that autocast (weights and the residual stream stay float32; matmuls run in the low
precision); the heads always run in float32 with autocast disabled, as upstream does.
"""

from __future__ import annotations

import contextlib
from contextlib import AbstractContextManager as ContextManager

import torch
from torch import Tensor, nn

from como3r.prior.mast3r.blocks import DecoderBlock, EncoderBlock, Linear, layer_norm
from como3r.prior.mast3r.config import MASt3RConfig
from como3r.prior.mast3r.heads import CatMlpDptHead, HeadOutput
from como3r.prior.mast3r.rope import RoPE2D

Grid = tuple[int, int]
#: decoder layer index -> (B, N, C) tokens (0 = encoder output)
DecoderLayers = dict[int, Tensor]


class PatchEmbed(nn.Module):
    """16x16 patches -> tokens (``patch_embed.proj``); no norm, no absolute position (§3.1)."""

    def __init__(self, patch_size: int, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch_size, stride=patch_size)

    def forward(self, images: Tensor) -> tuple[Tensor, Grid]:
        """``(B, 3, H, W) -> (B, h*w, C)`` row-major tokens and the ``(h, w)`` grid."""
        features = self.proj(images)
        grid = (int(features.shape[2]), int(features.shape[3]))
        return features.flatten(2).transpose(1, 2), grid


class MASt3RNetwork(nn.Module):
    """``AsymmetricMASt3R`` with the ``catmlp+dpt`` head, for any :class:`MASt3RConfig`.

    Not registered (known-unused checkpoint keys): ``mask_token`` (pre-training only) and the
    deepest DPT fusion block's first residual unit (never called).
    """

    def __init__(self, config: MASt3RConfig) -> None:
        super().__init__()
        self.config = config
        self.compute_dtype = torch.float32
        self.rope = RoPE2D(config.rope_base)
        self.patch_embed = PatchEmbed(config.patch_size, config.enc_embed_dim)
        self.enc_blocks = nn.ModuleList(
            EncoderBlock(config.enc_embed_dim, config.enc_num_heads, config.mlp_ratio, self.rope)
            for _ in range(config.enc_depth)
        )
        self.enc_norm = layer_norm(config.enc_embed_dim)
        self.decoder_embed = Linear(config.enc_embed_dim, config.dec_embed_dim)
        self.dec_blocks = self._decoder(config)
        self.dec_blocks2 = self._decoder(config)
        self.dec_norm = layer_norm(config.dec_embed_dim)
        self.downstream_head1 = CatMlpDptHead(config)
        self.downstream_head2 = CatMlpDptHead(config)
        # layers the heads read: the DPT hooks, plus 0 and the last for the local MLP
        self.kept_layers = frozenset(config.dpt_hooks) | {0, config.dec_depth}

    def _decoder(self, config: MASt3RConfig) -> nn.ModuleList:
        return nn.ModuleList(
            DecoderBlock(
                config.dec_embed_dim,
                config.dec_num_heads,
                config.mlp_ratio,
                self.rope,
                config.norm_im2_in_dec,
            )
            for _ in range(config.dec_depth)
        )

    def set_compute_dtype(self, dtype: torch.dtype) -> None:
        """Precision of encoder and decoders: ``torch.float32``, ``bfloat16`` or ``float16``."""
        if dtype not in (torch.float32, torch.bfloat16, torch.float16):
            raise ValueError(f"compute dtype must be float32, bfloat16 or float16, got {dtype}")
        if dtype != self.compute_dtype:
            # low-precision weight copies of the encoder's and decoders' linear layers
            low = None if dtype == torch.float32 else dtype
            for module in (
                *self.enc_blocks,
                self.decoder_embed,
                *self.dec_blocks,
                *self.dec_blocks2,
            ):
                for linear in module.modules():
                    if isinstance(linear, Linear):
                        linear.set_low_precision(low)
        self.compute_dtype = dtype

    def _autocast(self, device: torch.device) -> ContextManager[object]:
        if self.compute_dtype == torch.float32:
            return contextlib.nullcontext()
        return torch.autocast(device.type, dtype=self.compute_dtype)

    def encode(self, images: Tensor) -> tuple[Tensor, Grid]:
        """Encoder features of a batch of images (spec §3).

        Args:
            images: ``(B, 3, H, W)`` float32 in [-1, 1], H and W multiples of 16.

        Returns:
            tokens ``(B, h*w, enc_embed_dim)`` float32 after ``enc_norm``, and ``(h, w)``.
        """
        with self._autocast(images.device):
            tokens, grid = self.patch_embed(images)
            for block in self.enc_blocks:
                tokens = block(tokens, grid)
            tokens = self.enc_norm(tokens)
        return tokens.float(), grid

    def decode(
        self, tokens1: Tensor, grid1: Grid, tokens2: Tensor, grid2: Grid
    ) -> tuple[DecoderLayers, DecoderLayers]:
        """Run both decoders on the ordered pair (1, 2) (spec §4.3).

        Both decoders advance together: block ``i`` of each reads the other view's tokens of
        layer ``i - 1``. Only the layers the heads read are returned.

        Args:
            tokens1: ``(B, N1, enc_embed_dim)`` encoder tokens of the first views.
            grid1: their ``(h, w)`` grid.
            tokens2: ``(B, N2, enc_embed_dim)`` encoder tokens of the second views.
            grid2: their ``(h, w)`` grid.

        Returns:
            Two dicts layer index -> tokens; index 0 holds the encoder tokens (float32),
            index ``dec_depth`` the ``dec_norm``-ed last layer.
        """
        depth = self.config.dec_depth
        layers1: DecoderLayers = {0: tokens1}
        layers2: DecoderLayers = {0: tokens2}
        with self._autocast(tokens1.device):
            x1 = self.decoder_embed(tokens1)
            x2 = self.decoder_embed(tokens2)
            for index, (block1, block2) in enumerate(zip(self.dec_blocks, self.dec_blocks2), 1):
                x1, x2 = block1(x1, x2, grid1, grid2), block2(x2, x1, grid2, grid1)
                if index == depth:
                    x1, x2 = self.dec_norm(x1), self.dec_norm(x2)
                if index in self.kept_layers:
                    layers1[index], layers2[index] = x1, x2
        return layers1, layers2

    def predict(
        self, layers1: DecoderLayers, grid1: Grid, layers2: DecoderLayers, grid2: Grid
    ) -> tuple[HeadOutput, HeadOutput]:
        """Heads in float32 (autocast off): view 1 in camera 1, view 2 in camera 1 (§4.4)."""
        device = layers1[0].device
        with torch.autocast(device.type, enabled=False):
            return self.downstream_head1(layers1, grid1), self.downstream_head2(layers2, grid2)

    def forward(self, images1: Tensor, images2: Tensor) -> tuple[HeadOutput, HeadOutput]:
        """Full network on ordered image pairs ``(B, 3, H1, W1)``, ``(B, 3, H2, W2)``."""
        tokens1, grid1 = self.encode(images1)
        tokens2, grid2 = self.encode(images2)
        layers1, layers2 = self.decode(tokens1, grid1, tokens2, grid2)
        return self.predict(layers1, grid1, layers2, grid2)
