"""NAFNet's parts around the gated convolutions: LayerNorm2d, SimpleGate, channel attention,
and the view fusion of the SV-CoDe stages (:mod:`.models` assembles them)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "LayerNorm2d",
    "SimpleChannelAttention",
    "SimpleGate",
    "ViewFusion",
    "channel_mean",
    "is_channels_last",
    "pooled_mean",
    "spatial_mean",
    "spread",
]


class LayerNorm2d(nn.Module):
    """Layer normalisation over the channels of each pixel, with a per-channel affine.

    Channels-last features (the U-Nets) go through torch's fused layer norm on their
    ``(B, h, w, C)`` view, 4-5x faster than tensor operations for 16-64 channels; features
    with columns fastest (the view block's few channels, where a fused row of 4-8 numbers
    is slow) through tensor operations that run along the columns (3x faster there), the
    channel means as matrix products (:func:`channel_mean`).
    """

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if is_channels_last(x):
            pixels = x.permute(0, 2, 3, 1)  # (B, h, w, C)
            normed = F.layer_norm(pixels, (x.shape[1],), self.weight, self.bias, self.eps)
            return normed.permute(0, 3, 1, 2)
        centred = x - channel_mean(x)
        var = channel_mean(centred.square())
        scale = self.weight.view(1, -1, 1, 1) * torch.rsqrt(var + self.eps)
        return torch.addcmul(self.bias.view(1, -1, 1, 1), centred, scale)


class SimpleGate(nn.Module):
    """Split the channels in two halves and multiply them."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        first, second = x.chunk(2, dim=1)
        return first * second


class SimpleChannelAttention(nn.Module):
    """NAFNet's simplified channel attention: ``x · conv1×1(mean_space(x))``.

    The mean is over the whole tile, or over a window around each pixel when
    :attr:`window` is set (see :func:`pooled_mean`; set by the owning model from
    ``ModelConfig.pool_window``).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 1)
        self.window, self.cell = 0, 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weights = self.conv(pooled_mean(x, self.window, self.cell))
        return x * spread(weights, x)


def pooled_mean(x: torch.Tensor, window: int = 0, cell: int = 1) -> torch.Tensor:
    """The spatial mean that channel attention sees: over the whole map, or per pixel over
    a ``window``-pixel square centred on it, kept inside the map.

    A network trained on patches of ``P`` pixels has seen means over ``P × P`` squares
    only; on a larger tile, ``window = P`` (at this level's scale) gives every pixel such a
    mean instead of the whole tile's, so the output no longer depends on the tile's extent
    beyond ``P`` (near the map's edge the square is shifted inwards, as a training patch's
    edge pixels see their patch). The local means are taken on a grid of ``cell × cell``
    cells, to be interpolated back to the pixels by :func:`spread`: they vary slowly, and
    per pixel they would cost more than the block they serve. A cell's square is centred
    on the cell's centre, where :func:`spread` places its value (for an even number of
    cells per side, the mean of the two squares half a cell either side), so a linear
    ramp is its own local mean away from the edges.

    Parameters
    ----------
    x : torch.Tensor
        ``(B, C, H, W)``, ``H`` and ``W`` multiples of ``cell``.
    window : int
        Side of the square in pixels; 0, or a window covering the map, gives the mean
        over the whole map.
    cell : int
        Side of the grid cells in pixels.

    Returns
    -------
    torch.Tensor
        ``(B, C, 1, 1)`` for the whole map, else ``(B, C, H / cell, W / cell)``.

    Examples
    --------
    >>> x = torch.arange(8.0).view(1, 1, 1, 8).expand(1, 1, 4, 8)
    >>> pooled_mean(x).flatten().tolist()
    [3.5]
    >>> pooled_mean(x, window=4, cell=2)[0, 0, 0].tolist()  # squares of 4 columns
    [1.5, 2.5, 4.5, 5.5]
    """
    h, w = x.shape[-2:]
    if window <= 0 or (window >= h and window >= w):
        return spatial_mean(x)
    cells = F.avg_pool2d(x, cell) if cell > 1 else x
    size = max(window // cell, 1)
    return _box_mean(_box_mean(cells, 2, size), 3, size)


def channel_mean(x: torch.Tensor) -> torch.Tensor:
    """``x.mean(1, keepdim=True)`` of channels-first ``(B, C, h, w)``. Without gradients,
    one matrix product with a row of ``1/C`` in ``x``'s dtype (autocast or not),
    accumulated in float32: torch's reduction first copies bf16 features to float32 and
    is 2-5x slower (1.5-4x in float32). ``1/C`` is exact for 4 and 8 channels (the view
    block's). With gradients, torch's reduction, whose backward pass is the cheaper one.

    >>> x = torch.rand(2, 4, 3, 5)
    >>> with torch.no_grad():
    ...     torch.allclose(channel_mean(x), x.mean(1, keepdim=True), atol=1e-7)
    True
    """
    if torch.is_grad_enabled():
        return x.mean(1, keepdim=True)
    b, c, h, w = x.shape
    row = x.new_full((1, c), 1.0 / c)
    with torch.autocast(x.device.type, enabled=False):
        return torch.matmul(row, x.reshape(b, c, h * w)).view(b, 1, h, w)


def spatial_mean(x: torch.Tensor) -> torch.Tensor:
    """``x.mean((2, 3), keepdim=True)`` ``(B, C, 1, 1)`` in either memory layout, as
    :func:`channel_mean` computes its mean: without gradients the sum is a matrix product
    with a column of ones, divided in float32 (in bf16 two roundings, where torch's mean
    has one).

    >>> x = torch.rand(2, 3, 4, 5)
    >>> with torch.no_grad():
    ...     torch.allclose(spatial_mean(x), x.mean((2, 3), keepdim=True), atol=1e-7)
    True
    """
    if torch.is_grad_enabled():
        return x.mean((2, 3), keepdim=True)
    b, c, h, w = x.shape
    ones = x.new_ones(h * w, 1)
    with torch.autocast(x.device.type, enabled=False):
        if is_channels_last(x):  # (B, h·w, C) rows of pixels
            sums = torch.matmul(ones.T, x.permute(0, 2, 3, 1).reshape(b, h * w, c))
        else:
            sums = torch.matmul(x.reshape(b, c, h * w), ones)
    return (sums.float() / (h * w)).to(x.dtype).view(b, c, 1, 1)


def _box_mean(x: torch.Tensor, dim: int, size: int) -> torch.Tensor:
    """Mean over ``size`` consecutive entries along ``dim`` centred on each entry, the run
    shifted inside the axis at its ends (the whole axis if it is shorter). An even run
    has no middle entry: the mean of the two runs either side of the centre is taken."""
    n = x.shape[dim]
    if size >= n:
        return x.mean(dim, keepdim=True)
    sums = torch.cumsum(x, dim)
    sums = torch.cat([torch.zeros_like(sums.narrow(dim, 0, 1)), sums], dim)
    runs = sums.narrow(dim, size, n - size + 1) - sums.narrow(dim, 0, n - size + 1)
    first = torch.arange(n, device=x.device) - size // 2
    mean = runs.index_select(dim, first.clamp(0, n - size)) / size
    if size % 2:
        return mean
    later = runs.index_select(dim, (first + 1).clamp(0, n - size)) / size
    return (mean + later) / 2


def spread(weights: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Weights from :func:`pooled_mean`'s grid, bilinearly at ``x``'s pixels (a single
    value per map broadcasts as it is)."""
    if weights.shape[-2:] in ((1, 1), x.shape[-2:]):
        return weights
    return F.interpolate(weights, size=x.shape[-2:], mode="bilinear", align_corners=False)


def is_channels_last(x: torch.Tensor) -> bool:
    """Whether ``x``'s channels vary fastest in memory (and its columns do not)."""
    return x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


class ViewFusion(nn.Module):
    """Channel attention with view-wise pooling, then a 1×1 merge of the views.

    Every (view, channel) feature map is average-pooled over space (the tile, or a window
    around each pixel: :func:`pooled_mean`); a 1×1 layer and a
    sigmoid turn the pooled ``V·c`` vector into one weight per view and channel
    (squeeze-and-excitation), and a 1×1 convolution merges the weighted views into
    ``out_channels``.
    """

    def __init__(self, views: int, channels: int, out_channels: int) -> None:
        super().__init__()
        self.attention = nn.Conv2d(views * channels, views * channels, 1)
        self.merge = nn.Conv2d(views * channels, out_channels, 1)
        self.window, self.cell = 0, 1  # the pooling, as in SimpleChannelAttention

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x``: ``(B, V·c, h, w)`` (views major) → ``(B, out_channels, h, w)``."""
        weights = torch.sigmoid(self.attention(pooled_mean(x, self.window, self.cell)))
        return self.merge(x * spread(weights, x))
