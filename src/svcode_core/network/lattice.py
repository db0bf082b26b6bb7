"""The mask lattice: coordinate masks evaluated on coarse nodes and interpolated to pixels.

With ``ModelConfig.mask_spacing = p > 0`` the mask MLPs are not evaluated at every pixel.
At U-Net level ``k`` (pixels ``2^k`` level-0 pixels apart) the lattice nodes are the
level-``k`` pixel centres of the sub-view grid at every ``p``-th level-0 pixel: node ``j``
sits at level-0 position ``j·p + (2^k - 1)/2``. The masks of a tile pixel are the bilinear
interpolation of the masks at the four surrounding nodes; a tile pixel ``i`` of a tile at
origin ``o`` has the node coordinate ``u = (o + 2^k i) / p``. The lattice is global (it
does not move with the tile), so overlapping tiles and a whole sub-view see the same masks
and tiled and untiled outputs agree to float precision.

Interpolation error: the MLPs see the positional encoding, whose fastest feature is
``sin(π f t)`` with ``f`` the largest band frequency (units of π per normalised
coordinate). Linear interpolation of ``sin(ω t)`` with node spacing ``Δ`` errs by at most
``ω² Δ² / 8``; :func:`encoding_error_bound` gives that bound for a configuration and
:func:`mask_spacing_for` the largest spacing within a tolerance.

Two interpolation routes give the same values: for masks shared by the lenses, when the
level stride ``2^k`` divides both ``p`` and every tile origin (the usual case: tile grids
and training patches sit on multiples of the model stride), one bilinear up-sampling with
aligned corners covers the tiles; otherwise two passes of linear interpolation do
(columns, then rows), each taking two node rows or columns per pixel, which write each
tile's masks once, in the layout of the features they multiply (channels last, or
channels first for the view block). The up-sampling kernel is the faster of the two for
one lens and many channels, but slow for a batch of nine lenses of few channels.
Interpolation runs in float32 under autocast as well: its work is two taps per axis, and
a bfloat16 product on a processor without bfloat16 units is emulated (as a product with
the node-to-pixel weight matrices it was 24x slower than in float32 on a paper-scale tile).

Masks that are used once and not kept (inference without the mask cache, or beyond its
budget) need not exist at full resolution: :func:`row_interpolants` interpolates them
along the columns only (``R`` node rows, a few percent of the pixels), and
:class:`RowInterpolant` finishes the rows band by band where the masks are applied, each
band small enough to stay in the processor's cache while it multiplies the features. On
a paper-scale tile this makes the masks' interpolation and products 4-9x faster than
writing the masks out and reading them back.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .encoding import frequencies

__all__ = ["LatticeAxis", "RowInterpolant", "encoding_error_bound", "interpolate",
           "interpolate_once", "lattice_axis", "mask_spacing_for", "row_interpolants"]

#: Largest band of mask rows :class:`RowInterpolant` interpolates at once (bytes): it is
#: multiplied into the features while it is still in the processor's cache. Masks of a
#: tile that fit in one band are written out whole instead (:func:`interpolate_once`).
BAND_BYTES = 1 << 22


@dataclass(frozen=True)
class LatticeAxis:
    """Where the pixels of a batch of tiles fall among the lattice nodes along one axis.

    Attributes
    ----------
    position : torch.Tensor
        ``(U, n)`` float64: node coordinate of every tile pixel, relative to the first node
        of its tile (``0 <= position <= nodes - 1``).
    nodes : int
        Nodes per tile (the same for every tile of the batch).
    upsample : int or None
        Level pixels per node when the aligned route applies, else ``None``.
    crops : tuple of int
        Per tile, its first pixel in the aligned up-sampled grid (aligned route only).
    """

    position: torch.Tensor
    nodes: int
    upsample: int | None
    crops: tuple[int, ...]

    def select(self, tiles: list[int]) -> LatticeAxis:
        """The same axis for some of the tiles only."""
        crops = tuple(self.crops[t] for t in tiles) if self.crops else ()
        return LatticeAxis(self.position[tiles], self.nodes, self.upsample, crops)


def lattice_axis(
    origins: torch.Tensor, length: int, level: int, spacing: int, size: int
) -> tuple[torch.Tensor, LatticeAxis]:
    """Node coordinates covering each tile along one axis, and where its pixels fall.

    Parameters
    ----------
    origins : torch.Tensor
        ``(U,)`` integer first level-0 pixel of each tile.
    length : int
        Tile pixels along the axis at this level.
    level : int
        U-Net level ``k``.
    spacing : int
        ``p``, level-0 pixels between nodes.
    size : int
        The sub-view size ``S`` (normalises the coordinates).

    Returns
    -------
    coords : torch.Tensor
        ``(U, nodes)`` float64 normalised coordinates of the nodes each tile needs.
    axis : LatticeAxis

    Examples
    --------
    >>> coords, axis = lattice_axis(torch.tensor([0, 16]), 32, 0, 8, 65)
    >>> axis.nodes, axis.upsample, axis.crops
    (5, 8, (0, 0))
    >>> coords[0, :2].tolist()
    [-1.0, -0.75]
    """
    step = 2**level
    origins = origins.long().cpu()
    first = torch.div(origins, spacing, rounding_mode="floor")
    last = torch.div(origins + step * (length - 1), spacing, rounding_mode="floor") + 1
    nodes = int((last - first).max()) + 1
    index = first[:, None] + torch.arange(nodes)
    coords = (2.0 * (index * spacing + (step - 1) / 2) / (size - 1) - 1.0).to(torch.float64)
    pixels = origins[:, None] + step * torch.arange(length)
    position = pixels.to(torch.float64) / spacing - first[:, None]
    aligned = spacing % step == 0 and bool((origins % step == 0).all())
    upsample = spacing // step if aligned else None
    crops = tuple(((origins - first * spacing) // step).tolist()) if aligned else ()
    return coords, LatticeAxis(position, nodes, upsample, crops)


def interpolate(
    masks: torch.Tensor, rows: LatticeAxis, cols: LatticeAxis, channels_last: bool = True
) -> list[torch.Tensor]:
    """Masks at the tile pixels from masks at the nodes.

    Parameters
    ----------
    masks : torch.Tensor
        ``(U, lenses, C, rows.nodes, cols.nodes)``.
    rows, cols : LatticeAxis
    channels_last : bool
        The layout of the features the masks will multiply: channels vary fastest, or
        (``False``) columns do.

    Returns
    -------
    list of torch.Tensor
        Per tile ``(lenses, C, h, w)``, dense in the layout asked for (possibly views into
        one tensor holding every tile's).
    """
    tiles, lenses, channels = masks.shape[:3]
    h, w = rows.position.shape[1], cols.position.shape[1]
    aligned = rows.upsample is not None and cols.upsample is not None
    if channels_last and lenses == 1 and aligned:
        size = ((rows.nodes - 1) * rows.upsample + 1, (cols.nodes - 1) * cols.upsample + 1)
        flat = masks.reshape(tiles * lenses, channels, rows.nodes, cols.nodes)
        # a copy of the (small) node masks with canonical channels-last strides: the
        # up-sampling kernel takes its fast channels-last route only then (a batch of one
        # with a non-canonical batch stride is treated as contiguous, ~20x slower)
        flat = flat.clone(memory_format=torch.channels_last)
        up = F.interpolate(flat, size=size, mode="bilinear", align_corners=True)
        up = up.view(tiles, lenses, channels, *size)
        # each tile's crop copied out dense: the products with the features then run over
        # one contiguous block (a strided crop halves their speed on two threads)
        return [
            up[t, :, :, r : r + h, c : c + w].contiguous(memory_format=torch.channels_last)
            for t, (r, c) in enumerate(zip(rows.crops, cols.crops, strict=True))
        ]
    along_cols = _along_columns(masks, cols, channels_last)
    row_dim = 2 if channels_last else 3  # (U, lenses, R, w, C) or (U, lenses, C, R, w)
    out = _lerp_axis(along_cols, rows.position, row_dim, rows.nodes)
    if not channels_last:
        return list(out)
    return list(out.permute(0, 1, 4, 2, 3))  # (U, lenses, C, h, w), channels-last strides


def _along_columns(masks: torch.Tensor, cols: LatticeAxis, channels_last: bool) -> torch.Tensor:
    """Masks ``(U, lenses, C, R, S)`` at the nodes interpolated to the tile columns, in the
    features' memory order: ``(U, lenses, R, w, C)``, or ``(U, lenses, C, R, w)``."""
    if channels_last:
        return _lerp_axis(masks.permute(0, 1, 3, 4, 2), cols.position, 3, cols.nodes)
    return _lerp_axis(masks, cols.position, 4, cols.nodes)


def _lerp_axis(t: torch.Tensor, position: torch.Tensor, dim: int, nodes: int) -> torch.Tensor:
    """``t`` ``(U, lenses, ...)`` interpolated along ``dim`` from its ``nodes`` node values
    to the ``(U, n)`` node coordinates ``position``: two taps and one lerp per value, in
    ``t``'s dtype whatever autocast says (neither step is a product).

    Examples
    --------
    >>> t = torch.tensor([[[0.0, 2.0, 6.0]]])
    >>> _lerp_axis(t, torch.tensor([[0.0, 0.5, 1.5, 2.0]], dtype=torch.float64), 2, 3)
    tensor([[[0., 1., 4., 6.]]])
    """
    below = _node_below(position, nodes)
    weights = (position - below).to(t.device, t.dtype)
    below = below.long().to(t.device)
    if t.requires_grad and torch.is_grad_enabled():
        # every tile at once: each tile's node indices broadcast over its other dims, the
        # upper tap gathered from the nodes shifted by one (no index tensor of that size)
        shape = [1] * t.ndim
        shape[0], shape[dim] = below.shape
        index = below.view(shape).expand(*t.shape[:dim], below.shape[1], *t.shape[dim + 1 :])
        upper = t.narrow(dim, 1, nodes - 1)
        return torch.lerp(t.gather(dim, index), upper.gather(dim, index), weights.view(shape))
    # written in place, one lens at a time: the only temporary is one lens's second tap
    shape = [-1 if d == dim - 2 else 1 for d in range(t.ndim - 2)]  # a lens's dims
    out = t.new_empty(*t.shape[:dim], position.shape[1], *t.shape[dim + 1 :])
    for tile, index in enumerate(below):
        weight = weights[tile].view(shape)
        for lens, nodes_of_lens in enumerate(t[tile]):
            target = out[tile, lens]
            torch.index_select(nodes_of_lens, dim - 2, index, out=target)
            target.lerp_(nodes_of_lens.index_select(dim - 2, index + 1), weight)
    return out


@dataclass(frozen=True)
class RowInterpolant:
    """One tile's masks interpolated along the columns, the rows left to where they are
    applied (:meth:`multiply_`, :meth:`add_product`), band by band.

    Attributes
    ----------
    columns : torch.Tensor
        The masks at the tile's columns and the lattice's node rows, in the features'
        memory order: ``(lenses, R, w, C)`` when ``channels_last``, else
        ``(lenses, C, R, w)``.
    bands : tuple of (int, int, int)
        ``(first row, end row, node row)``: consecutive tile rows between node rows ``j``
        and ``j + 1``, at most :data:`BAND_BYTES` of masks each.
    weights : torch.Tensor
        ``(h,)`` weight of node row ``j + 1`` at each tile row.
    channels_last : bool
    """

    columns: torch.Tensor
    bands: tuple[tuple[int, int, int], ...]
    weights: torch.Tensor
    channels_last: bool

    @property
    def dtype(self) -> torch.dtype:
        return self.columns.dtype

    def to(self, dtype: torch.dtype) -> RowInterpolant:
        """The same masks in ``dtype``."""
        return RowInterpolant(self.columns.to(dtype), self.bands, self.weights.to(dtype),
                              self.channels_last)

    def materialize(self) -> torch.Tensor:
        """The masks ``(lenses, C, h, w)`` at every pixel (for tests and inspection)."""
        rows = [mask for _, _, mask in self._masks()]
        return self._from_memory_order(torch.cat(rows, self._row_dim))

    def multiply_(self, features: torch.Tensor) -> None:
        """``features ⊙= masks`` in place; ``features`` is ``(V, C, h, w)`` in the layout
        the masks were made for, ``V`` the masks' lenses (any number for shared masks)."""
        ordered = self._in_memory_order(features)
        for start, end, mask in self._masks():
            ordered.narrow(self._row_dim, start, end - start).mul_(mask)

    def add_product(self, x: torch.Tensor, z: torch.Tensor, out: torch.Tensor) -> None:
        """``out = x + masks ⊙ z``, all ``(V, C, h, w)`` as in :meth:`multiply_`."""
        x, z, out = (self._in_memory_order(t) for t in (x, z, out))
        for start, end, mask in self._masks():
            x_band, z_band, out_band = (t.narrow(self._row_dim, start, end - start)
                                        for t in (x, z, out))
            torch.addcmul(x_band, mask, z_band, out=out_band)

    @property
    def _row_dim(self) -> int:
        return 1 if self.channels_last else 2

    def _in_memory_order(self, t: torch.Tensor) -> torch.Tensor:
        return t.permute(0, 2, 3, 1) if self.channels_last else t

    def _from_memory_order(self, t: torch.Tensor) -> torch.Tensor:
        return t.permute(0, 3, 1, 2) if self.channels_last else t

    def _masks(self) -> Iterator[tuple[int, int, torch.Tensor]]:
        """``(first row, end row, masks of those rows)`` per band, in memory order."""
        dim = self._row_dim
        for start, end, node in self.bands:
            weight = self.weights[start:end].view(-1, *[1] * (self.columns.ndim - dim - 1))
            yield start, end, torch.lerp(self.columns.narrow(dim, node, 1),
                                         self.columns.narrow(dim, node + 1, 1), weight)


def row_interpolants(
    masks: torch.Tensor, rows: LatticeAxis, cols: LatticeAxis, channels_last: bool = True
) -> list[RowInterpolant]:
    """Per tile, its masks as a :class:`RowInterpolant` (the arguments as for
    :func:`interpolate`, which gives the same masks at every pixel to float rounding).

    Examples
    --------
    >>> _, rows = lattice_axis(torch.tensor([0]), 12, 0, 4, 65)
    >>> masks = torch.rand(1, 1, 2, rows.nodes, rows.nodes)
    >>> lazy = row_interpolants(masks, rows, rows, channels_last=False)[0]
    >>> full = interpolate(masks, rows, rows, channels_last=False)[0]
    >>> torch.allclose(lazy.materialize(), full, rtol=1e-6, atol=1e-7)
    True
    """
    columns = _along_columns(masks, cols, channels_last)
    row_bytes = columns[0].numel() // rows.nodes * columns.element_size()
    longest = max(1, BAND_BYTES // row_bytes)
    out = []
    for tile, position in enumerate(rows.position):
        node = _node_below(position, rows.nodes)
        below = [int(j) for j in node.tolist()]
        bands, start = [], 0
        for end in range(1, len(below) + 1):
            if end == len(below) or below[end] != below[start] or end - start == longest:
                bands.append((start, end, below[start]))
                start = end
        weights = (position - node).to(masks.device, masks.dtype)
        out.append(RowInterpolant(columns[tile], tuple(bands), weights, channels_last))
    return out


def interpolate_once(
    masks: torch.Tensor, rows: LatticeAxis, cols: LatticeAxis, channels_last: bool = True
) -> list[torch.Tensor | RowInterpolant]:
    """Per tile, its masks for a single use without gradient: written out
    (:func:`interpolate`) when they fit in :data:`BAND_BYTES`, where band by band would
    only add steps, else as a :class:`RowInterpolant`."""
    nodes = rows.nodes * cols.nodes
    pixels = rows.position.shape[1] * cols.position.shape[1]
    per_tile = masks[0].numel() // nodes * pixels * masks.element_size()
    route = row_interpolants if per_tile > BAND_BYTES else interpolate
    return route(masks, rows, cols, channels_last)


def _node_below(position: torch.Tensor, nodes: int) -> torch.Tensor:
    """The node at or before each position (the last pixel counts as in the last gap)."""
    return position.floor().clamp(max=nodes - 2)


def encoding_error_bound(
    spacing: int, sub_view_size: int, bands: int, scheme: str, enabled: bool = True
) -> float:
    """Bound on the linear-interpolation error of the encoding features: ``ω² Δ² / 8``.

    ``Δ = 2 p / (S - 1)`` is the node spacing in normalised coordinates and ``ω = π f`` the
    fastest band; without positional encoding the raw coordinate is linear and
    interpolates exactly (0). ``spacing = 0`` (exact masks) gives 0.

    Examples
    --------
    >>> round(encoding_error_bound(8, 384, 4, "code"), 4)
    0.0086
    """
    if spacing == 0 or not enabled:
        return 0.0
    omega = math.pi * max(frequencies(bands, scheme))
    delta = 2.0 * spacing / (sub_view_size - 1)
    return omega**2 * delta**2 / 8.0


def mask_spacing_for(
    sub_view_size: int,
    bands: int,
    scheme: str,
    levels: int,
    tolerance: float = 1e-2,
) -> int:
    """The largest node spacing, a multiple of the model stride ``2**levels`` where
    possible, whose :func:`encoding_error_bound` is within ``tolerance``; 0 (exact masks)
    when even one pixel is too coarse.

    Examples
    --------
    >>> mask_spacing_for(384, 4, "code", levels=3), mask_spacing_for(2400, 4, "code", levels=4)
    (8, 48)
    """
    omega = math.pi * max(frequencies(bands, scheme))
    largest = math.sqrt(8.0 * tolerance) / omega * (sub_view_size - 1) / 2.0
    stride = 2**levels
    if largest >= stride:
        return int(largest // stride) * stride
    return int(largest)
