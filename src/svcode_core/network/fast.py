"""The fast route: CoDe blocks run on folded masks, cached or interpolated from a lattice.

:class:`FastMasks` is the mask provider a model uses by default; it gives each block a
:class:`FoldedMasks`, which runs the block's formula (:class:`~.models.CoDeBlock`)
rearranged as follows. The results equal those of :class:`~.masks.PlainMasks` to float
rounding (``tests/test_network_formula.py``).

Folding
    The two halves of the conv2 and conv4 masks meet in a SimpleGate,
    ``(Ma⊙a)⊙(Mb⊙b) = (Ma⊙Mb)⊙(a⊙b)``, so each pair becomes one mask of ``c`` channels
    applied after the gate; β and γ scale the conv3 and conv5 masks, whose products are
    then added to the residual in one ``addcmul`` (:func:`fold`): the pairs' masks are half
    as wide, and each residual branch takes one pass over the features fewer. On a mask
    lattice the folded masks are what is interpolated.
Where the masks come from
    From the mask cache when one is switched on and no gradient is needed (a crop of the
    block's whole-sub-view field, or a tile's interpolated lattice masks:
    :mod:`.cache`); else computed for the call, tiles at one origin sharing them. Lattice
    masks used once are not written out when large: they come as
    :class:`~.lattice.RowInterpolant` and are finished band by band where they are applied.
How they are applied
    Without gradient in place, tile by tile, in the features' memory layout. With
    gradient out of place, on a view with the channels last in index order (for
    channels-last features): a mask shared by the tiles of a batch gets as gradient a sum
    over the tiles, which torch takes 2-3x faster along a dense last axis than along the
    channels-last layout of a 5-d tensor (the same values, measured bit for bit).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial

import torch
from torch import nn

from .blocks import is_channels_last
from .cache import cached_lattice_masks, from_field
from .lattice import RowInterpolant
from .masks import CoordGrid

__all__ = ["FastMasks", "FoldedMasks", "fold", "pointwise"]

Masks = tuple[torch.Tensor, ...]


class FastMasks:
    """The default mask provider: each block gets :class:`FoldedMasks`.

    Parameters
    ----------
    grids : sequence of CoordGrid
        One per U-Net level (:func:`~.masks.coordinate_grids`), with the model's cache
        when it is on.
    names : mapping
        Each CoDe block's key in the mask cache.
    """

    def __init__(self, grids: Sequence[CoordGrid], names: Mapping[nn.Module, str]) -> None:
        self.grids, self.names = list(grids), names

    def __call__(self, block: nn.Module, level: int) -> FoldedMasks:
        return FoldedMasks(self.grids[level], self.names[block])


def fold(block: nn.Module, enc_row: torch.Tensor, enc_col: torch.Tensor) -> Masks:
    """A CoDe block's masks folded as in the module docstring, at a grid of encodings.

    Returns
    -------
    tuple of torch.Tensor
        conv1 ``(B, lenses, 2c, h, w)``, then the conv2 pair, β·conv3, the conv4 pair and
        γ·conv5 ``(B, lenses, c, h, w)``, in the MLPs' dtype.
    """
    c = block.beta.shape[1]
    m2 = block.conv2.masks(enc_row, enc_col)
    m4 = block.conv4.masks(enc_row, enc_col)
    return (
        block.conv1.masks(enc_row, enc_col),
        m2[:, :, :c] * m2[:, :, c:],
        block.conv3.masks(enc_row, enc_col) * block.beta.view(c, 1, 1),
        m4[:, :, :c] * m4[:, :, c:],
        block.conv5.masks(enc_row, enc_col) * block.gamma.view(c, 1, 1),
    )


@dataclass(frozen=True)
class FoldedMasks:
    """One block's folded masks for the tiles of a call, computed when the block runs.

    Attributes
    ----------
    grid : CoordGrid
        The tiles at the block's level.
    name : str
        The block's key in the mask cache.
    """

    grid: CoordGrid
    name: str

    def run(self, block: nn.Module, x: torch.Tensor) -> torch.Tensor:
        """``block(x)`` on folded masks; ``x`` is ``(B·V, c, h, w)``."""
        m1, m2, m3, m4, m5 = zip(*self.tile_masks(block, x), strict=True)
        z = _multiply(_conv(block.conv1.conv, block.norm1(x)), m1)
        z = _multiply(block.gate(_conv(block.conv2.conv, z)), m2)
        y = _add_product(x, m3, _conv(block.conv3.conv, block.sca(z)))
        z = _multiply(block.gate(_conv(block.conv4.conv, block.norm2(y))), m4)
        return _add_product(y, m5, _conv(block.conv5.conv, z))

    def tile_masks(self, block: nn.Module, x: torch.Tensor) -> list[Masks]:
        """Per tile, the folded masks ``(lenses, C, h, w)`` in the compute dtype, in the
        layout of ``x``: from the cache, or computed (at the pixels, or at the lattice nodes
        and interpolated)."""
        grid, mlp = self.grid, block.conv1.mlp
        c, compute = block.beta.shape[1], partial(fold, block)
        dtype = _mask_dtype(x.device, x.dtype)
        channels_last = is_channels_last(x)
        if grid.cached and grid.lattice is not None:
            return cached_lattice_masks(grid, self.name, compute, dtype, channels_last)
        if grid.cached:
            shapes = [(mlp.lenses, 2 * c)] + [(mlp.lenses, c)] * 4
            pixel_bytes = mlp.lenses * (mlp.w_out.shape[-1] + 8 * c) * mlp.w_out.element_size()
            return from_field(grid, self.name, compute, shapes, pixel_bytes, dtype)
        return grid.tile_masks(compute(grid.enc_row, grid.enc_col), channels_last, dtype)


def _conv(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """``conv(x)`` in the layout of ``x``. Features with the columns fastest (the view
    block's few channels) go through a batched matrix product when the kernel is 1×1
    (as fast as oneDNN's channels-first 1×1 kernel in float32, 6-12x faster in bf16, and
    the layout copies around its channels-last one cost more than the convolution),
    else are convolved channels last, in autocast's dtype when it is on: there oneDNN's
    depthwise kernels run 4x (fp32) to 6x (bf16) faster, more than the two copies cost."""
    if is_channels_last(x):
        return conv(x)
    if conv.kernel_size == (1, 1) and conv.groups == 1:
        return pointwise(conv, x)
    dtype = x.dtype
    if torch.is_autocast_enabled(x.device.type):
        dtype = torch.get_autocast_dtype(x.device.type)
    return conv(x.to(dtype, memory_format=torch.channels_last)).contiguous()


def pointwise(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """A 1×1 convolution of channels-first ``x`` as one batched matrix product.

    >>> conv = nn.Conv2d(4, 8, 1)
    >>> x = torch.rand(3, 4, 5, 6)
    >>> torch.allclose(pointwise(conv, x), conv(x), atol=1e-6)
    True
    """
    n, c, h, w = x.shape
    out = conv.out_channels
    bias = conv.bias if conv.bias is not None else x.new_zeros(out)
    y = torch.baddbmm(bias.view(1, out, 1).expand(n, out, 1),
                      conv.weight.view(1, out, c).expand(n, out, c), x.reshape(n, c, h * w))
    return y.view(n, out, h, w)


def _mask_dtype(device: torch.device, default: torch.dtype) -> torch.dtype:
    """The dtype masks are stored and applied in: autocast's, else ``default`` (the
    features')."""
    if torch.is_autocast_enabled(device.type):
        return torch.get_autocast_dtype(device.type)
    return default


def _tiles(t: torch.Tensor, batch: int) -> torch.Tensor:
    """``(B·V, C, h, w)`` viewed as ``(B, V, C, h, w)``."""
    return t.view(batch, -1, *t.shape[1:])


def _in_memory_order(t: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """``(B, V, C, h, w)`` with the channels moved last when they are last in memory."""
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
        last = is_channels_last(y)
        product = _in_memory_order(_tiles(y, len(masks)), last) * _in_memory_order(
            _batched(masks), last
        )
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


def _add_product(x: torch.Tensor, masks: tuple[torch.Tensor, ...], z: torch.Tensor) -> torch.Tensor:
    """``x + mask ⊙ z`` tile by tile, in one pass per tile."""
    batch = len(masks)
    if torch.is_grad_enabled():
        last = is_channels_last(x)
        x5, z5 = (_in_memory_order(_tiles(t, batch), last) for t in (x, z))
        out = torch.addcmul(x5, _in_memory_order(_batched(masks), last), z5)
        return _from_memory_order(out, last, x)
    dtype = torch.promote_types(torch.promote_types(x.dtype, z.dtype), masks[0].dtype)
    out = torch.empty_like(x, dtype=dtype)
    for o, xb, m, zb in zip(
        _tiles(out, batch), _tiles(x, batch), masks, _tiles(z, batch), strict=True
    ):
        if isinstance(m, RowInterpolant):
            m.add_product(xb, zb, o)
        else:
            torch.addcmul(xb, m, zb, out=o)
    return out
