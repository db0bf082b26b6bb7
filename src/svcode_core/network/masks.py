"""The masks of one forward call: where the tiles lie, and providers of each block's masks.

A *mask provider* is built for the tiles of a call (:meth:`~.base.TiledModel.masks_for`)
and called as ``masks(block, level)`` for each CoDe block at its U-Net level. Two exist:

* :class:`PlainMasks` gives the five gates' masks ``M(r)`` at the tile pixels, computed as
  the formula states; the block applies them gate by gate (:class:`~.models.CoordGate`).
* :class:`~.fast.FastMasks`, the default, gives the same masks folded, cached or
  interpolated from a lattice, and runs the block on them (:mod:`.fast`).

Both start from a :class:`CoordGrid` per level (:func:`coordinate_grids`): the positional
encodings of the points where the mask MLPs are evaluated, the tile pixels or, with
``ModelConfig.mask_spacing``, the lattice nodes around each tile (:mod:`.lattice`).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from .cache import MaskCache, MaskField, field_grids
from .encoding import level_coordinates
from .lattice import LatticeAxis, interpolate, interpolate_once, lattice_axis

__all__ = ["CoordGrid", "MaskProvider", "PlainMasks", "coordinate_grids"]

Masks = tuple[torch.Tensor, ...]
MaskProvider = Callable[[nn.Module, int], Any]
"""``masks(block, level)``: what a CoDe block at a U-Net level is given for its gates."""
Encoder = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class CoordGrid:
    """Coordinates of a batch of tiles at one U-Net level.

    Attributes
    ----------
    enc_row, enc_col : torch.Tensor
        Positional encodings of the points where the mask MLPs are evaluated: the tile
        pixels ``(B, h, E)`` and ``(B, w, E)``, or the lattice nodes of each tile when
        ``lattice`` is set; ``U`` rows instead of ``B`` for the ``U`` distinct tile
        origins when ``tiles`` is set.
    cache : MaskCache or None
        Where masks are looked up; ``None`` computes them every time.
    field : MaskField or None
        The level's whole-field grid (set when ``cache`` is, for exact masks).
    tiles : torch.Tensor or None
        ``(B,)`` index of each tile's origin among the encodings: tiles at the same
        origin share one mask computation.
    lattice : tuple of LatticeAxis or None
        ``(rows, cols)``: the encodings are lattice nodes, interpolated to the tile pixels.
    places : tuple or None
        With ``lattice`` and ``cache``: per distinct origin, a hashable key of where its
        tile lies (sub-view, level, size, origin), under which its interpolated masks
        are cached.
    """

    enc_row: torch.Tensor
    enc_col: torch.Tensor
    cache: MaskCache | None = None
    field: MaskField | None = None
    tiles: torch.Tensor | None = None
    lattice: tuple[LatticeAxis, LatticeAxis] | None = None
    places: tuple[Hashable, ...] | None = None

    @property
    def batch(self) -> int:
        """Number of tiles."""
        return self.enc_row.shape[0] if self.tiles is None else self.tiles.shape[0]

    @property
    def cached(self) -> bool:
        """Whether masks come from the cache (a cache is set and no gradient is needed)."""
        return self.cache is not None and not torch.is_grad_enabled()

    def tile_masks(self, masks: Masks, channels_last: bool = True,
                   dtype: torch.dtype | None = None) -> list[Masks]:  # fmt: skip
        """Per tile, its masks ``(lenses, C, h, w)`` from masks ``(U, lenses, C, ., .)``
        computed at ``enc_row`` and ``enc_col``: interpolated from the lattice nodes when
        ``lattice`` is set (in the features' layout; without gradient, large ones as
        :class:`~.lattice.RowInterpolant`), converted to ``dtype`` if given, and repeated
        for tiles that share an origin (the same object, so they broadcast, not copy)."""
        if self.lattice is None:
            per_origin = list(zip(*masks, strict=True))
        else:
            lattice = interpolate_once if not torch.is_grad_enabled() else interpolate
            per_origin = list(zip(*(lattice(m, *self.lattice, channels_last) for m in masks),
                                  strict=True))  # fmt: skip
        if dtype is not None:
            per_origin = [tuple(m.to(dtype) for m in origin) for origin in per_origin]
        return self.per_tile(per_origin)

    def per_tile(self, per_origin: list) -> list:
        """Values per distinct origin repeated for the tiles that share it."""
        if self.tiles is None:
            return per_origin
        return [per_origin[u] for u in self.tiles.tolist()]


def coordinate_grids(
    encode: Encoder,
    origins: torch.Tensor,
    sub_view_size: int,
    shape: tuple[int, int],
    levels: int,
    spacing: int = 0,
    cache: MaskCache | None = None,
    first: int = 0,
) -> list[CoordGrid]:
    """The grid of every U-Net level for tiles of padded ``shape`` at ``origins``.

    Parameters
    ----------
    encode : callable
        Positional encoding of normalised coordinates ``(n, m)`` → ``(n, m, E)``, in the
        dtype and on the device of the mask MLPs.
    origins : torch.Tensor
        ``(B, 2)`` integer level-0 origins of the tiles.
    sub_view_size : int
        ``S``.
    shape : (int, int)
        Tile size at level 0, a multiple of ``2**levels``.
    levels : int
        Down-sampling steps.
    spacing : int
        ``ModelConfig.mask_spacing``: 0 for masks at the pixels, else the lattice spacing.
    cache : MaskCache, optional
        With exact masks, the grids carry the whole-sub-view fields the cache keeps;
        with lattice masks, the tiles' places.
    first : int
        The sub-view's level at which the U-Net starts (``ModelConfig.coarse_levels``):
        ``shape`` and ``origins`` stay in sub-view pixels, ``shape`` a multiple of
        ``2**(first + levels)``, and the grids are those of levels ``first`` to
        ``first + levels``.

    Returns
    -------
    list of CoordGrid
        ``levels + 1`` grids. Tiles at one origin share their encodings (``tiles``),
        except for cached exact masks, which the field serves tile by tile.

    Examples
    --------
    >>> from .encoding import positional_encoding
    >>> grids = coordinate_grids(lambda t: positional_encoding(t, 4, "code"),
    ...                          torch.tensor([[0, 0], [8, 4], [0, 0]]), 48, (16, 16), 2)
    >>> [tuple(g.enc_row.shape) for g in grids], grids[0].tiles.tolist()
    ([(2, 16, 8), (2, 8, 8), (2, 4, 8)], [0, 1, 0])
    """
    levels += first
    fields: list[MaskField | None] = [None] * (levels + 1)
    if cache is not None and not spacing:
        fields = field_grids(encode, origins, sub_view_size, shape, levels)
    tiles = None
    if cache is None or spacing:
        distinct, tiles = torch.unique(origins, dim=0, return_inverse=True)
        if len(distinct) == len(origins):
            tiles = None
        else:  # tiles at one origin share their masks
            origins = distinct
    if spacing:
        return [
            _lattice_grid(encode, origins, sub_view_size, shape, level, spacing, tiles, cache)
            for level in range(first, levels + 1)
        ]
    rows = level_coordinates(origins[:, 0], shape[0], sub_view_size, levels)
    cols = level_coordinates(origins[:, 1], shape[1], sub_view_size, levels)
    return [
        CoordGrid(encode(r), encode(c), cache, field, tiles)
        for r, c, field in list(zip(rows, cols, fields, strict=True))[first:]
    ]


def _lattice_grid(
    encode: Encoder,
    origins: torch.Tensor,
    sub_view_size: int,
    shape: tuple[int, int],
    level: int,
    spacing: int,
    tiles: torch.Tensor | None,
    cache: MaskCache | None,
) -> CoordGrid:
    """The lattice nodes of every tile at one level; with a cache, the tiles' places."""
    axes = [
        lattice_axis(origins[:, axis], shape[axis] // 2**level, level, spacing, sub_view_size)
        for axis in (0, 1)
    ]
    (rows, row_axis), (cols, col_axis) = axes
    places = None
    if cache is not None:
        places = tuple((sub_view_size, level, *shape, *origin) for origin in origins.tolist())
    return CoordGrid(
        encode(rows),
        encode(cols),
        cache=cache,
        tiles=tiles,
        lattice=(row_axis, col_axis),
        places=places,
    )


class PlainMasks:
    """The masks as the formula states: each gate's ``M(r)`` at the tile pixels.

    Exact masks are the MLP at every pixel. On a lattice (``mask_spacing > 0``) the masks
    are interpolated from the nodes as the model was trained, where the two halves of a
    conv2 or conv4 mask, which meet in a SimpleGate, are interpolated as their product:
    that product stands in the first half of the mask here and the second half is 1, so
    that the gate ``M ⊙ conv`` followed by the SimpleGate applies it. Nothing is cached
    and every tile gets its own masks (``(B, lenses, C, h, w)`` per gate).

    Parameters
    ----------
    grids : sequence of CoordGrid
        One per U-Net level, without a cache (:func:`coordinate_grids`).
    """

    def __init__(self, grids: Sequence[CoordGrid]) -> None:
        self.grids = list(grids)

    def __call__(self, block: nn.Module, level: int) -> Masks:
        """The masks of ``block``'s five gates at ``level``."""
        grid = self.grids[level]
        gates = [getattr(block, f"conv{i}") for i in range(1, 6)]
        masks = [gate.masks(grid.enc_row, grid.enc_col) for gate in gates]
        if grid.lattice is not None:
            for i in (1, 3):  # conv2 and conv4: the pair's product, then 1
                first, second = masks[i].chunk(2, dim=2)
                masks[i] = torch.cat((first * second, torch.ones_like(second)), dim=2)
            masks = [torch.stack(interpolate(m, *grid.lattice)) for m in masks]
        if grid.tiles is not None:
            masks = [m[grid.tiles] for m in masks]
        return tuple(masks)
