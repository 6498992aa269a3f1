"""Transformer blocks of the MASt3R encoder and decoders (MAST3R_SPEC.md §3.4, §4.2).

Attention uses ``torch.nn.functional.scaled_dot_product_attention``, which computes the same
``softmax(q k^T / sqrt(D)) v`` as the explicit form (spec §9.3 item 7) with fused kernels.
Module names equal the official ones so that the checkpoint's keys load directly.

Linear layers (:class:`Linear`) run float32 inference on CPU through oneDNN's
``mkldnn._linear_pointwise`` (the kernel torch's inductor uses), which takes 1.3-2x less time
than ``F.linear``'s BLAS call at the network's shapes, with the MLP's exact GELU fused in;
results equal ``F.linear`` to float32 rounding (relative 3e-7); a block's residual addition
is applied as the projection writes its output (one pass over the tokens less per addition,
48 per encode, 72 per decoder). Under bfloat16 autocast a
:class:`Linear` given a low-precision copy of its weights (:meth:`Linear.set_low_precision`,
done by ``MASt3RNetwork.set_compute_dtype`` for the encoder and decoders) multiplies with it
instead of casting its float32 weights on every call as autocast does.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from como3r.prior.mast3r.rope import RoPE2D

#: every LayerNorm of the network uses this epsilon (spec §1.3)
LAYER_NORM_EPS = 1e-6

Grid = tuple[int, int]


def layer_norm(dim: int) -> nn.LayerNorm:
    """Affine LayerNorm with the network's epsilon."""
    return nn.LayerNorm(dim, eps=LAYER_NORM_EPS)


_ONEDNN = torch.backends.mkldnn.is_available()
#: oneDNN's bf16 inner product needs bf16 instructions (AVX512-BF16/AMX, or its AVX512
#: emulation); on an AVX2-only CPU it has no primitive and raises, so bf16 takes ``F.linear``
_ONEDNN_DTYPES = (
    (torch.float32, torch.bfloat16)
    if _ONEDNN and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    else (torch.float32,)
)


def _linear(x: Tensor, weight: Tensor, bias: Tensor, gelu: bool, residual: Tensor | None) -> Tensor:
    """``gelu?(x W^T + b) (+ residual)``, through oneDNN for CPU inference (no autograd; the
    residual added as the output is written when it has the output's dtype), else
    ``F.linear``."""
    onednn_dtype = x.dtype in _ONEDNN_DTYPES and x.dtype == weight.dtype
    if _ONEDNN and onednn_dtype and x.device.type == "cpu" and not torch.is_grad_enabled():
        if residual is not None and not gelu and residual.dtype == x.dtype:
            return torch.ops.mkldnn._linear_pointwise.binary(x, residual, weight, bias, "add")
        # attribute "gelu" with algorithm "none" is the erf form
        activation, algorithm = ("gelu", "none") if gelu else ("none", "")
        y = torch.ops.mkldnn._linear_pointwise(x, weight, bias, activation, [], algorithm)
        return y if residual is None else residual + y
    return _plain_linear(x, weight, bias, gelu, residual)


def _plain_linear(
    x: Tensor, weight: Tensor, bias: Tensor, gelu: bool, residual: Tensor | None
) -> Tensor:
    """``gelu?(F.linear(x, W, b)) (+ residual)``: any device, dtype, autocast or autograd."""
    y = F.linear(x, weight, bias)
    y = F.gelu(y) if gelu else y
    return y if residual is None else residual + y


class Linear(nn.Linear):
    """``nn.Linear`` (same parameters and keys) with the fast paths of the module docstring.

    The low-precision copies are non-persistent buffers (not in the state dict; they follow
    ``.to(device)``).
    """

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__(in_features, out_features)
        self.register_buffer("low_weight", None, persistent=False)
        self.register_buffer("low_bias", None, persistent=False)

    def set_low_precision(self, dtype: torch.dtype | None) -> None:
        """Keep ``dtype`` copies of weight and bias for autocast to ``dtype``; None drops them."""
        with torch.no_grad():
            self.low_weight = None if dtype is None else self.weight.to(dtype)
            self.low_bias = None if dtype is None else self.bias.to(dtype)

    def forward(self, x: Tensor, gelu: bool = False, residual: Tensor | None = None) -> Tensor:
        """``(..., in) -> (..., out)``, followed by the exact (erf) GELU when ``gelu``, plus
        ``residual`` ``(..., out)`` when given (``residual + y``, in their promoted dtype)."""
        weight, bias, device = self.weight, self.bias, x.device.type
        if torch.is_autocast_enabled(device):
            if self.low_weight is None or self.low_weight.dtype != torch.get_autocast_dtype(device):
                # autocast casts the weights on every call
                return _plain_linear(x, weight, bias, gelu, residual)
            weight, bias = self.low_weight, self.low_bias
            x = x.to(weight.dtype)
        return _linear(x, weight, bias, gelu, residual)


class Mlp(nn.Module):
    """``fc1 -> exact (erf) GELU -> fc2``; keys ``fc1.*``, ``fc2.*``."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int) -> None:
        super().__init__()
        self.fc1 = Linear(in_dim, hidden_dim)
        self.fc2 = Linear(hidden_dim, out_dim)

    def forward(self, x: Tensor, residual: Tensor | None = None) -> Tensor:
        """``(..., in_dim) -> (..., out_dim)`` (``+ residual`` when given)."""
        return self.fc2(self.fc1(x, gelu=True), residual=residual)


def _split_heads(x: Tensor, num_heads: int) -> Tensor:
    """``(B, N, C) -> (B, heads, N, C / heads)``; head ``h`` owns dims ``[hD, hD + D)``."""
    return x.unflatten(-1, (num_heads, -1)).transpose(1, 2)


def _merge_heads(x: Tensor) -> Tensor:
    """``(B, heads, N, D) -> (B, N, heads * D)``, head-major."""
    return x.transpose(1, 2).flatten(-2)


class SelfAttention(nn.Module):
    """Multi-head self-attention with 2-D RoPE on q and k; keys ``qkv.*``, ``proj.*``."""

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = Linear(dim, 3 * dim)
        self.proj = Linear(dim, dim)
        self.rope = rope

    def forward(self, x: Tensor, grid: Grid, residual: Tensor | None = None) -> Tensor:
        """``x`` ``(B, N, C)`` tokens on the ``(h, w)`` grid -> ``(B, N, C)`` (``+ residual``)."""
        # qkv output rows are [q | k | v], each split head-major
        q, k, v = (_split_heads(part, self.num_heads) for part in self.qkv(x).chunk(3, dim=-1))
        q = self.rope.apply(q, grid)
        k = self.rope.apply(k, grid)
        return self.proj(_merge_heads(F.scaled_dot_product_attention(q, k, v)), residual=residual)


class CrossAttention(nn.Module):
    """Multi-head cross-attention, RoPE on q (own grid) and k (other grid).

    Keys ``projq.*``, ``projk.*``, ``projv.*``, ``proj.*``.
    """

    def __init__(self, dim: int, num_heads: int, rope: RoPE2D) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.projq = Linear(dim, dim)
        self.projk = Linear(dim, dim)
        self.projv = Linear(dim, dim)
        self.proj = Linear(dim, dim)
        self.rope = rope

    def forward(
        self, x: Tensor, y: Tensor, x_grid: Grid, y_grid: Grid, residual: Tensor | None = None
    ) -> Tensor:
        """Queries from ``x`` ``(B, N, C)``, keys and values from ``y`` ``(B, M, C)``.

        Returns ``(B, N, C)`` (``+ residual`` when given).
        """
        q = self.rope.apply(_split_heads(self.projq(x), self.num_heads), x_grid)
        k = self.rope.apply(_split_heads(self.projk(y), self.num_heads), y_grid)
        v = _split_heads(self.projv(y), self.num_heads)
        return self.proj(_merge_heads(F.scaled_dot_product_attention(q, k, v)), residual=residual)


class EncoderBlock(nn.Module):
    """Pre-norm ViT block: ``x += attn(norm1(x)); x += mlp(norm2(x))`` (spec §3.4)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D) -> None:
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = SelfAttention(dim, num_heads, rope)
        self.norm2 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), dim)

    def forward(self, x: Tensor, grid: Grid) -> Tensor:
        """``(B, N, C) -> (B, N, C)``."""
        # the residual additions happen as the projections write their outputs
        x = self.attn(self.norm1(x), grid, residual=x)
        return self.mlp(self.norm2(x), residual=x)


class DecoderBlock(nn.Module):
    """Decoder block: self-attention, cross-attention to the other view, MLP (spec §4.2)."""

    def __init__(
        self, dim: int, num_heads: int, mlp_ratio: float, rope: RoPE2D, norm_other: bool
    ) -> None:
        super().__init__()
        self.norm1 = layer_norm(dim)
        self.attn = SelfAttention(dim, num_heads, rope)
        self.cross_attn = CrossAttention(dim, num_heads, rope)
        self.norm2 = layer_norm(dim)
        self.norm3 = layer_norm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), dim)
        self.norm_y = layer_norm(dim) if norm_other else nn.Identity()

    def forward(self, x: Tensor, y: Tensor, x_grid: Grid, y_grid: Grid) -> Tensor:
        """Update own tokens ``x`` ``(B, N, C)`` given the other view's ``y`` ``(B, M, C)``."""
        x = self.attn(self.norm1(x), x_grid, residual=x)
        x = self.cross_attn(self.norm2(x), self.norm_y(y), x_grid, y_grid, residual=x)
        return self.mlp(self.norm3(x), residual=x)
