"""CoordGate: a convolution whose output is gated by a coordinate-conditioned mask.

``CoordGate(F) = M(r) ⊙ (W ∗ F)`` with ``M(r) = sigmoid(MLP(γ(r)))`` per channel. The MLP
sees only the positional encoding of the global pixel coordinates ``r = (v, u)``, so the
masks are a fixed function of the position in the sub-view and can be computed once and
frozen (:class:`MaskCache`, :func:`tile_masks`).

The first MLP layer acts on the concatenation ``[γ(v), γ(u)]``, so it splits exactly into
a row term plus a column term; it is evaluated on the ``h + w`` axis samples and
broadcast, and only the output layer runs per pixel.

Mask cache
    Masks are cached per layer over the whole (padded) sub-view grid of a U-Net level, a
    *field*, and every tile crops a view of it. A tile can use the field when its origin
    is a multiple of the level stride ``2^k`` (then its level-``k`` grid is a subgrid of
    the field's) and it lies inside the field; other tiles get masks computed for them.
    Memory is therefore set by ``S`` and the model, not by the number of tiles. Fields
    are stored channels-last like the features (:mod:`.models`), so a tile's crop is
    read in runs of ``w · C`` contiguous values.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from .lattice import LatticeAxis, RowInterpolant, interpolate, interpolate_once

__all__ = ["CoordGate", "CoordGrid", "CoordMLP", "MaskCache", "MaskField", "tile_masks"]

FIELD_CHUNK_BYTES = 1 << 26
"""Bound on the working memory (hidden activations and masks) while a field is computed."""


class CoordMLP(nn.Module):
    """``features → hidden (ReLU) → channels (sigmoid)``, one weight set per lens.

    Parameters
    ----------
    axis_features : int
        Encoding features per axis ``E`` (input is ``2E``: rows then columns).
    hidden : int
        Hidden units.
    channels : int
        Mask channels (the gated convolution's output channels).
    lenses : int
        1 for an MLP shared by all lenses, 9 for one MLP per lens.
    """

    def __init__(self, axis_features: int, hidden: int, channels: int, lenses: int = 1) -> None:
        super().__init__()
        self.lenses, self.channels = lenses, channels
        self.w_row = nn.Parameter(torch.empty(lenses, hidden, axis_features))
        self.w_col = nn.Parameter(torch.empty(lenses, hidden, axis_features))
        self.b_hidden = nn.Parameter(torch.empty(lenses, hidden, 1, 1))
        self.w_out = nn.Parameter(torch.empty(lenses, channels, hidden))
        self.b_out = nn.Parameter(torch.empty(lenses, channels, 1))
        for weight, fan_in in (
            (self.w_row, 2 * axis_features),
            (self.w_col, 2 * axis_features),
            (self.b_hidden, 2 * axis_features),
            (self.w_out, hidden),
            (self.b_out, hidden),
        ):  # the default nn.Linear initialisation, U(±1/sqrt(fan_in))
            nn.init.uniform_(weight, -1.0 / math.sqrt(fan_in), 1.0 / math.sqrt(fan_in))

    def forward(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor, channels: slice | None = None
    ) -> torch.Tensor:
        """Masks for a batch of grids.

        Parameters
        ----------
        enc_row, enc_col : torch.Tensor
            Encodings ``(B, h, E)`` and ``(B, w, E)``.
        channels : slice, optional
            Compute only these mask channels.

        Returns
        -------
        torch.Tensor
            ``(B, lenses, C, h, w)`` in ``(0, 1)``, channels-last (channels vary fastest)
            like the features it gates.
        """
        lenses, hidden_size = self.w_row.shape[:2]
        rows = torch.einsum("bhe,nke->bnhk", enc_row, self.w_row)
        cols = torch.einsum("bwe,nke->bnwk", enc_col, self.w_col)
        bias = self.b_hidden.view(lenses, 1, 1, hidden_size)
        hidden = torch.relu(rows.unsqueeze(-2) + cols.unsqueeze(-3) + bias)
        w_out, b_out = self.w_out, self.b_out
        if channels is not None:
            w_out, b_out = w_out[:, channels], b_out[:, channels]
        logits = torch.matmul(hidden, w_out.transpose(1, 2).unsqueeze(1))
        logits = logits + b_out.view(lenses, 1, 1, -1)
        return torch.sigmoid(logits).permute(0, 1, 4, 2, 3)


class MaskCache:
    """Frozen masks (tuples of tensors) under hashable keys, bounded in bytes.

    Least-recently-used entries make room for new ones, except entries used during the
    current or the previous forward call (:meth:`new_call`), the working set: when the
    masks of one call do not all fit, the first ones stay cached and the rest are
    computed each time, instead of every new entry evicting one needed later in the call
    (an LRU cycling through more than it holds never hits). Entries of a pattern no
    longer in use (another sub-view size, dtype or tile size) become evictable one call
    later. The owner calls :meth:`check_weights` before each call so that changed
    weights drop everything. Every method holds one lock, so forward calls may run on
    several threads at once (frames of a recording side by side).
    """

    def __init__(self, max_bytes: int) -> None:
        if not isinstance(max_bytes, int) or max_bytes < 0:
            raise ValueError(f"max_bytes must be a non-negative integer, got {max_bytes!r}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[Hashable, tuple[tuple[torch.Tensor, ...], int]] = OrderedDict()
        self._bytes = 0
        self._weights_key: Hashable = None
        self._call = 0
        self.hits = 0
        self.misses = 0
        self._lock = threading.RLock()

    def check_weights(self, key: Hashable) -> None:
        """Drop every entry if ``key`` (a fingerprint of the mask weights) changed."""
        with self._lock:
            if key != self._weights_key:
                self.clear()
                self._weights_key = key

    def new_call(self) -> None:
        """Start a forward call: entries it uses are not evicted during it or the next one."""
        with self._lock:
            self._call += 1

    def clear(self) -> None:
        """Drop every entry (the hit and miss counters are kept)."""
        with self._lock:
            self._entries.clear()
            self._bytes = 0

    def get(self, key: Hashable) -> tuple[torch.Tensor, ...] | None:
        """The entry for ``key`` (marked most recently used), or ``None``."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is None:
                self.misses += 1
                return None
            self.hits += 1
            self._entries[key] = (entry[0], self._call)
            self._entries.move_to_end(key)
            return entry[0]

    def reserve(self, nbytes: int) -> bool:
        """Make room for ``nbytes`` by evicting entries outside the working set, if that
        suffices (otherwise nothing is evicted); whether ``nbytes`` fit."""
        with self._lock:
            evictable = [
                (key, _nbytes(mask))
                for key, (mask, call) in self._entries.items()
                if call < self._call - 1
            ]
            if self._bytes - sum(size for _, size in evictable) + nbytes > self.max_bytes:
                return False
            for key, size in evictable:  # least recently used first
                if self._bytes + nbytes <= self.max_bytes:
                    break
                del self._entries[key]
                self._bytes -= size
            return True

    def put(self, key: Hashable, masks: tuple[torch.Tensor, ...]) -> bool:
        """Store ``masks`` (detached, not copied) if :meth:`reserve` makes room; whether stored."""
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self._bytes -= _nbytes(old[0])
            size = _nbytes(masks)
            if not self.reserve(size):
                return False
            self._entries[key] = (tuple(m.detach() for m in masks), self._call)
            self._bytes += size
            return True

    def info(self) -> dict[str, int]:
        """``entries``, ``bytes``, ``max_bytes``, ``hits`` and ``misses``."""
        with self._lock:
            return {
                "entries": len(self._entries),
                "bytes": self._bytes,
                "max_bytes": self.max_bytes,
                "hits": self.hits,
                "misses": self.misses,
            }


def _nbytes(masks: tuple[torch.Tensor, ...]) -> int:
    return sum(m.numel() * m.element_size() for m in masks)


@dataclass(frozen=True)
class MaskField:
    """The whole-field grid of one U-Net level and where each tile sits in it.

    Attributes
    ----------
    key : tuple
        Identifies the field (sub-view size, level, cells per side).
    enc_row, enc_col : torch.Tensor
        Encodings ``(1, rows, E)`` and ``(1, cols, E)`` of the field's grid.
    offsets : tuple
        Per tile, its first ``(row, col)`` in field cells, or ``None`` when the tile is
        not a subgrid of the field (unaligned origin, or outside).
    """

    key: tuple
    enc_row: torch.Tensor
    enc_col: torch.Tensor
    offsets: tuple[tuple[int, int] | None, ...]


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
        The level's whole-field grid (set when ``cache`` is).
    tiles : torch.Tensor or None
        ``(B,)`` index of each tile's origin among the encodings: tiles at the same
        origin share one mask computation (set only on the uncached path).
    lattice : tuple of LatticeAxis or None
        ``(rows, cols)``: the encodings are lattice nodes, interpolated to the tile pixels
        (:mod:`.lattice`).
    places : tuple or None
        With ``lattice`` and ``cache``: per distinct origin, a hashable key of where its
        tile lies (origin, level, size, sub-view), under which its interpolated masks
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

    def tile_masks(self, masks: Masks, channels_last: bool = True) -> list[Masks]:
        """Per tile, its masks ``(lenses, C, h, w)`` from masks ``(U, lenses, C, ., .)``
        computed at ``enc_row`` and ``enc_col``: interpolated from the lattice nodes when
        ``lattice`` is set (in the features' layout; without gradient, large ones as
        :class:`~.lattice.RowInterpolant`), and repeated for tiles that share an origin."""
        if self.lattice is None:
            per_origin = list(zip(*masks, strict=True))
        else:
            lattice = interpolate_once if not torch.is_grad_enabled() else interpolate
            per_origin = list(zip(*(lattice(m, *self.lattice, channels_last)
                                    for m in masks), strict=True))  # fmt: skip
        return self._per_tile(per_origin)

    def cached_lattice_masks(
        self, name: Hashable, compute: MaskFunction, dtype: torch.dtype, channels_last: bool
    ) -> list[Masks]:
        """Per tile, its interpolated lattice masks ``(lenses, C, h, w)`` in ``dtype``:
        from the cache, or computed for the origins it lacks and stored while they fit.

        A recording's frames run the same tiles, so from the second frame on the masks are
        read, not interpolated (the interpolation is most of what lattice masks cost).
        Large masks beyond the cache's budget are not written out at all: they come as
        :class:`~.lattice.RowInterpolant`, finished where they are applied.
        """
        keys = [(name, place, dtype, channels_last) for place in self.places]
        per_origin: list[Masks | tuple[RowInterpolant, ...] | None] = [
            self.cache.get(key) for key in keys]
        missing = [u for u, masks in enumerate(per_origin) if masks is None]
        if missing:
            index = torch.tensor(missing, device=self.enc_row.device)
            nodes = compute(self.enc_row[index], self.enc_col[index])
            rows, cols = (axis.select(missing) for axis in self.lattice)
            pixels = rows.position.shape[1] * cols.position.shape[1]
            nbytes = sum(math.prod(m.shape[1:3]) for m in nodes) * pixels * dtype.itemsize
            keep = self.cache.reserve(nbytes)  # False: none of them would fit
            lattice = interpolate if keep else interpolate_once
            computed = zip(*(lattice(m, rows, cols, channels_last) for m in nodes),
                           strict=True)  # fmt: skip
            for u, masks in zip(missing, computed, strict=True):
                masks = tuple(m.to(dtype) for m in masks)
                if keep and self.cache.reserve(sum(m.nbytes for m in masks)):
                    # stored on their own: a view would keep the whole batch's tensor
                    masks = tuple(m.clone() if _shares_storage(m) else m for m in masks)
                    self.cache.put(keys[u], masks)
                per_origin[u] = masks
        return self._per_tile(per_origin)

    def _per_tile(self, per_origin: list[Masks]) -> list[Masks]:
        """Masks per distinct origin repeated for the tiles that share it."""
        if self.tiles is None:
            return per_origin
        return [per_origin[u] for u in self.tiles.tolist()]


def _shares_storage(t: torch.Tensor) -> bool:
    """Whether ``t`` is a view of a larger tensor (its storage holds more than it)."""
    return t.untyped_storage().nbytes() > t.nbytes


Masks = tuple[torch.Tensor, ...]
MaskFunction = Callable[[torch.Tensor, torch.Tensor], Masks]


def tile_masks(
    grid: CoordGrid,
    name: Hashable,
    compute: MaskFunction,
    shapes: Sequence[tuple[int, int]],
    pixel_bytes: int,
    dtype: torch.dtype,
) -> list[Masks]:
    """Per-tile masks, cropped from the cached field where possible.

    Parameters
    ----------
    grid : CoordGrid
        With ``cache`` and ``field`` set.
    name : hashable
        Identifies the masks (the layer) in the cache.
    compute : callable
        ``compute(enc_row (B, h, E), enc_col (B, w, E))`` returns a tuple of masks
        ``(B, lenses, C_i, h, w)``.
    shapes : sequence of (int, int)
        ``(lenses, C_i)`` of each mask.
    pixel_bytes : int
        Working memory of ``compute`` per pixel, to evaluate a field in row chunks.
    dtype : torch.dtype
        Of the returned (and stored) masks, which are channels-last.

    Returns
    -------
    list of tuple of torch.Tensor
        Per tile, its masks ``(lenses, C_i, h, w)`` (views into the cached field for the
        tiles that fit it).
    """
    field, cache = grid.field, grid.cache
    h, w = grid.enc_row.shape[1], grid.enc_col.shape[1]
    full = None
    if any(o is not None for o in field.offsets):
        key = (name, field.key, dtype)
        full = cache.get(key)
        if full is None:
            cells = field.enc_row.shape[1] * field.enc_col.shape[1]
            if cache.reserve(sum(math.prod(s) for s in shapes) * cells * dtype.itemsize):
                full = _field_masks(field, compute, shapes, pixel_bytes, dtype)
                cache.put(key, full)
    out: list[Masks | None] = [
        None if full is None or o is None
        else tuple(m[..., o[0] : o[0] + h, o[1] : o[1] + w] for m in full)
        for o in field.offsets
    ]
    missing = [b for b, masks in enumerate(out) if masks is None]
    if missing:
        index = torch.tensor(missing, device=grid.enc_row.device)
        computed = compute(grid.enc_row[index], grid.enc_col[index])
        for i, b in enumerate(missing):
            out[b] = tuple(m[i].to(dtype, memory_format=torch.channels_last) for m in computed)
    return out


def _field_masks(
    field: MaskField,
    compute: MaskFunction,
    shapes: Sequence[tuple[int, int]],
    pixel_bytes: int,
    dtype: torch.dtype,
) -> Masks:
    """The masks of the whole field ``(lenses, C_i, rows, cols)``, computed in row chunks."""
    rows, cols = field.enc_row.shape[1], field.enc_col.shape[1]
    full = tuple(
        torch.empty(*shape, rows, cols, dtype=dtype, device=field.enc_row.device,
                    memory_format=torch.channels_last)
        for shape in shapes
    )
    chunk = max(1, FIELD_CHUNK_BYTES // (pixel_bytes * cols))
    for start in range(0, rows, chunk):
        parts = compute(field.enc_row[:, start : start + chunk], field.enc_col)
        for target, part in zip(full, parts, strict=True):
            target[:, :, start : start + chunk] = part[0]
    return full


class CoordGate(nn.Module):
    """A convolution followed by a coordinate-conditioned per-channel mask.

    With ``mlp_hidden=None`` no MLP is built and the layer is the plain convolution
    (the ``coord_gate=False`` ablation).

    Parameters
    ----------
    in_channels, out_channels, kernel_size : int
        Of the convolution (``padding = kernel_size // 2``, zero padded).
    groups : int
        Convolution groups (``out_channels`` for the depthwise convolution).
    axis_features : int
        Encoding features per axis.
    mlp_hidden : int or None
        Hidden units of the mask MLP, or ``None`` for no mask.
    lenses : int
        1 (mask shared by the lenses) or 9 (one MLP per lens).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 1,
        groups: int = 1,
        axis_features: int = 8,
        mlp_hidden: int | None = 64,
        lenses: int = 1,
    ) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels, kernel_size, padding=kernel_size // 2, groups=groups
        )
        self.mlp = (
            None
            if mlp_hidden is None
            else CoordMLP(axis_features, mlp_hidden, out_channels, lenses)
        )

    def forward(self, x: torch.Tensor, grid: CoordGrid | None) -> torch.Tensor:
        """``M(r) ⊙ conv(x)``; ``x`` is ``(B·V, C, h, w)`` with ``V`` views per tile.

        The masks are computed here; the cached inference path is
        :meth:`~.blocks.CoDeBlock.forward`, which folds the masks of a whole block.
        """
        y = self.conv(x)
        if self.mlp is None:
            return y
        if grid is None:
            raise ValueError("a CoordGate with a mask needs the tile coordinates")
        batch = grid.batch
        mask = self.masks(grid.enc_row, grid.enc_col)
        if grid.tiles is not None:
            mask = mask[grid.tiles]
        return (y.view(batch, -1, *y.shape[1:]) * mask.to(y.dtype)).view_as(y)

    def masks(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor, channels: slice | None = None
    ) -> torch.Tensor:
        """Masks ``(B, lenses, C, h, w)``, computed in the MLP's dtype without autocast."""
        if self.mlp is None:
            raise ValueError("this layer has no coordinate mask (coord_gate=False)")
        dtype = self.mlp.w_out.dtype
        with torch.autocast(enc_row.device.type, enabled=False):
            return self.mlp(enc_row.to(dtype), enc_col.to(dtype), channels)
