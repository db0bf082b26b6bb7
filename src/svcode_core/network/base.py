"""What tiled inference asks of a model beyond its formula: input checks and padding, the
mask provider of each call, the mask cache, mask inspection and the sizes of a tile plan.

:class:`TiledModel` is the base of the models of :mod:`.models` that take tiles (the joint
:class:`~.models.SVCoDe` and each stage on its own); they define ``_stages()``.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ..config import DEFAULT_MEMORY_BUDGET, N_LENSES
from .cache import MaskCache, field_cells
from .config import ModelConfig
from .encoding import level_coordinates, positional_encoding
from .fast import FastMasks
from .lattice import interpolate, lattice_axis
from .masks import PlainMasks, coordinate_grids

__all__ = ["MaskLayer", "TiledModel", "set_pooling"]

DEFAULT_CACHE_BYTES = DEFAULT_MEMORY_BUDGET
GATES = ("conv1", "conv2", "conv3", "conv4", "conv5")


class MaskLayer(NamedTuple):
    """One gated convolution: where it sits and the shape of its mask."""

    stage: str
    block: str
    layer: str
    channels: int
    lenses: int
    level: int


class TiledModel(nn.Module):
    """Tile inputs, their masks, the mask cache and mask inspection for a top-level model.

    Attributes
    ----------
    fast_masks : bool
        ``True`` (default): blocks run on :class:`~.fast.FastMasks` (folded, cached,
        interpolated where the cache cannot serve). ``False``: on
        :class:`~.masks.PlainMasks`, gate by gate as the formula states: slower, and
        never cached; the results agree to float rounding.
    """

    def _stages(self) -> list[nn.Module]:
        raise NotImplementedError

    def _setup_masks(self, config: ModelConfig) -> None:
        self.model_config = config
        self.fast_masks = True
        self._mask_cache: MaskCache | None = None
        self._gates = {}
        self._masked_blocks: list[tuple[nn.Module, int]] = []
        self._block_names: dict[nn.Module, str] = {}
        for stage in self._stages():
            for name, block, level in stage.named_blocks():
                for layer in GATES:
                    gate = getattr(block, layer)
                    if gate.mlp is not None:
                        info = MaskLayer(
                            stage.stage, name, layer, gate.mlp.channels, gate.mlp.lenses, level
                        )
                        self._gates[(stage.stage, name, layer)] = (info, gate)
                if block.conv1.mlp is not None:
                    self._block_names[block] = f"{stage.stage}/{name}"
                    self._masked_blocks.append((block, level))

    # ----------------------------------------------------------- inputs, masks
    def _prepare(
        self, views: torch.Tensor, origins: torch.Tensor | Sequence, sub_view_size: int
    ) -> tuple[torch.Tensor, FastMasks | PlainMasks | None]:
        """Validate, pad to a multiple of the stride; the padded views and their masks."""
        channels = N_LENSES * self._stages()[0].views_per_lens
        if not isinstance(views, torch.Tensor) or views.ndim != 4 or views.shape[1] != channels:
            shape = tuple(views.shape) if isinstance(views, torch.Tensor) else type(views).__name__
            raise ValueError(f"views must have shape (B, {channels}, H, W), got {shape}")
        if not views.is_floating_point():
            raise ValueError(f"views must be floating point, got {views.dtype}")
        if views.numel() and not torch.isfinite(torch.stack(torch.aminmax(views))).all():
            raise ValueError("views contain NaN or Inf")  # one read, no mask written
        origins = torch.as_tensor(origins, device=torch.device("cpu"))
        if origins.shape != (views.shape[0], 2) or origins.is_floating_point():
            raise ValueError(
                f"origins must be integer (row, col) of shape ({views.shape[0]}, 2), "
                f"got {origins.dtype} {tuple(origins.shape)}"
            )
        if not isinstance(sub_view_size, int) or sub_view_size < 2:
            raise ValueError(f"sub_view_size must be an integer >= 2, got {sub_view_size!r}")
        h, w = views.shape[-2:]
        # mirrored padding needs 2 pixels at the coarsest level
        least = 2 * self.stride if self.model_config.padding == "reflect" else 0
        height, width = (max(n + -n % self.stride, least) for n in (h, w))
        padded = views if (height, width) == (h, w) else F.pad(views, (0, width - w, 0, height - h))
        return padded, self.masks_for(origins.long(), sub_view_size, tuple(padded.shape[-2:]))

    def masks_for(
        self, origins: torch.Tensor, sub_view_size: int, shape: tuple[int, int]
    ) -> FastMasks | PlainMasks | None:
        """The mask provider for tiles of padded ``shape`` at integer ``origins`` ``(B, 2)``
        (see :mod:`.masks`); ``None`` for a model without coordinate gates."""
        if not self._gates:
            return None
        levels, spacing = self._levels(), self.model_config.mask_spacing
        first = self.model_config.coarse_levels
        if not self.fast_masks:
            grids = coordinate_grids(
                self._encode, origins, sub_view_size, shape, levels, spacing, first=first
            )
            return PlainMasks(grids)
        cache = self._mask_cache if not torch.is_grad_enabled() else None
        if cache is not None:
            cache.check_weights(self._weights_key())
            cache.new_call()
        grids = coordinate_grids(
            self._encode, origins, sub_view_size, shape, levels, spacing, cache, first
        )
        return FastMasks(grids, self._block_names)

    def _encode(self, coords: torch.Tensor) -> torch.Tensor:
        config = self.model_config
        param = next(iter(self._gates.values()))[1].mlp.w_out  # the masks' own precision
        return positional_encoding(
            coords, config.pe_bands, config.pe_scheme, config.positional_encoding, param.dtype
        ).to(param.device)

    def _levels(self) -> int:
        return max(stage.levels for stage in self._stages())

    def _weights_key(self) -> Hashable:
        params = [p for _, gate in self._gates.values() for p in gate.mlp.parameters()]
        params += [p for block, _ in self._masked_blocks for p in (block.beta, block.gamma)]
        return tuple((p.data_ptr(), p._version, p.dtype, str(p.device)) for p in params)

    # ------------------------------------------------------------- mask cache
    def cache_masks(
        self, enabled: bool = True, max_bytes: int = DEFAULT_CACHE_BYTES
    ) -> _CacheSwitch:
        """Switch the mask cache on (or off); usable plainly or as a context manager.

        The cache serves only forward passes without gradient (``torch.no_grad`` or
        ``torch.inference_mode``) on the fast route (:attr:`fast_masks`); with gradients
        enabled masks are always recomputed. For exact masks it holds one entry per CoDe
        block (and sub-view size and dtype): the block's folded masks
        (:func:`~.fast.fold`) over the whole padded sub-view grid of its U-Net level,
        channels-last, in the compute dtype (autocast's, else the parameters'). At level
        ``k`` a tile whose origin is a multiple of ``2**k`` crops its masks from it (every
        tile at level 0, and every tile of a grid whose origins are multiples of the model
        stride); other tiles get theirs computed. A whole sub-view needs
        :meth:`mask_field_bytes`; with less, the masks that fit stay cached and the others
        are computed per call (see :class:`~.cache.MaskCache`). For models with masks on a
        lattice (``mask_spacing > 0``) it keeps instead each tile's interpolated masks
        under the tile's place (origin, shape, sub-view size). Entries are dropped when the
        weights they depend on change (in-place updates, loading, dtype or device moves).
        Leaving the ``with`` block restores the previous cache.

        Examples
        --------
        >>> from svcode_core.network import ModelConfig, SVCoDe
        >>> model = SVCoDe(ModelConfig.mini())
        >>> with model.cache_masks(max_bytes=2**28), torch.no_grad():
        ...     pass  # run the tiles of every frame here
        """
        previous = self._mask_cache
        self._mask_cache = MaskCache(max_bytes) if enabled else None
        return _CacheSwitch(self, previous)

    def mask_cache_info(self) -> dict[str, int | bool]:
        """``enabled``, ``entries``, ``bytes``, ``max_bytes``, ``hits`` and ``misses``."""
        if self._mask_cache is None:
            return {
                "enabled": False,
                "entries": 0,
                "bytes": 0,
                "max_bytes": 0,
                "hits": 0,
                "misses": 0,
            }
        return {"enabled": True, **self._mask_cache.info()}

    def mask_field_bytes(self, sub_view_size: int, dtype: torch.dtype = torch.float32) -> int:
        """Bytes the mask cache needs to hold every mask for a whole ``S × S`` sub-view.

        That is the ``max_bytes`` for which tiled inference of a stack never recomputes
        a mask (with tile origins on multiples of the model stride); ``dtype`` is the
        compute dtype (the autocast dtype under autocast).
        """
        first = self.model_config.coarse_levels
        cells = field_cells(sub_view_size, first + self._levels())
        return dtype.itemsize * sum(
            6 * block.beta.shape[1] * block.conv1.mlp.lenses * (cells // 2 ** (first + level)) ** 2
            for block, level in self._masked_blocks
        )

    # -------------------------------------------------------------- tile plans
    def set_pool_window(self, window: int) -> None:
        """Pool channel attention and view fusion over ``window`` level-0 pixels around each
        pixel, or (0) over the whole tile: :attr:`ModelConfig.pool_window`, which this
        sets (a saved model records it). Weights and training are unaffected.

        Examples
        --------
        >>> from svcode_core.network import ModelConfig, SVCoDe
        >>> model = SVCoDe(ModelConfig.mini())
        >>> model.set_pool_window(96)
        >>> model.model_config.pool_window
        96
        """
        self.model_config = self.model_config.replace(pool_window=window)
        for stage in self._stages():
            stage.config = stage.config.replace(pool_window=window)
            set_pooling(stage, window)

    @property
    def stride(self) -> int:
        """The model stride ``pixel_unshuffle · 2**levels``: tile sides are padded to a
        multiple of it."""
        return self.model_config.pixel_unshuffle * 2 ** self._levels()

    def working_bytes_per_pixel(self, dtype: torch.dtype = torch.float32) -> int:
        """An upper estimate of the inference working memory per tile pixel.

        ``16 · (9 · view_width + width)`` values of ``dtype`` per network pixel (which is
        ``pixel_unshuffle²`` tile pixels): the nine views' features and the fused features
        with the temporaries of a block and the U-Net skips; on a coarser grid also the
        full-resolution copies that the pixel (un)shuffles make. Measured peaks (float32,
        one tile): ``ModelConfig.mini()`` 2.1–2.6 kB per pixel against 3.3 kB estimated;
        ``ModelConfig.reference()`` 4.7 kB against 6.7 kB; the cm2-v2 curve's networks
        with lens context: depth 5, 1.6 kB against 3.3 kB; on a grid twice coarser
        (``depth5-f2``) 1.4 kB against 2.1 kB; four times coarser (``depth4-f4``) 1.0 kB
        against 1.3 kB.
        """
        config, f = self.model_config, self.model_config.pixel_unshuffle
        values = 16 * (9 * config.view_width + config.width) // f**2
        if f > 1:  # the crops' unshuffled copy, the demixed views' shuffles, the output
            values += 9 * config.views_per_lens + 27 + 2
        return dtype.itemsize * values

    def receptive_radius(self) -> int:
        """Sub-view pixels a tile's output depends on beyond its own pixels, through the
        convolutions (each 3×3 depthwise convolution at level ``k`` reaches ``2^k``
        network pixels, each down- or up-sampling ``2^k``, the first and last 3×3
        convolutions one; a network pixel is ``pixel_unshuffle`` sub-view pixels, whose
        block adds ``pixel_unshuffle - 1``); channel attention averages over the whole
        tile, or a window around each pixel (``pool_window``), and is not counted."""
        radius, f = 0, self.model_config.pixel_unshuffle
        for stage in self._stages():
            radius += 2 * f + f - 1  # the first and last 3x3 convolutions, the unshuffle
            radius += f * sum(2**level for _, _, level in stage.named_blocks())
            radius += 2 * f * sum(2**level for level in range(stage.levels))
        return radius

    # --------------------------------------------------------- mask inspection
    def mask_layers(self) -> list[MaskLayer]:
        """Every gated convolution (empty with ``coord_gate=False``)."""
        return [info for info, _ in self._gates.values()]

    @torch.no_grad()
    def coordinate_mask(
        self,
        stage: str,
        block: str,
        layer: str,
        sub_view_size: int,
        lens: int = 0,
        channels: int | slice | None = None,
        max_chunk_bytes: int = 1 << 27,
    ) -> torch.Tensor:
        """One layer's mask ``M(r)`` over the whole ``S × S`` sub-view, on request.

        The MLP is evaluated at the full-resolution pixel coordinates (at a down-sampled
        level the network samples the same function on the coarser grid), or on the mask
        lattice and interpolated (``ModelConfig.mask_spacing``). The conv2 and conv4
        masks act as products of their two halves; each half is shown here.

        Parameters
        ----------
        stage, block, layer : str
            A layer from :meth:`mask_layers` (e.g. ``"demix", "enc1.0", "conv2"``).
        sub_view_size : int
            ``S``.
        lens : int
            Lens of a lens-specific layer (ignored for shared ones).
        channels : int or slice, optional
            Mask channels to compute; all by default.
        max_chunk_bytes : int
            Memory bound for the hidden activations (rows are done in chunks).

        Returns
        -------
        torch.Tensor
            ``(C, S, S)`` float32 on the model's device.
        """
        key = (stage, block, layer)
        if key not in self._gates:
            raise ValueError(f"no gated layer {key}; see mask_layers()")
        info, gate = self._gates[key]
        if not 0 <= lens < N_LENSES:
            raise ValueError(f"lens must be in 0..{N_LENSES - 1}, got {lens}")
        if isinstance(channels, int):
            channels = slice(channels, channels + 1)
        config, param = self.model_config, gate.mlp.w_out
        lens = min(lens, info.lenses - 1)
        origin = torch.zeros(1, dtype=torch.long)
        if config.mask_spacing:
            nodes, lattice = lattice_axis(
                origin, sub_view_size, 0, config.mask_spacing, sub_view_size
            )
            enc = self._encode(nodes)
            masks = gate.masks(enc, enc, channels)[:, lens : lens + 1]
            return interpolate(masks, lattice, lattice)[0][0].float()
        axis = level_coordinates(origin, sub_view_size, sub_view_size, 0)[0]
        enc = positional_encoding(
            axis, config.pe_bands, config.pe_scheme, config.positional_encoding, param.dtype
        ).to(param.device)
        row_bytes = sub_view_size * param.shape[-1] * info.lenses * param.element_size()
        chunk = max(1, max_chunk_bytes // row_bytes)
        parts = [
            gate.masks(enc[:, start : start + chunk], enc, channels)[0, lens]
            for start in range(0, sub_view_size, chunk)
        ]
        return torch.cat(parts, dim=1).float()


class _CacheSwitch:
    """Returned by :meth:`~TiledModel.cache_masks`; as a context manager restores the
    previous cache."""

    def __init__(self, model: TiledModel, previous: MaskCache | None) -> None:
        self._model, self._previous = model, previous

    def __enter__(self) -> TiledModel:
        return self._model

    def __exit__(self, *exc: object) -> None:
        self._model._mask_cache = self._previous


def set_pooling(stage: nn.Module, window: int) -> None:
    """Make a stage's channel attention and view fusion pool over ``window`` sub-view
    pixels (0: the whole tile), on the grid of the stage's coarsest level
    (:func:`~.blocks.pooled_mean`)."""
    first = stage.config.coarse_levels  # the stage's level 0 is the sub-view's level `first`
    for _, block, level in stage.named_blocks():
        scaled = max(window >> (first + level), 1) if window else 0  # never 0 by rounding
        block.sca.window, block.sca.cell = scaled, 2 ** (stage.levels - level)
    stage.fusion.window = max(window >> first, 1) if window else 0
    stage.fusion.cell = 2**stage.levels
