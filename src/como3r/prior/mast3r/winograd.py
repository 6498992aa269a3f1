"""Winograd F(4x4, 3x3) convolution for the DPT's 3x3 convolutions on CPU, float32.

The DPT of MASt3R's heads spends about 85 % of its time in 3x3 stride-1 convolutions of 96-
768 input channels at 1/2x to 16x the token grid (the last one, 128 -> 128 channels on every
pixel of the image, alone 29 GMAC per view at 512x384). oneDNN's direct convolution already
runs them near the core's peak FMA rate, so only fewer multiplications make them faster.
Winograd's minimal filtering (Lavin & Gray, "Fast Algorithms for Convolutional Neural
Networks", CVPR 2016, F(4x4, 3x3), their eq. 9) computes each 4x4 output tile from a 6x6
input tile as ``Y = A^T [(G g G^T) . (B^T d B)] A``: the channel contraction becomes 36
independent GEMMs of ``tiles x C_in`` by ``C_in x C_out`` (``torch.bmm``), 36
multiplications per 16 outputs and input channel instead of 144 (4x fewer). The GEMMs of
these shapes run at about 30 GMAC/s on one core against the direct convolution's 48, and
the transforms (compiled loops, one pass each) add the rest.

Precision: the transforms' coefficients reach 8 (output) and 1/24 (filter), so the result
differs from a direct float32 convolution by about 2e-6 relative (1e-6 at 256 channels),
against 5e-7 for oneDNN's direct convolution, both measured against float64 on the DPT's
shapes. F(2x2, 3x3) (coefficients 1 and 1/2) was measured too: 2.25x fewer multiplications
do not pay for its 4x larger transformed input (0.8-1.2x the direct convolution).

Work is done in bands of tile rows whose transformed input and GEMM output stay in the
cache (:data:`BAND_ELEMENTS`); bias, residual addition and ReLU are applied on the output
tiles as they are written.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from como3r.jit import compiled

#: tiles x channels of one band per tile position (36 of them: 9.4 MB of float32); 16k-128k
#: measured within noise of each other on the DPT's shapes, 8k slower
BAND_ELEMENTS = 65_536

#: G of F(4x4, 3x3), the filter transform ``U = G g G^T`` (Lavin & Gray, eq. 9)
G = np.array(
    [
        [1 / 4, 0, 0],
        [-1 / 6, -1 / 6, -1 / 6],
        [-1 / 6, 1 / 6, -1 / 6],
        [1 / 24, 1 / 12, 1 / 6],
        [1 / 24, -1 / 12, 1 / 6],
        [0, 0, 1],
    ],
    np.float64,
)
#: output tile side m and input tile side m + 2
TILE, SIZE = 4, 6


def filter_transform(weight: Tensor) -> Tensor:
    """``(C_out, C_in, 3, 3)`` kernel -> ``(36, C_out, C_in)``: ``G g G^T`` per channel pair,
    index ``6 i + j`` the tile position ``(i, j)``; computed in float64, rounded once."""
    G64 = torch.from_numpy(G).to(weight.device)
    U = torch.einsum("ik,ockl,jl->ijoc", G64, weight.double(), G64)
    return U.reshape(SIZE * SIZE, weight.shape[0], weight.shape[1]).to(weight.dtype).contiguous()


@njit(cache=True, inline="always")
def _bt(d0: float, d1: float, d2: float, d3: float, d4: float, d5: float) -> tuple:
    """``B^T d`` of a 6-vector, ``B^T = [[4, 0, -5, 0, 1, 0], [0, -4, -4, 1, 1, 0],
    [0, 4, -4, -1, 1, 0], [0, -2, -1, 2, 1, 0], [0, 2, -1, -2, 1, 0], [0, 4, 0, -5, 0, 1]]``."""
    a, b = d4 - 4 * d2, d3 - 4 * d1
    c, e = d4 - d2, 2 * (d3 - d1)
    return 4 * d0 - 5 * d2 + d4, a + b, a - b, c + e, c - e, 4 * d1 - 5 * d3 + d5


@njit(cache=True, inline="always")
def _at(m0: float, m1: float, m2: float, m3: float, m4: float, m5: float) -> tuple:
    """``A^T m`` of a 6-vector, ``A^T = [[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 0],
    [0, 1, 1, 4, 4, 0], [0, 1, -1, 8, -8, 1]]``."""
    s12, d12, s34, d34 = m1 + m2, m1 - m2, m3 + m4, m3 - m4
    return m0 + s12 + s34, d12 + 2 * d34, s12 + 4 * s34, d12 + 8 * d34 + m5


def _input_tiles(padded: np.ndarray, t0: int, out: np.ndarray) -> None:  # pragma: no cover
    """``V = B^T d B`` of the 6x6 tiles of tile rows ``[t0, t0 + n)`` (compiled).

    ``padded`` is the zero-padded ``(H + 2, W + 2, C)`` input, ``out`` ``(36, n, W / 4, C)``
    with tile position ``6 i + j`` first.
    """
    channels = padded.shape[2]
    for t in prange(out.shape[1]):
        r = TILE * (t0 + t)
        col = np.empty((SIZE, SIZE, channels), np.float32)  # B^T d: [row i, column j, channel]
        for s in range(out.shape[2]):
            q = TILE * s
            for j in range(SIZE):
                for c in range(channels):
                    b0, b1, b2, b3, b4, b5 = _bt(
                        padded[r, q + j, c],
                        padded[r + 1, q + j, c],
                        padded[r + 2, q + j, c],
                        padded[r + 3, q + j, c],
                        padded[r + 4, q + j, c],
                        padded[r + 5, q + j, c],
                    )
                    col[0, j, c], col[1, j, c], col[2, j, c] = b0, b1, b2
                    col[3, j, c], col[4, j, c], col[5, j, c] = b3, b4, b5
            for i in range(SIZE):
                k = SIZE * i
                for c in range(channels):
                    v0, v1, v2, v3, v4, v5 = _bt(
                        col[i, 0, c],
                        col[i, 1, c],
                        col[i, 2, c],
                        col[i, 3, c],
                        col[i, 4, c],
                        col[i, 5, c],
                    )
                    out[k, t, s, c], out[k + 1, t, s, c], out[k + 2, t, s, c] = v0, v1, v2
                    out[k + 3, t, s, c], out[k + 4, t, s, c], out[k + 5, t, s, c] = v3, v4, v5


def _output_tiles(
    m: np.ndarray, bias: np.ndarray, add: np.ndarray, relu: bool, t0: int, out: np.ndarray
) -> None:  # pragma: no cover
    """``Y = A^T M A`` of tile rows ``[t0, t0 + n)`` into ``out`` ``(H, W, C_out)``, then
    ``+ bias``, ``+ add`` (an ``(H, W, C_out)`` array, or ``(0, 0, 0)`` for none), ReLU.

    ``m`` is the GEMM output ``(36, n, W / 4, C_out)``.
    """
    channels = m.shape[3]
    has_add = add.shape[0] > 0
    for t in prange(m.shape[1]):
        r = TILE * (t0 + t)
        row = np.empty((TILE, SIZE, channels), np.float32)  # A^T M: [row a, column j, channel]
        for s in range(m.shape[2]):
            q = TILE * s
            for j in range(SIZE):
                for o in range(channels):
                    y0, y1, y2, y3 = _at(
                        m[j, t, s, o],
                        m[6 + j, t, s, o],
                        m[12 + j, t, s, o],
                        m[18 + j, t, s, o],
                        m[24 + j, t, s, o],
                        m[30 + j, t, s, o],
                    )
                    row[0, j, o], row[1, j, o], row[2, j, o], row[3, j, o] = y0, y1, y2, y3
            for a in range(TILE):
                for o in range(channels):
                    y0, y1, y2, y3 = _at(
                        row[a, 0, o],
                        row[a, 1, o],
                        row[a, 2, o],
                        row[a, 3, o],
                        row[a, 4, o],
                        row[a, 5, o],
                    )
                    y0, y1, y2, y3 = y0 + bias[o], y1 + bias[o], y2 + bias[o], y3 + bias[o]
                    if has_add:
                        y0 += add[r + a, q, o]
                        y1 += add[r + a, q + 1, o]
                        y2 += add[r + a, q + 2, o]
                        y3 += add[r + a, q + 3, o]
                    if relu:
                        y0, y1, y2, y3 = max(y0, 0.0), max(y1, 0.0), max(y2, 0.0), max(y3, 0.0)
                    out[r + a, q, o], out[r + a, q + 1, o] = y0, y1
                    out[r + a, q + 2, o], out[r + a, q + 3, o] = y2, y3


def winograd_conv3x3(
    x: Tensor, U: Tensor, bias: Tensor | None, add: Tensor | None = None, relu: bool = False
) -> Tensor:
    """3x3 convolution, stride 1, zero padding 1, by Winograd F(4x4, 3x3), float32 on CPU.

    Args:
        x: ``(B, C_in, H, W)`` float32, H and W multiples of 4, preferably channels-last.
        U: ``(36, C_out, C_in)`` from :func:`filter_transform`.
        bias: ``(C_out,)`` or None.
        add: ``(B, C_out, H, W)`` added after the bias, or None.
        relu: apply ReLU last.

    Returns:
        ``(B, C_out, H, W)``, channels-last.
    """
    batch, channels, height, width = x.shape
    if height % TILE or width % TILE:
        raise ValueError(f"Winograd F(4x4, 3x3) needs H and W multiples of 4, got {height}x{width}")
    out_channels = U.shape[1]
    width_tiles = width // TILE
    # the input with a zero border, written once: the interior copied, the border zeroed
    padded = x.new_empty(batch, height + 2, width + 2, channels)
    padded[:, 1:-1, 1:-1] = x.permute(0, 2, 3, 1)
    for border in (padded[:, 0], padded[:, -1], padded[:, :, 0], padded[:, :, -1]):
        border.zero_()
    out = x.new_empty(batch, height, width, out_channels)
    add_nhwc = None if add is None else add.permute(0, 2, 3, 1).contiguous()
    bias_np = (bias if bias is not None else x.new_zeros(out_channels)).detach().numpy()
    band = max(1, BAND_ELEMENTS // (width_tiles * max(channels, out_channels)))
    V = x.new_empty(SIZE * SIZE, band, width_tiles, channels)
    M = x.new_empty(SIZE * SIZE, band * width_tiles, out_channels)
    inputs, outputs = compiled(_input_tiles), compiled(_output_tiles)
    none = np.zeros((0, 0, 0), np.float32)
    for b in range(batch):
        padded_np, out_np = padded[b].numpy(), out[b].numpy()
        add_np = none if add_nhwc is None else add_nhwc[b].numpy()
        for t0 in range(0, height // TILE, band):
            n = min(band, height // TILE - t0)
            v = V[:, :n]
            inputs(padded_np, t0, v.numpy())
            m = M[:, : n * width_tiles]
            torch.bmm(v.reshape(SIZE * SIZE, -1, channels), U.transpose(1, 2), out=m)
            outputs(
                m.view(-1, n, width_tiles, out_channels).numpy(), bias_np, add_np, relu, t0, out_np
            )
    return out.permute(0, 3, 1, 2)
