"""The SV-CoDe models: the shared U-Net, Demixing-Net, Recon-Net and the joint SVCoDe.

Every model takes the nine stacked sub-view tiles ``(B, 9, H, W)`` (``(B, 81, H, W)``,
lens-major, for a demixing stage with ``ModelConfig.lens_context``), the integer
``(row, col)`` origin of each tile inside its ``S × S`` sub-view and ``S``. Pixel
coordinates are global: pixel ``(i, j)`` of a tile sits at ``2(origin + (i, j))/(S-1) - 1``.
Inputs of any size are zero-padded at the bottom and right to a multiple of the U-Net
stride (the coordinates continue over the padding) and the outputs are cropped back.
Outputs pass through a sigmoid, or are clamped at zero (``ModelConfig.output``).
Features run in the channels-last (NHWC) memory format, which makes the cm2-mini network
~1.7× faster on CPU; the math is unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ..config import DEFAULT_MEMORY_BUDGET, N_LENSES
from .blocks import CoDeBlock, ViewFusion
from .config import ModelConfig
from .coordgate import CoordGate, CoordGrid, MaskCache, MaskField
from .encoding import encoding_size, level_coordinates, positional_encoding
from .lattice import interpolate, lattice_axis

__all__ = ["DemixNet", "MaskLayer", "ReconNet", "SVCoDe", "UNet", "with_lens_context"]

DEFAULT_CACHE_BYTES = DEFAULT_MEMORY_BUDGET


class MaskLayer(NamedTuple):
    """One gated convolution: where it sits and the shape of its mask."""

    stage: str
    block: str
    layer: str
    channels: int
    lenses: int
    level: int


def _blocks(count: int, channels: int, config: ModelConfig) -> nn.ModuleList:
    hidden = config.mlp_hidden if config.coord_gate else None
    features = encoding_size(config.pe_bands, config.positional_encoding)
    return nn.ModuleList(CoDeBlock(channels, features, hidden) for _ in range(count))


def _run_blocks(blocks: nn.ModuleList, x: torch.Tensor, grid: CoordGrid | None) -> torch.Tensor:
    for block in blocks:
        x = block(x, grid)
    return x


class UNet(nn.Module):
    """NAFNet-style encoder–decoder of CoDe blocks with additive skips.

    Level ``k`` has ``width · 2^k`` channels; down-sampling is a 2×2 stride-2
    convolution, up-sampling a 1×1 convolution and a pixel shuffle.
    """

    def __init__(
        self,
        config: ModelConfig,
        enc_blocks: Sequence[int],
        middle_blocks: int,
        dec_blocks: Sequence[int],
    ) -> None:
        super().__init__()
        self.levels = len(enc_blocks)
        widths = [config.width * 2**k for k in range(self.levels + 1)]
        self.encoders = nn.ModuleList(
            _blocks(n, widths[k], config) for k, n in enumerate(enc_blocks)
        )
        self.downs = nn.ModuleList(
            nn.Conv2d(widths[k], widths[k + 1], 2, stride=2) for k in range(self.levels)
        )
        self.middle = _blocks(middle_blocks, widths[-1], config)
        self.ups = nn.ModuleList(
            nn.Sequential(nn.Conv2d(widths[k + 1], 2 * widths[k + 1], 1, bias=False),
                          nn.PixelShuffle(2))
            for k in range(self.levels)
        )
        self.decoders = nn.ModuleList(
            _blocks(n, widths[k], config) for k, n in enumerate(dec_blocks)
        )

    def forward(self, x: torch.Tensor, grids: Sequence[CoordGrid | None]) -> torch.Tensor:
        """``x`` ``(B, width, H, W)`` with ``H, W`` divisible by ``2**levels``."""
        skips = []
        for level, (blocks, down) in enumerate(zip(self.encoders, self.downs, strict=True)):
            x = _run_blocks(blocks, x, grids[level])
            skips.append(x)
            x = down(x)
        x = _run_blocks(self.middle, x, grids[self.levels])
        for level in reversed(range(self.levels)):
            x = self.ups[level](x) + skips[level]
            x = _run_blocks(self.decoders[level], x, grids[level])
        return x

    def named_blocks(self) -> list[tuple[str, CoDeBlock, int]]:
        """``(name, block, level)`` for every CoDe block, names like ``enc0.0``."""
        out = []
        for tag, groups in (("enc", self.encoders), ("dec", self.decoders)):
            for level, blocks in enumerate(groups):
                out += [(f"{tag}{level}.{i}", b, level) for i, b in enumerate(blocks)]
        out += [(f"middle.{i}", b, self.levels) for i, b in enumerate(self.middle)]
        return out


class _ViewNet(nn.Module):
    """Shared design of both stages: view-dependent CoDe block, view fusion, U-Net.

    Each view goes through a 3×3 convolution to ``view_width`` channels and the
    view-dependent CoDe block (shared convolutions, lens-specific mask MLPs); the
    features of the nine views are fused by :class:`~.blocks.ViewFusion` into ``width``
    channels for the shared U-Net, and a 3×3 convolution and the output activation
    (:attr:`ModelConfig.output`) give the output.
    """

    stage = ""

    def __init__(
        self,
        config: ModelConfig,
        out_channels: int,
        enc_blocks: Sequence[int],
        middle_blocks: int,
        dec_blocks: Sequence[int],
    ) -> None:
        super().__init__()
        self.config = config.validate()
        hidden = config.mlp_hidden if config.coord_gate else None
        features = encoding_size(config.pe_bands, config.positional_encoding)
        lenses = N_LENSES if config.lens_specific_first_block else 1
        self.views_per_lens = config.views_per_lens if self.stage == "demix" else 1
        if self.views_per_lens == 1:  # one convolution shared by the nine views
            self.intro = nn.Conv2d(1, config.view_width, 3, padding=1)
        else:  # each lens combines its own crops: which of them matter depends on the lens
            self.intro = nn.Conv2d(N_LENSES * self.views_per_lens, N_LENSES * config.view_width,
                                   3, padding=1, groups=N_LENSES)
        self.view_block = CoDeBlock(config.view_width, features, hidden, lenses)
        self.fusion = ViewFusion(N_LENSES, config.view_width, config.width)
        self.unet = UNet(config, enc_blocks, middle_blocks, dec_blocks)
        self.ending = nn.Conv2d(config.width, out_channels, 3, padding=1)
        self._set_pooling(config.pool_window)

    def _set_pooling(self, window: int) -> None:
        """Channel attention and view fusion pool over ``window`` level-0 pixels (0: the
        whole tile), on the grid of the stage's coarsest level (:func:`~.blocks.pooled_mean`)."""
        for _, block, level in self.named_blocks():
            scaled = max(window >> level, 1) if window else 0  # never 0 (whole tile) by rounding
            block.sca.window, block.sca.cell = scaled, 2 ** (self.levels - level)
        self.fusion.window, self.fusion.cell = window, 2**self.levels

    @property
    def levels(self) -> int:
        """Down-sampling steps of the U-Net (the stride is ``2**levels``)."""
        return self.unet.levels

    def run(self, views: torch.Tensor, grids: Sequence[CoordGrid | None]) -> torch.Tensor:
        """Network on padded views ``(B, 9 · views_per_lens, H, W)``; ``grids[k]`` for
        level ``k``."""
        batch, _, h, w = views.shape
        # the view block's few channels per lens run channels first (see LayerNorm2d)
        if self.views_per_lens == 1:
            x = self.intro(views.reshape(batch * N_LENSES, 1, h, w).contiguous())
        else:
            x = self.intro(views.contiguous()).reshape(batch * N_LENSES, -1, h, w)
        x = self.view_block(x, grids[0])
        x = self.fusion(_channels_last(x.reshape(batch, N_LENSES * x.shape[1], h, w)))
        out = self.ending(self.unet(x, grids))
        if self.config.output == "sigmoid":
            return torch.sigmoid(out)
        return out if self.training else out.clamp_min(0)

    def named_gates(self) -> list[tuple[MaskLayer, CoordGate]]:
        """Every gated convolution of this stage with its description."""
        out = []
        for block_name, block, level in self.named_blocks():
            for layer in ("conv1", "conv2", "conv3", "conv4", "conv5"):
                gate = getattr(block, layer)
                if gate.mlp is not None:
                    info = MaskLayer(self.stage, block_name, layer, gate.mlp.channels,
                                     gate.mlp.lenses, level)
                    out.append((info, gate))
        return out

    def named_blocks(self) -> list[tuple[str, CoDeBlock, int]]:
        """``(name, block, level)`` for every CoDe block of this stage."""
        return [("view", self.view_block, 0), *self.unet.named_blocks()]


def _field_cells(sub_view_size: int, levels: int) -> int:
    """Level-0 side of the cached mask field: pixels ``0 .. S + 2**levels - 2`` rounded up
    to the model stride, so a tile padded to the stride fits it whenever its unpadded
    part lies inside the sub-view."""
    stride = 2**levels
    return math.ceil((sub_view_size + stride - 1) / stride) * stride


def _channels_last(x: torch.Tensor) -> torch.Tensor:
    """Features run channels-last (NHWC): faster convolutions on CPU."""
    return x.contiguous(memory_format=torch.channels_last)


class _MaskedModel(nn.Module):
    """Tile coordinates, the mask cache and mask inspection for a top-level model."""

    def _stages(self) -> list[_ViewNet]:
        raise NotImplementedError

    def _setup_masks(self, config: ModelConfig) -> None:
        self.model_config = config
        self._mask_cache: MaskCache | None = None
        self._gates = {}
        self._masked_blocks: list[tuple[CoDeBlock, int]] = []
        for stage in self._stages():
            for info, gate in stage.named_gates():
                self._gates[(info.stage, info.block, info.layer)] = (info, gate)
            for name, block, level in stage.named_blocks():
                if block.conv1.mlp is not None:
                    block.cache_name = f"{stage.stage}/{name}"
                    self._masked_blocks.append((block, level))

    # ------------------------------------------------------------- mask cache
    def cache_masks(
        self, enabled: bool = True, max_bytes: int = DEFAULT_CACHE_BYTES
    ) -> _CacheSwitch:
        """Switch the mask cache on (or off); usable plainly or as a context manager.

        The cache serves only forward passes without gradient (``torch.no_grad`` or
        ``torch.inference_mode``); with gradients enabled masks are always recomputed.
        It holds one entry per CoDe block (and sub-view size and dtype): the block's
        folded masks (:meth:`~.blocks.CoDeBlock.folded_masks`) over the whole padded
        sub-view grid of its U-Net level, channels-last, in the compute dtype
        (autocast's, else the parameters'). At level ``k`` a tile whose origin is a
        multiple of ``2**k`` crops its masks from it (every tile at level 0, and every
        tile of a grid whose origins are multiples of the model stride); other tiles get
        theirs computed. A whole sub-view needs :meth:`mask_field_bytes`; with less,
        the masks that fit stay cached and the others are computed per call (see
        :class:`~.coordgate.MaskCache`). For models with masks on a lattice
        (``mask_spacing > 0``) it keeps instead each tile's interpolated masks under the
        tile's place (origin, shape, sub-view size): the frames of a recording run the same
        tiles, and reading the masks costs less than interpolating them again. Entries are
        dropped when the weights they depend on change (in-place updates, loading, dtype
        or device moves). Leaving the ``with`` block restores the previous cache.

        Examples
        --------
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
            return {"enabled": False, "entries": 0, "bytes": 0, "max_bytes": 0,
                    "hits": 0, "misses": 0}
        return {"enabled": True, **self._mask_cache.info()}

    def mask_field_bytes(self, sub_view_size: int, dtype: torch.dtype = torch.float32) -> int:
        """Bytes the mask cache needs to hold every mask for a whole ``S × S`` sub-view.

        That is the ``max_bytes`` for which tiled inference of a stack never recomputes
        a mask (with tile origins on multiples of the model stride); ``dtype`` is the
        compute dtype (the autocast dtype under autocast).
        """
        cells = _field_cells(sub_view_size, self._levels())
        return dtype.itemsize * sum(
            6 * block.beta.shape[1] * block.conv1.mlp.lenses * (cells // 2**level) ** 2
            for block, level in self._masked_blocks
        )

    def _levels(self) -> int:
        return max(stage.levels for stage in self._stages())

    def set_pool_window(self, window: int) -> None:
        """Pool channel attention and view fusion over ``window`` level-0 pixels around each
        pixel, or (0) over the whole tile: :attr:`ModelConfig.pool_window`, which this
        sets (a saved model records it). Weights and training are unaffected.

        Examples
        --------
        >>> model = SVCoDe(ModelConfig.mini())
        >>> model.set_pool_window(96)
        >>> model.model_config.pool_window
        96
        """
        self.model_config = self.model_config.replace(pool_window=window)
        for stage in self._stages():
            stage.config = stage.config.replace(pool_window=window)
            stage._set_pooling(window)

    @property
    def stride(self) -> int:
        """The model stride ``2**levels``: tile sides are padded to a multiple of it."""
        return 2 ** self._levels()

    def working_bytes_per_pixel(self, dtype: torch.dtype = torch.float32) -> int:
        """An upper estimate of the inference working memory per tile pixel.

        ``16 · (9 · view_width + width)`` values of ``dtype``: the nine views' features
        and the fused features with the temporaries of a block and the U-Net skips.
        Measured peaks (float32, one tile): ``ModelConfig.mini()`` 2.1–2.6 kB per pixel
        against 3.3 kB estimated; ``ModelConfig.reference()`` 4.7 kB against 6.7 kB.
        """
        config = self.model_config
        return dtype.itemsize * 16 * (9 * config.view_width + config.width)

    def receptive_radius(self) -> int:
        """Level-0 pixels a tile's output depends on beyond its own pixels, through the
        convolutions (each 3×3 depthwise convolution at level ``k`` reaches ``2^k``
        pixels, each down- or up-sampling ``2^k``, the first and last 3×3 convolutions
        one); channel attention averages over the whole tile, or a window around each
        pixel (``pool_window``), and is not counted."""
        radius = 0
        for stage in self._stages():
            radius += 2  # the stage's first and last 3x3 convolutions
            radius += sum(2**level for _, _, level in stage.named_blocks())
            radius += 2 * sum(2**level for level in range(stage.levels))
        return radius

    def _weights_key(self) -> Hashable:
        params = [p for _, gate in self._gates.values() for p in gate.mlp.parameters()]
        params += [p for block, _ in self._masked_blocks for p in (block.beta, block.gamma)]
        return tuple((p.data_ptr(), p._version, p.dtype, str(p.device)) for p in params)

    # ------------------------------------------------------------ coordinates
    def _grids(
        self, origins: torch.Tensor, sub_view_size: int, shape: tuple[int, int], levels: int
    ) -> list[CoordGrid | None]:
        if not self._gates:
            return [None] * (levels + 1)
        spacing = self.model_config.mask_spacing
        cache = self._mask_cache if not torch.is_grad_enabled() else None
        fields: list[MaskField | None] = [None] * (levels + 1)
        if cache is not None:
            cache.check_weights(self._weights_key())
            cache.new_call()
            if not spacing:
                fields = self._fields(origins, sub_view_size, shape, levels)
        tiles = None
        if cache is None or spacing:
            distinct, tiles = torch.unique(origins, dim=0, return_inverse=True)
            if len(distinct) == len(origins):
                tiles = None
            else:  # tiles at one origin share their masks
                origins = distinct
        if spacing:
            return [self._lattice_grid(origins, sub_view_size, shape, level, tiles, cache)
                    for level in range(levels + 1)]  # fmt: skip
        rows = level_coordinates(origins[:, 0], shape[0], sub_view_size, levels)
        cols = level_coordinates(origins[:, 1], shape[1], sub_view_size, levels)
        return [
            CoordGrid(self._encode(r), self._encode(c), cache, field, tiles)
            for r, c, field in zip(rows, cols, fields, strict=True)
        ]

    def _lattice_grid(
        self,
        origins: torch.Tensor,
        sub_view_size: int,
        shape: tuple[int, int],
        level: int,
        tiles: torch.Tensor | None,
        cache: MaskCache | None,
    ) -> CoordGrid:
        """The lattice nodes of every tile at one level (see :mod:`.lattice`); with a
        cache, each tile's interpolated masks are kept under its place."""
        spacing = self.model_config.mask_spacing
        axes = [
            lattice_axis(origins[:, axis], shape[axis] // 2**level, level, spacing, sub_view_size)
            for axis in (0, 1)
        ]
        (rows, row_axis), (cols, col_axis) = axes
        places = None
        if cache is not None:
            places = tuple((sub_view_size, level, *shape, *origin)
                           for origin in origins.tolist())  # fmt: skip
        return CoordGrid(self._encode(rows), self._encode(cols), cache=cache, tiles=tiles,
                         lattice=(row_axis, col_axis), places=places)  # fmt: skip

    def _encode(self, coords: torch.Tensor) -> torch.Tensor:
        config, param = self.model_config, next(self.parameters())
        return positional_encoding(coords, config.pe_bands, config.pe_scheme,
                                   config.positional_encoding, param.dtype).to(param.device)

    def _fields(
        self, origins: torch.Tensor, sub_view_size: int, shape: tuple[int, int], levels: int
    ) -> list[MaskField]:
        """The whole-field grid of every level and the tiles' offsets in it.

        See :func:`_field_cells` for its extent.
        """
        axis = level_coordinates(torch.zeros(1, dtype=torch.long),
                                 _field_cells(sub_view_size, levels), sub_view_size, levels)
        out = []
        for level, coords in enumerate(axis):
            step, cells = 2**level, coords.shape[1]
            offsets = tuple(
                (r // step, c // step)
                if min(r, c) >= 0 and r % step == 0 and c % step == 0
                and r + shape[0] <= cells * step and c + shape[1] <= cells * step
                else None
                for r, c in origins.tolist()
            )
            enc = self._encode(coords)
            out.append(MaskField((sub_view_size, level, cells), enc, enc, offsets))
        return out

    def _prepare(
        self, views: torch.Tensor, origins: torch.Tensor | Sequence, sub_view_size: int, levels: int
    ) -> tuple[torch.Tensor, list[CoordGrid | None]]:
        """Validate, pad to a multiple of ``2**levels`` and build the coordinate grids."""
        channels = N_LENSES * self._stages()[0].views_per_lens
        if not isinstance(views, torch.Tensor) or views.ndim != 4 or views.shape[1] != channels:
            shape = tuple(views.shape) if isinstance(views, torch.Tensor) else type(views).__name__
            raise ValueError(f"views must have shape (B, {channels}, H, W), got {shape}")
        if not views.is_floating_point():
            raise ValueError(f"views must be floating point, got {views.dtype}")
        if not torch.isfinite(views).all():
            raise ValueError("views contain NaN or Inf")
        origins = torch.as_tensor(origins, device=torch.device("cpu"))
        if origins.shape != (views.shape[0], 2) or origins.is_floating_point():
            raise ValueError(
                f"origins must be integer (row, col) of shape ({views.shape[0]}, 2), "
                f"got {origins.dtype} {tuple(origins.shape)}"
            )
        if not isinstance(sub_view_size, int) or sub_view_size < 2:
            raise ValueError(f"sub_view_size must be an integer >= 2, got {sub_view_size!r}")
        stride = 2**levels
        h, w = views.shape[-2:]
        hp, wp = math.ceil(h / stride) * stride, math.ceil(w / stride) * stride
        padded = F.pad(views, (0, wp - w, 0, hp - h))
        return padded, self._grids(origins.long(), sub_view_size, (hp, wp), levels)

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
            nodes, lattice = lattice_axis(origin, sub_view_size, 0, config.mask_spacing,
                                          sub_view_size)  # fmt: skip
            enc = self._encode(nodes)
            masks = gate.masks(enc, enc, channels)[:, lens : lens + 1]
            return interpolate(masks, lattice, lattice)[0][0].float()
        axis = level_coordinates(origin, sub_view_size, sub_view_size, 0)[0]
        enc = positional_encoding(axis, config.pe_bands, config.pe_scheme,
                                  config.positional_encoding, param.dtype).to(param.device)
        row_bytes = sub_view_size * param.shape[-1] * info.lenses * param.element_size()
        chunk = max(1, max_chunk_bytes // row_bytes)
        parts = [
            gate.masks(enc[:, start : start + chunk], enc, channels)[0, lens]
            for start in range(0, sub_view_size, chunk)
        ]
        return torch.cat(parts, dim=1).float()


class _CacheSwitch:
    """Returned by :meth:`cache_masks`; as a context manager restores the previous cache."""

    def __init__(self, model: _MaskedModel, previous: MaskCache | None) -> None:
        self._model, self._previous = model, previous

    def __enter__(self) -> _MaskedModel:
        return self._model

    def __exit__(self, *exc: object) -> None:
        self._model._mask_cache = self._previous


class _Stage(_ViewNet, _MaskedModel):
    """One stage as a model of its own; ``stage`` names its fields of :class:`ModelConfig`
    (``{stage}_enc_blocks``, ``{stage}_middle_blocks``, ``{stage}_dec_blocks``)."""

    out_channels = 1

    def __init__(self, config: ModelConfig) -> None:
        parts = ("enc", "middle", "dec")
        blocks = [getattr(config, f"{self.stage}_{part}_blocks") for part in parts]
        super().__init__(config, self.out_channels, *blocks)
        self._setup_masks(config)

    def _stages(self) -> list[_ViewNet]:
        return [self]

    def forward(
        self, views: torch.Tensor, origins: torch.Tensor | Sequence, sub_view_size: int
    ) -> torch.Tensor:
        """The stage's output ``(B, out_channels, H, W)``; see the module docstring."""
        padded, grids = self._prepare(views, origins, sub_view_size, self.levels)
        return self.run(padded, grids)[..., : views.shape[-2], : views.shape[-1]]


class DemixNet(_Stage):
    """Demixing-Net: nine multiplexed sub-view tiles in, nine demixed tiles out."""

    stage = "demix"
    out_channels = N_LENSES


class ReconNet(_Stage):
    """Recon-Net: nine demixed tiles in, one tile of the object out."""

    stage = "recon"


class SVCoDe(_MaskedModel):
    """The joint model: Demixing-Net then Recon-Net, trained end to end.

    Parameters
    ----------
    config : ModelConfig

    Examples
    --------
    >>> model = SVCoDe(ModelConfig.mini())
    >>> demixed, recon = model(torch.rand(2, 9, 40, 37), [[0, 0], [100, 48]], 384)
    >>> tuple(demixed.shape), tuple(recon.shape)
    ((2, 9, 40, 37), (2, 1, 40, 37))
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.demix = DemixNet(config)
        self.recon = ReconNet(config)
        self._setup_masks(config)

    def _stages(self) -> list[_ViewNet]:
        return [self.demix, self.recon]

    def forward(
        self, views: torch.Tensor, origins: torch.Tensor | Sequence, sub_view_size: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(demixed (B, 9, H, W), reconstruction (B, 1, H, W))`` from ``views`` ``(B, 9,
        H, W)`` (``(B, 9 k, H, W)`` with ``k`` crops per lens with ``lens_context``)."""
        levels = self._levels()
        padded, grids = self._prepare(views, origins, sub_view_size, levels)
        demixed = self.demix.run(padded, grids)
        recon = self.recon.run(demixed, grids)
        h, w = views.shape[-2:]
        return demixed[..., :h, :w], recon[..., :h, :w]


def with_lens_context(model: SVCoDe, reach: int = 1) -> SVCoDe:
    """A copy of ``model`` whose demixing stage also takes the crops up to ``reach``
    lens pitches away (:attr:`ModelConfig.lens_context`, :attr:`ModelConfig.context_reach`),
    computing exactly what ``model`` computes until it is trained further: the new inputs
    enter with zero weights. The starting point for fine-tuning a model without lens
    context, or with a shorter reach.

    Examples
    --------
    >>> plain = SVCoDe(ModelConfig.mini()).eval()
    >>> wide = with_lens_context(plain).eval()
    >>> views = torch.rand(1, 81, 16, 16)
    >>> with torch.no_grad():
    ...     before = plain(views[:, ::9], [[0, 0]], 384)[1]
    ...     after = wide(views, [[0, 0]], 384)[1]
    >>> torch.allclose(before, after, rtol=1e-5, atol=1e-6)  # float32 sums in another order
    True
    """
    config = model.model_config
    if config.lens_context and reach <= config.context_reach:
        raise ValueError(f"the model already has lens context of reach {config.context_reach}")
    wide = SVCoDe(config.replace(lens_context=True, context_reach=reach))
    state = model.state_dict()
    narrow, bias = state["demix.intro.weight"], state["demix.intro.bias"]
    if not config.lens_context:  # one first convolution shared by the nine lenses
        narrow, bias = narrow.repeat(N_LENSES, 1, 1, 1), bias.repeat(N_LENSES)
    narrow = narrow.unflatten(0, (N_LENSES, -1))  # (lens, out, crops, k, k)
    weight = narrow.new_zeros(*narrow.shape[:2], wide.demix.views_per_lens, *narrow.shape[3:])
    weight[:, :, : narrow.shape[2]] = narrow  # a shorter reach's crops come first
    state["demix.intro.weight"] = weight.flatten(0, 1)
    state["demix.intro.bias"] = bias
    wide.load_state_dict(state)
    return wide.to(next(model.parameters()).device)
