"""The mask cache: frozen masks kept across forward calls, within a byte budget.

The masks are a fixed function of the position in the sub-view, so for inference they can
be computed once and read afterwards. Two kinds of entries:

Fields (exact masks, ``mask_spacing = 0``)
    A block's folded masks (:func:`~.fast.fold`) over the whole padded sub-view grid of its
    U-Net level, a *field*; every tile crops a view of it (:func:`from_field`). A tile can
    use the field when its origin is a multiple of the level stride ``2^k`` (then its
    level-``k`` grid is a subgrid of the field's) and it lies inside the field; other tiles
    get masks computed for them. Memory is therefore set by ``S`` and the model, not by the
    number of tiles. Fields are stored channels-last like the features, so a tile's crop is
    read in runs of ``w · C`` contiguous values.
Places (masks on a lattice)
    Each tile's interpolated masks under the tile's place (origin, shape, sub-view size,
    level; :func:`cached_lattice_masks`): the frames of a recording run the same tiles,
    and reading the masks costs less than interpolating them again.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from .encoding import level_coordinates
from .lattice import RowInterpolant, interpolate, interpolate_once

if TYPE_CHECKING:
    from .masks import CoordGrid

__all__ = [
    "MaskCache",
    "MaskField",
    "cached_lattice_masks",
    "field_cells",
    "field_grids",
    "from_field",
]

FIELD_CHUNK_BYTES = 1 << 26
"""Bound on the working memory (hidden activations and masks) while a field is computed."""

Masks = tuple[torch.Tensor, ...]
MaskFunction = Callable[[torch.Tensor, torch.Tensor], Masks]


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

    Examples
    --------
    >>> cache = MaskCache(max_bytes=64)
    >>> cache.put("a", (torch.zeros(8),)), cache.put("b", (torch.zeros(16),))
    (True, False)
    >>> cache.get("a")[0].shape, cache.get("b")
    (torch.Size([8]), None)
    """

    def __init__(self, max_bytes: int) -> None:
        if not isinstance(max_bytes, int) or max_bytes < 0:
            raise ValueError(f"max_bytes must be a non-negative integer, got {max_bytes!r}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[Hashable, tuple[Masks, int]] = OrderedDict()
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

    def get(self, key: Hashable) -> Masks | None:
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

    def put(self, key: Hashable, masks: Masks) -> bool:
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


def _nbytes(masks: Masks) -> int:
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


def field_cells(sub_view_size: int, levels: int) -> int:
    """Level-0 side of a field: pixels ``0 .. S + 2**levels - 2`` rounded up to the model
    stride, so a tile padded to the stride fits it whenever its unpadded part lies inside
    the sub-view.

    Examples
    --------
    >>> field_cells(48, 2)
    52
    """
    stride = 2**levels
    return math.ceil((sub_view_size + stride - 1) / stride) * stride


def field_grids(
    encode: Callable[[torch.Tensor], torch.Tensor],
    origins: torch.Tensor,
    sub_view_size: int,
    shape: tuple[int, int],
    levels: int,
) -> list[MaskField]:
    """The field of every level and the tiles' offsets in it; ``encode`` gives the
    positional encoding of coordinates."""
    axis = level_coordinates(
        torch.zeros(1, dtype=torch.long), field_cells(sub_view_size, levels), sub_view_size, levels
    )
    out = []
    for level, coords in enumerate(axis):
        step, cells = 2**level, coords.shape[1]
        offsets = tuple(
            (r // step, c // step)
            if min(r, c) >= 0
            and r % step == 0
            and c % step == 0
            and r + shape[0] <= cells * step
            and c + shape[1] <= cells * step
            else None
            for r, c in origins.tolist()
        )
        enc = encode(coords)
        out.append(MaskField((sub_view_size, level, cells), enc, enc, offsets))
    return out


def from_field(
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
        Identifies the masks (the block) in the cache.
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
        None
        if full is None or o is None
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
        torch.empty(
            *shape,
            rows,
            cols,
            dtype=dtype,
            device=field.enc_row.device,
            memory_format=torch.channels_last,
        )
        for shape in shapes
    )
    chunk = max(1, FIELD_CHUNK_BYTES // (pixel_bytes * cols))
    for start in range(0, rows, chunk):
        parts = compute(field.enc_row[:, start : start + chunk], field.enc_col)
        for target, part in zip(full, parts, strict=True):
            target[:, :, start : start + chunk] = part[0]
    return full


def cached_lattice_masks(
    grid: CoordGrid,
    name: Hashable,
    compute: MaskFunction,
    dtype: torch.dtype,
    channels_last: bool,
) -> list[Masks | tuple[RowInterpolant, ...]]:
    """Per tile, its interpolated lattice masks ``(lenses, C, h, w)`` in ``dtype``: from the
    cache, or computed for the places it lacks and stored while they fit.

    ``grid`` has ``cache``, ``lattice`` and ``places`` set; ``compute`` is as for
    :func:`from_field`, at the lattice nodes. Large masks beyond the cache's budget are not
    written out at all: they come as :class:`~.lattice.RowInterpolant`, finished where they
    are applied.
    """
    keys = [(name, place, dtype, channels_last) for place in grid.places]
    per_origin: list[Masks | tuple[RowInterpolant, ...] | None] = [
        grid.cache.get(key) for key in keys
    ]
    missing = [u for u, masks in enumerate(per_origin) if masks is None]
    if missing:
        index = torch.tensor(missing, device=grid.enc_row.device)
        nodes = compute(grid.enc_row[index], grid.enc_col[index])
        rows, cols = (axis.select(missing) for axis in grid.lattice)
        pixels = rows.position.shape[1] * cols.position.shape[1]
        nbytes = sum(math.prod(m.shape[1:3]) for m in nodes) * pixels * dtype.itemsize
        keep = grid.cache.reserve(nbytes)  # False: none of them would fit
        lattice = interpolate if keep else interpolate_once
        computed = zip(*(lattice(m, rows, cols, channels_last) for m in nodes), strict=True)
        for u, masks in zip(missing, computed, strict=True):
            masks = tuple(m.to(dtype) for m in masks)
            if keep and grid.cache.reserve(sum(m.nbytes for m in masks)):
                # stored on their own: a view would keep the whole batch's tensor
                masks = tuple(m.clone() if _shares_storage(m) else m for m in masks)
                grid.cache.put(keys[u], masks)
            per_origin[u] = masks
    return grid.per_tile(per_origin)


def _shares_storage(t: torch.Tensor) -> bool:
    """Whether ``t`` is a view of a larger tensor (its storage holds more than it)."""
    return t.untyped_storage().nbytes() > t.nbytes
