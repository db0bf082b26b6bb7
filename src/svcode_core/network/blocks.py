"""Building blocks: LayerNorm2d, SimpleGate, channel attention, the CoDe block, view fusion."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .coordgate import CoordGate, CoordGrid, tile_masks
from .lattice import RowInterpolant

__all__ = ["CoDeBlock", "LayerNorm2d", "SimpleChannelAttention", "SimpleGate", "ViewFusion",
           "pooled_mean", "spread"]


class LayerNorm2d(nn.Module):
    """Layer normalisation over the channels of each pixel, with a per-channel affine.

    Channels-last features (the U-Nets) go through torch's fused layer norm on their
    ``(B, h, w, C)`` view, 4-5x faster than tensor operations for 16-64 channels; features
    with columns fastest (the view block's few channels, where a fused row of 4-8 numbers
    is slow) through tensor operations that run along the columns (3x faster there).
    """

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if _is_channels_last(x):
            pixels = x.permute(0, 2, 3, 1)  # (B, h, w, C)
            normed = F.layer_norm(pixels, (x.shape[1],), self.weight, self.bias, self.eps)
            return normed.permute(0, 3, 1, 2)
        mean = x.mean(1, keepdim=True)
        centred = x - mean
        var = centred.pow(2).mean(1, keepdim=True)
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
        return x.mean((2, 3), keepdim=True)
    cells = F.avg_pool2d(x, cell) if cell > 1 else x
    size = max(window // cell, 1)
    return _box_mean(_box_mean(cells, 2, size), 3, size)


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


class CoDeBlock(nn.Module):
    """A NAFNet block in which every convolution is a :class:`CoordGate`.

    ``x + β·conv3(SCA(SimpleGate(conv2(conv1(LN(x))))))``, then
    ``y + γ·conv5(SimpleGate(conv4(LN(y))))``; β and γ start at zero.

    With coordinate masks the block runs on *folded* masks (:meth:`folded_masks`): the
    two halves of the conv2 and conv4 masks meet in a SimpleGate,
    ``(Ma⊙a)⊙(Mb⊙b) = (Ma⊙Mb)⊙(a⊙b)``, so each pair becomes one mask of ``c`` channels
    applied after the gate, and β and γ scale the conv3 and conv5 masks, whose products
    are then added to the residual in one ``addcmul``. On a mask lattice
    (``ModelConfig.mask_spacing``) the folded masks are what is interpolated.

    Parameters
    ----------
    channels : int
        Feature channels ``c`` (the block widens to ``2c`` inside).
    axis_features : int
        Positional-encoding features per axis.
    mlp_hidden : int or None
        Hidden units of the mask MLPs; ``None`` builds a plain NAFBlock.
    lenses : int
        1 for masks shared across lenses, 9 for lens-specific masks.
    """

    def __init__(
        self, channels: int, axis_features: int, mlp_hidden: int | None, lenses: int = 1
    ) -> None:
        super().__init__()
        c = channels

        def gate(cin: int, cout: int, kernel: int = 1, groups: int = 1) -> CoordGate:
            return CoordGate(cin, cout, kernel, groups, axis_features, mlp_hidden, lenses)

        self.norm1 = LayerNorm2d(c)
        self.conv1 = gate(c, 2 * c)
        self.conv2 = gate(2 * c, 2 * c, 3, groups=2 * c)
        self.gate = SimpleGate()
        self.sca = SimpleChannelAttention(c)
        self.conv3 = gate(c, c)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.norm2 = LayerNorm2d(c)
        self.conv4 = gate(c, 2 * c)
        self.conv5 = gate(c, c)
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.cache_name = ""  # set by the owning model: the block's key in the mask cache

    def forward(self, x: torch.Tensor, grid: CoordGrid | None) -> torch.Tensor:
        if grid is None or self.conv1.mlp is None:
            z = self.conv2(self.conv1(self.norm1(x), grid), grid)
            z = self.conv3(self.sca(self.gate(z)), grid)
            y = torch.addcmul(x, self.beta, z)
            z = self.conv5(self.gate(self.conv4(self.norm2(y), grid)), grid)
            return torch.addcmul(y, self.gamma, z)
        m1, m2, m3, m4, m5 = zip(*self._tile_masks(x, grid), strict=True)
        z = _multiply(self.conv1.conv(self.norm1(x)), m1)
        z = _multiply(self.gate(self.conv2.conv(z)), m2)
        y = _add_product(x, m3, self.conv3.conv(self.sca(z)))
        z = _multiply(self.gate(self.conv4.conv(self.norm2(y))), m4)
        return _add_product(y, m5, self.conv5.conv(z))

    def folded_masks(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """The block's masks folded as in the class docstring.

        Returns
        -------
        tuple of torch.Tensor
            conv1 ``(B, lenses, 2c, h, w)``, then the conv2 pair, β·conv3, the conv4
            pair and γ·conv5 ``(B, lenses, c, h, w)``, in the MLPs' dtype.
        """
        c = self.beta.shape[1]
        m2 = self.conv2.masks(enc_row, enc_col)
        m4 = self.conv4.masks(enc_row, enc_col)
        return (
            self.conv1.masks(enc_row, enc_col),
            m2[:, :, :c] * m2[:, :, c:],
            self.conv3.masks(enc_row, enc_col) * self.beta.view(c, 1, 1),
            m4[:, :, :c] * m4[:, :, c:],
            self.conv5.masks(enc_row, enc_col) * self.gamma.view(c, 1, 1),
        )

    def _tile_masks(self, x: torch.Tensor, grid: CoordGrid) -> list[tuple[torch.Tensor, ...]]:
        """Per tile, the folded masks ``(lenses, C, h, w)`` in the compute dtype: from the
        cache, or computed (at the pixels, or at the lattice nodes and interpolated; large
        lattice masks used once as :class:`~.lattice.RowInterpolant`, finished by
        :func:`_multiply` and :func:`_add_product` band by band)."""
        c, mlp = self.beta.shape[1], self.conv1.mlp
        dtype = _mask_dtype(x.device, mlp.w_out.dtype)
        channels_last = _is_channels_last(x)
        if grid.cached and grid.lattice is not None:
            return grid.cached_lattice_masks(self.cache_name, self.folded_masks, dtype,
                                             channels_last)  # fmt: skip
        if grid.cached:
            shapes = [(mlp.lenses, 2 * c)] + [(mlp.lenses, c)] * 4
            pixel_bytes = mlp.lenses * (mlp.w_out.shape[-1] + 8 * c) * mlp.w_out.element_size()
            return tile_masks(grid, self.cache_name, self.folded_masks, shapes, pixel_bytes,
                              dtype)  # fmt: skip
        tiles = grid.tile_masks(self.folded_masks(grid.enc_row, grid.enc_col), channels_last)
        return [tuple(m.to(dtype) for m in masks) for masks in tiles]


def _is_channels_last(x: torch.Tensor) -> bool:
    """Whether ``x``'s channels vary fastest in memory (and its columns do not)."""
    return x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


def _mask_dtype(device: torch.device, default: torch.dtype) -> torch.dtype:
    """The dtype masks are stored and applied in: autocast's, else the parameters'."""
    if torch.is_autocast_enabled(device.type):
        return torch.get_autocast_dtype(device.type)
    return default


def _tiles(t: torch.Tensor, batch: int) -> torch.Tensor:
    """``(B·V, C, h, w)`` viewed as ``(B, V, C, h, w)``."""
    return t.view(batch, -1, *t.shape[1:])


def _in_memory_order(t: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """``(B, V, C, h, w)`` with the channels moved last when they are last in memory.

    Products that need gradients run on this view: their masks' gradients are sums over
    the tiles, which torch takes 2-3x faster along a dense last axis than along the
    channels-last layout of a 5-d tensor (the same values, measured bit for bit).
    """
    return t.permute(0, 1, 3, 4, 2) if channels_last else t


def _from_memory_order(t: torch.Tensor, channels_last: bool, like: torch.Tensor) -> torch.Tensor:
    """Undo :func:`_in_memory_order` and view as ``like`` ``(B·V, C, h, w)``."""
    if channels_last:
        t = t.permute(0, 1, 4, 2, 3)
    return t.reshape(like.shape)


def _multiply(y: torch.Tensor, masks: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``y`` multiplied by the mask of each tile: in place (``y`` is a temporary) without
    gradient, out of place (the product needs ``y``) with it."""
    if torch.is_grad_enabled():
        last = _is_channels_last(y)
        product = (_in_memory_order(_tiles(y, len(masks)), last)
                   * _in_memory_order(_batched(masks), last))  # fmt: skip
        return _from_memory_order(product, last, y)
    for tile, mask in zip(_tiles(y, len(masks)), masks, strict=True):
        if isinstance(mask, RowInterpolant):
            mask.multiply_(tile)
        else:
            tile.mul_(mask)
    return y


def _batched(masks: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """The tiles' masks as one ``(B or 1, lenses, C, h, w)`` tensor: tiles that share one
    mask (training runs at one origin) broadcast it instead of copying it."""
    if all(m is masks[0] for m in masks):
        return masks[0].unsqueeze(0)
    return torch.stack(masks)


def _add_product(
    x: torch.Tensor, masks: tuple[torch.Tensor, ...], z: torch.Tensor
) -> torch.Tensor:
    """``x + mask ⊙ z`` tile by tile, in one pass per tile."""
    batch = len(masks)
    if torch.is_grad_enabled():
        last = _is_channels_last(x)
        x5, z5 = (_in_memory_order(_tiles(t, batch), last) for t in (x, z))
        out = torch.addcmul(x5, _in_memory_order(_batched(masks), last), z5)
        return _from_memory_order(out, last, x)
    dtype = torch.promote_types(torch.promote_types(x.dtype, z.dtype), masks[0].dtype)
    out = torch.empty_like(x, dtype=dtype)
    for o, xb, m, zb in zip(_tiles(out, batch), _tiles(x, batch), masks, _tiles(z, batch),
                            strict=True):
        if isinstance(m, RowInterpolant):
            m.add_product(xb, zb, o)
        else:
            torch.addcmul(xb, m, zb, out=o)
    return out


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
