"""CoordGate: a convolution whose output is gated by a coordinate-conditioned mask.

``CoordGate(F) = M(r) ⊙ (W ∗ F)`` with ``M(r) = sigmoid(MLP(γ(r)))`` per channel. The MLP
sees only the positional encoding of the global pixel coordinates ``r = (v, u)``, so the
masks can be computed once per tile position and cached (:class:`MaskCache`).

The first MLP layer acts on the concatenation ``[γ(v), γ(u)]``, so it splits exactly into
a row term plus a column term; it is evaluated on the ``h + w`` axis samples and
broadcast, and only the output layer runs per pixel.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Hashable, Iterator
from dataclasses import dataclass

import torch
from torch import nn

__all__ = ["CoordGate", "CoordGrid", "CoordMLP", "MaskCache"]


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
            ``(B, lenses, C, h, w)`` in ``(0, 1)``.
        """
        batch, h, w = enc_row.shape[0], enc_row.shape[1], enc_col.shape[1]
        rows = torch.einsum("bhe,nke->bnkh", enc_row, self.w_row)
        cols = torch.einsum("bwe,nke->bnkw", enc_col, self.w_col)
        hidden = torch.relu(rows.unsqueeze(-1) + cols.unsqueeze(-2) + self.b_hidden)
        w_out, b_out = self.w_out, self.b_out
        if channels is not None:
            w_out, b_out = w_out[:, channels], b_out[:, channels]
        logits = torch.matmul(w_out, hidden.flatten(-2)) + b_out
        return torch.sigmoid(logits).view(batch, self.lenses, -1, h, w)


class MaskCache:
    """Frozen masks keyed by (gate name, tile origin, padded size, sub-view size).

    Least-recently-used entries are dropped once the stored bytes exceed ``max_bytes``;
    an entry larger than the whole budget is not stored. The owner calls
    :meth:`check_weights` before each use so that changed MLP weights drop everything.
    """

    def __init__(self, max_bytes: int) -> None:
        if not isinstance(max_bytes, int) or max_bytes < 0:
            raise ValueError(f"max_bytes must be a non-negative integer, got {max_bytes!r}")
        self.max_bytes = max_bytes
        self._entries: OrderedDict[Hashable, torch.Tensor] = OrderedDict()
        self._bytes = 0
        self._weights_key: Hashable = None
        self.hits = 0
        self.misses = 0

    def check_weights(self, key: Hashable) -> None:
        """Drop every entry if ``key`` (a fingerprint of the MLP weights) changed."""
        if key != self._weights_key:
            self.clear()
            self._weights_key = key

    def clear(self) -> None:
        """Drop every entry (the hit and miss counters are kept)."""
        self._entries.clear()
        self._bytes = 0

    def get(self, key: Hashable) -> torch.Tensor | None:
        """The entry for ``key`` (marked most recently used), or ``None``."""
        mask = self._entries.get(key)
        if mask is None:
            self.misses += 1
            return None
        self.hits += 1
        self._entries.move_to_end(key)
        return mask

    def put(self, key: Hashable, mask: torch.Tensor) -> None:
        """Store ``mask`` (detached, not copied), evicting least recently used entries."""
        size = mask.numel() * mask.element_size()
        if size > self.max_bytes:
            return
        old = self._entries.pop(key, None)
        if old is not None:
            self._bytes -= old.numel() * old.element_size()
        self._entries[key] = mask.detach()
        self._bytes += size
        while self._bytes > self.max_bytes:
            _, dropped = self._entries.popitem(last=False)
            self._bytes -= dropped.numel() * dropped.element_size()

    def info(self) -> dict[str, int]:
        """``entries``, ``bytes``, ``max_bytes``, ``hits`` and ``misses``."""
        return {
            "entries": len(self._entries),
            "bytes": self._bytes,
            "max_bytes": self.max_bytes,
            "hits": self.hits,
            "misses": self.misses,
        }


@dataclass
class CoordGrid:
    """Coordinates of a batch of tiles at one U-Net level.

    Attributes
    ----------
    enc_row, enc_col : torch.Tensor
        Positional encodings ``(B, h, E)`` and ``(B, w, E)``.
    keys : tuple
        One hashable per batch element identifying its tile (origin, padded size, ``S``).
    cache : MaskCache or None
        Where masks are looked up; ``None`` computes them every time.
    """

    enc_row: torch.Tensor
    enc_col: torch.Tensor
    keys: tuple[Hashable, ...]
    cache: MaskCache | None = None

    @property
    def batch(self) -> int:
        """Number of tiles."""
        return self.enc_row.shape[0]


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
        self.cache_name = ""  # set by the owning model: the key prefix in the mask cache

    def forward(self, x: torch.Tensor, grid: CoordGrid | None) -> torch.Tensor:
        """``M(r) ⊙ conv(x)``; ``x`` is ``(B·V, C, h, w)`` with ``V`` views per tile."""
        y = self.conv(x)
        if self.mlp is None:
            return y
        if grid is None:
            raise ValueError("a CoordGate with a mask needs the tile coordinates")
        batch = grid.batch
        shape = (batch, y.shape[0] // batch, *y.shape[1:])
        if grid.cache is not None and not torch.is_grad_enabled():
            masks = list(self._cached_masks(grid))
            if all(m is masks[0] for m in masks):
                y.view(shape).mul_(masks[0])
            else:
                y5 = y.view(shape)
                for b, mask in enumerate(masks):
                    y5[b].mul_(mask)
            return y
        mask = self.masks(grid.enc_row, grid.enc_col)
        return (y.view(shape) * mask.to(y.dtype)).view_as(y)

    def masks(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor, channels: slice | None = None
    ) -> torch.Tensor:
        """Masks ``(B, lenses, C, h, w)``, computed in the MLP's dtype without autocast."""
        if self.mlp is None:
            raise ValueError("this layer has no coordinate mask (coord_gate=False)")
        dtype = self.mlp.w_out.dtype
        with torch.autocast(enc_row.device.type, enabled=False):
            return self.mlp(enc_row.to(dtype), enc_col.to(dtype), channels)

    def _cached_masks(self, grid: CoordGrid) -> Iterator[torch.Tensor]:
        computed: dict[Hashable, torch.Tensor] = {}
        for b, tile in enumerate(grid.keys):
            if tile in computed:
                yield computed[tile]
                continue
            key = (self.cache_name, tile)
            mask = grid.cache.get(key)
            if mask is None:
                mask = self.masks(grid.enc_row[b : b + 1], grid.enc_col[b : b + 1])[0]
                grid.cache.put(key, mask)
            computed[tile] = mask
            yield mask
