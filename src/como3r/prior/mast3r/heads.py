"""The ``catmlp+dpt`` head of MASt3R and its post-processing (MAST3R_SPEC.md §5).

A head turns one view's decoder layers into per-pixel outputs with two branches:

* a DPT adapter (:class:`DPTAdapter`) reading four layers and regressing xyz and confidence
  at full resolution (4 channels);
* a local-feature MLP on ``[encoder tokens | last decoder tokens]`` whose per-token output is
  pixel-shuffled to full resolution (descriptor + descriptor confidence).

The DPT's widths (96/192/384/768 -> 256, last 128) are fixed by the architecture; only its
input widths follow the encoder/decoder dimensions, so tiny configurations keep them.
Heads always run in float32.

The DPT runs in the channels-last memory format: the ``(B, h*w, C)`` tokens already are an
NHWC map (no copy to reshape them), and oneDNN convolves NHWC directly, without converting
every input and output to and from its blocked layout as it does for NCHW. For float32 CPU
inference its convolutions go through ``mkldnn._convolution_pointwise`` (the kernel torch's
inductor uses) with the following ReLU or residual addition fused (:func:`conv2d`), except
its 3x3 convolutions (:class:`Conv3x3`), which run by Winograd's F(4x4, 3x3)
(:mod:`como3r.prior.mast3r.winograd`) where both sides of the map are multiples of 4.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from como3r.prior.mast3r.blocks import Mlp
from como3r.prior.mast3r.config import MASt3RConfig
from como3r.prior.mast3r.winograd import TILE, filter_transform, winograd_conv3x3

_ONEDNN = torch.backends.mkldnn.is_available()

#: DPT widths (spec §5.1): per-hook layer widths, fused width, width before the last conv
DPT_LAYER_DIMS = (96, 192, 384, 768)
DPT_FEATURE_DIM = 256
DPT_LAST_DIM = DPT_FEATURE_DIM // 2
#: the local MLP's hidden width is this factor times its input width (spec §5.5)
LOCAL_HIDDEN_FACTOR = 4.0


def upsample2(x: Tensor) -> Tensor:
    """Bilinear x2 up-sampling with ``align_corners=True`` (spec §5.1)."""
    return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)


class Conv3x3(nn.Conv2d):
    """3x3 convolution, stride 1, zero padding 1 (keys ``weight``, ``bias``), which keeps the
    Winograd transform of its weights for :func:`conv2d` (computed on first use, again when
    the weights change)."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True) -> None:
        super().__init__(in_channels, out_channels, 3, padding=1, bias=bias)
        self._winograd: tuple[tuple[int, int], Tensor] | None = None

    def winograd_weight(self) -> Tensor:
        """``(36, C_out, C_in)``: :func:`~como3r.prior.mast3r.winograd.filter_transform`."""
        key = (self.weight.data_ptr(), self.weight._version)
        if self._winograd is None or self._winograd[0] != key:
            with torch.no_grad():
                self._winograd = key, filter_transform(self.weight)
        return self._winograd[1]


def conv2d(conv: nn.Conv2d, x: Tensor, add: Tensor | None = None, relu: bool = False) -> Tensor:
    """``conv(x)``, then ``+ add`` if given, then ReLU if ``relu``.

    Float32 CPU inference (no autograd) runs a :class:`Conv3x3` on a map whose sides are
    multiples of 4 by Winograd's F(4x4, 3x3) (relative difference about 2e-6), any other
    convolution through oneDNN, both with the addition and the ReLU applied to the output
    tiles as they are written (passes over memory saved); other devices, dtypes and autograd
    take ``F.conv2d``. oneDNN's results equal ``F.conv2d``'s to float32 rounding.

    Args:
        conv: the convolution (zero padding).
        x: ``(B, C_in, h, w)``, preferably channels-last.
        add: ``(B, C_out, h', w')``, the shape of the convolution's output.
        relu: apply ReLU last.
    """
    if (
        _ONEDNN
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and conv.weight.dtype == torch.float32
        and not torch.is_grad_enabled()
    ):
        if isinstance(conv, Conv3x3) and x.shape[2] % TILE == 0 and x.shape[3] % TILE == 0:
            return winograd_conv3x3(x, conv.winograd_weight(), conv.bias, add, relu)
        args = (
            conv.weight,
            conv.bias,
            list(conv.padding),
            list(conv.stride),
            list(conv.dilation),
            conv.groups,
        )
        unary = "relu" if relu else None
        if add is not None:
            return torch.ops.mkldnn._convolution_pointwise.binary(
                x, add, *args, "add", None, unary, [], None
            )
        return torch.ops.mkldnn._convolution_pointwise(x, *args, unary or "none", [], "")
    y = conv(x)
    if add is not None:
        y = y + add
    return F.relu(y) if relu else y


class Upsample2(nn.Module):
    """:func:`upsample2` as a module (a parameter-free slot of the DPT output head)."""

    def forward(self, x: Tensor) -> Tensor:
        """``(B, C, h, w) -> (B, C, 2h, 2w)``."""
        return upsample2(x)


class ResidualConvUnit(nn.Module):
    """``z + conv2(relu(conv1(relu(z))))`` with 3x3 convolutions; keys ``conv1.*``, ``conv2.*``."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.conv1 = Conv3x3(dim, dim)
        self.conv2 = Conv3x3(dim, dim)

    def forward(self, z: Tensor) -> Tensor:
        """``(B, C, h, w) -> (B, C, h, w)``."""
        # relu(z) is a new tensor: z itself is the residual
        return conv2d(self.conv2, conv2d(self.conv1, F.relu(z), relu=True), add=z)


class FusionBlock(nn.Module):
    """``out_conv(up2(rcu2(path + rcu1(skip))))``, or without a skip input for the deepest level.

    The deepest level (``refinenet4``) gets a single input, so its ``resConfUnit1`` would never
    run; it is not built (its checkpoint keys are known-unused, see ``loader.py``).
    """

    def __init__(self, dim: int, has_skip: bool) -> None:
        super().__init__()
        if has_skip:
            self.resConfUnit1 = ResidualConvUnit(dim)
        self.resConfUnit2 = ResidualConvUnit(dim)
        self.out_conv = nn.Conv2d(dim, dim, 1)

    def forward(self, path: Tensor, skip: Tensor | None = None) -> Tensor:
        """``(B, C, h, w)`` (+ skip of the same shape) -> ``(B, C, 2h, 2w)``.

        ``out_conv`` (1x1) runs before the up-sampling, on 4x fewer pixels: both are linear
        maps, one across channels and one across pixels, and the bilinear weights of each
        output pixel sum to 1, so the bias passes through too; the result equals
        ``out_conv(up2(.))`` to float32 rounding.
        """
        if skip is not None:
            path = path + self.resConfUnit1(skip)
        return upsample2(conv2d(self.out_conv, self.resConfUnit2(path)))


class Scratch(nn.Module):
    """Projection of the four levels to a common width and their fusion (``dpt.scratch``)."""

    def __init__(self) -> None:
        super().__init__()
        for level, in_dim in enumerate(DPT_LAYER_DIMS, start=1):
            conv = Conv3x3(in_dim, DPT_FEATURE_DIM, bias=False)
            self.add_module(f"layer{level}_rn", conv)
            self.add_module(f"refinenet{level}", FusionBlock(DPT_FEATURE_DIM, has_skip=level < 4))

    def forward(self, levels: list[Tensor]) -> Tensor:
        """Four maps at ``4x, 2x, 1x, 1/2x`` the token grid -> ``(B, 256, 8h, 8w)``."""
        l1, l2, l3, l4 = (conv2d(getattr(self, f"layer{k}_rn"), x) for k, x in enumerate(levels, 1))
        path = self.refinenet4(l4)
        # odd grids: the stride-2 level rounds up, so crop back to level 3 (spec §5.1 step 4)
        path = path[:, :, : l3.shape[2], : l3.shape[3]]
        path = self.refinenet3(path, l3)
        path = self.refinenet2(path, l2)
        return self.refinenet1(path, l1)


class DPTAdapter(nn.Module):
    """DPT regression adapter (``<head>.dpt``), output ``(B, 4, H, W)``: xyz and confidence.

    Args:
        hook_dims: widths of the four decoder layers it reads.
        out_channels: 3 + 1 (xyz and confidence).
    """

    def __init__(self, hook_dims: tuple[int, int, int, int], out_channels: int) -> None:
        super().__init__()
        d0, d1, d2, d3 = DPT_LAYER_DIMS
        self.act_postprocess = nn.ModuleList(
            [
                nn.Sequential(
                    nn.Conv2d(hook_dims[0], d0, 1), nn.ConvTranspose2d(d0, d0, 4, stride=4)
                ),
                nn.Sequential(
                    nn.Conv2d(hook_dims[1], d1, 1), nn.ConvTranspose2d(d1, d1, 2, stride=2)
                ),
                nn.Sequential(nn.Conv2d(hook_dims[2], d2, 1)),
                nn.Sequential(
                    nn.Conv2d(hook_dims[3], d3, 1), nn.Conv2d(d3, d3, 3, stride=2, padding=1)
                ),
            ]
        )
        self.scratch = Scratch()
        self.head = nn.Sequential(
            Conv3x3(DPT_FEATURE_DIM, DPT_LAST_DIM),
            Upsample2(),
            Conv3x3(DPT_LAST_DIM, DPT_LAST_DIM),
            # parameter-free slots keep the checkpoint's indices; forward fuses this ReLU
            # into the convolution before it
            nn.ReLU(inplace=True),
            nn.Conv2d(DPT_LAST_DIM, out_channels, 1),
        )

    def forward(self, layers: list[Tensor], grid: tuple[int, int]) -> Tensor:
        """Four ``(B, h*w, C_j)`` token layers -> ``(B, out_channels, 16h, 16w)``.

        The output is channels-last (its memory is ``(B, 16h, 16w, out_channels)``).
        """
        levels = []
        for post, tokens in zip(self.act_postprocess, layers):
            # (B, h*w, C) row-major tokens are the NHWC map: a channels-last view, no copy
            level = tokens.unflatten(1, grid).permute(0, 3, 1, 2)
            for layer in post:
                level = conv2d(layer, level) if isinstance(layer, nn.Conv2d) else layer(level)
            levels.append(level)
        conv1, upsample, conv2, _, conv3 = self.head
        x = upsample(conv2d(conv1, self.scratch(levels)))
        return conv2d(conv3, conv2d(conv2, x, relu=True))


@dataclass(frozen=True)
class HeadOutput:
    """Post-processed outputs of one head for a batch of views (spec §5.4), all float32.

    Attributes:
        pts3d: ``(B, H, W, 3)`` pointmap (in the first view's camera).
        conf: ``(B, H, W)`` pointmap confidence, ``>= conf_min``.
        desc: ``(B, H, W, d)`` unit-norm local descriptors.
        desc_conf: ``(B, H, W)`` descriptor confidence, ``> desc_conf_min``.
    """

    pts3d: Tensor
    conf: Tensor
    desc: Tensor
    desc_conf: Tensor


def _bounded_exp(x: Tensor, vmin: float, vmax: float) -> Tensor:
    """``vmin + min(exp(x), vmax - vmin)`` (the ``('exp', vmin, vmax)`` mode)."""
    value = x.exp()
    if vmax != float("inf"):
        value = value.clamp(max=vmax - vmin)
    return vmin + value


class CatMlpDptHead(nn.Module):
    """One ``catmlp+dpt`` head (``downstream_head1`` or ``downstream_head2``)."""

    def __init__(self, config: MASt3RConfig) -> None:
        super().__init__()
        self.config = config
        hooks = config.dpt_hooks
        hook_dims = tuple(config.enc_embed_dim if k == 0 else config.dec_embed_dim for k in hooks)
        self.dpt = DPTAdapter(hook_dims, out_channels=4)
        local_in = config.enc_embed_dim + config.dec_embed_dim
        self.head_local_features = Mlp(
            local_in,
            int(LOCAL_HIDDEN_FACTOR * local_in),
            config.local_channels * config.patch_size**2,
        )

    def forward(self, layers: dict[int, Tensor], grid: tuple[int, int]) -> HeadOutput:
        """Post-processed outputs of one view.

        Args:
            layers: decoder layer index -> ``(B, h*w, C)`` tokens; 0 is the encoder output,
                ``dec_depth`` the normalised last decoder layer. Must hold the DPT hooks.
            grid: ``(h, w)`` token grid; the output has ``(H, W) = (16h, 16w)``.
        """
        layers = {index: tokens.float() for index, tokens in layers.items()}
        dpt = self.dpt([layers[k] for k in self.config.dpt_hooks], grid)
        local_in = torch.cat([layers[0], layers[self.config.dec_depth]], dim=-1)
        local = self.head_local_features(local_in)
        # token (y, x) holds channel-major 16x16 sub-blocks: pixel_shuffle places
        # element c*256 + i*16 + j at pixel (16y + i, 16x + j) of channel c (spec §5.2)
        local = F.pixel_shuffle(local.transpose(1, 2).unflatten(-1, grid), self.config.patch_size)
        return self.postprocess(torch.cat([dpt, local], dim=1).permute(0, 2, 3, 1))

    def postprocess(self, fmap: Tensor) -> HeadOutput:
        """Raw ``(B, H, W, 4 + d [+ 1])`` map -> :class:`HeadOutput` (spec §5.4)."""
        config = self.config
        xyz = fmap[..., 0:3]
        distance = xyz.norm(dim=-1, keepdim=True)
        pts3d = xyz / distance.clamp(min=1e-8) * torch.expm1(distance)
        conf = _bounded_exp(fmap[..., 3], config.conf_min, config.conf_max)
        raw_desc = fmap[..., 4 : 4 + config.desc_dim]
        desc = raw_desc / raw_desc.norm(dim=-1, keepdim=True)
        if config.two_confs:
            desc_conf = _bounded_exp(
                fmap[..., 4 + config.desc_dim], config.desc_conf_min, config.desc_conf_max
            )
        else:
            desc_conf = conf.clone()
        return HeadOutput(pts3d=pts3d, conf=conf, desc=desc, desc_conf=desc_conf)
