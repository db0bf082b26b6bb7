"""The network configuration: widths, depths, positional encoding and ablation switches."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any, TypeVar

from ..config import ConfigError, check_int
from ..physics.geometry import context_shifts

__all__ = ["PADDINGS", "PE_SCHEMES", "BlockConfig", "ModelConfig"]

PE_SCHEMES = ("paper", "code")
"""Frequency schemes of the positional encoding: ``"paper"`` uses ``2^k π`` (k = 0..L-1),
``"code"`` (the published implementation) uses ``0.5 π · (1..L)``."""

OUTPUTS = ("sigmoid", "linear")

PADDINGS = ("zeros", "reflect")
"""How a padded convolution extends its input past the edge: with zeros (NAFNet's) or
mirrored."""

_Config = TypeVar("_Config", bound="BlockConfig")


class BlockConfig:
    """JSON round trip of a frozen dataclass of network sizes (mixin).

    The fields named in ``block_lists`` (blocks per U-Net level) are tuples, so the
    configuration stays hashable; JSON gives lists, which are converted back.
    Subclasses define ``validate``.
    """

    block_lists: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in self.block_lists:  # JSON gives lists; keep the dataclass hashable
            value = getattr(self, name)
            if isinstance(value, list):
                object.__setattr__(self, name, tuple(value))

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of every field."""
        data = dataclasses.asdict(self)
        for name in self.block_lists:
            data[name] = list(data[name])
        return data

    def to_json(self) -> str:
        """The configuration as an indented JSON string."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls: type[_Config], data: dict[str, Any]) -> _Config:
        """Build and validate a configuration; unknown fields and bad values name the field."""
        if not isinstance(data, dict):
            raise ConfigError(f"model: expected a JSON object, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"model.{unknown[0]}: unknown field (known: {sorted(names)})")
        return cls(**data).validate()

    @classmethod
    def from_json(cls: type[_Config], text: str) -> _Config:
        """Parse a JSON string; see :meth:`from_dict`."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigError(f"model: not valid JSON ({err})") from None
        return cls.from_dict(data)


@dataclass(frozen=True)
class ModelConfig(BlockConfig):
    """Sizes and switches of the SV-CoDe network.

    Attributes
    ----------
    width : int
        Channels of the first U-Net level; level ``k`` has ``width · 2^k``, at most
        :attr:`max_width`.
    max_width : int
        ``0``: no cap. ``C > 0``: no U-Net level has more than ``C`` channels, so extra
        levels widen the receptive field (a paper-scale PSF is 4× the mini one in pixels)
        without the parameters doubling each time. Model files written before this option
        existed load with ``0``.
    pixel_unshuffle : int
        ``1``: both stages work on the sub-view's pixel grid. ``f = 2`` or ``4``: each stage
        works on a grid ``f`` times coarser, its inputs rearranged losslessly into ``f²``
        channels per pixel (pixel unshuffle) and its output back (pixel shuffle), so every
        level costs ``f²`` times less and reaches ``f`` times further: a paper-scale PSF
        (4× the mini one in pixels) then spans as many network pixels as the mini one.
        :attr:`width`, :attr:`view_width` and :attr:`pool_window` stay as they are (the
        first two per network pixel, the window in sub-view pixels); :attr:`mask_spacing`
        is in sub-view pixels. Model files written before this option existed load with
        ``1``.
    view_width : int
        Channels per view in the view-dependent first block (``9 · view_width`` in all).
    demix_enc_blocks, demix_dec_blocks : tuple of int
        CoDe blocks per encoder / decoder level of the Demixing-Net U-Net (same length;
        the length is the number of down-sampling steps).
    demix_middle_blocks : int
        CoDe blocks at the bottom of the Demixing-Net U-Net.
    recon_enc_blocks, recon_dec_blocks, recon_middle_blocks
        The same for the Recon-Net U-Net.
    pe_bands : int
        ``L``, frequency bands per axis of the positional encoding.
    pe_scheme : {"paper", "code"}
        ``"paper"``: frequencies ``2^k π``; ``"code"``: ``0.5 π (k + 1)``, k = 0..L-1.
    mlp_hidden : int
        Hidden units of each coordinate MLP (``4L → mlp_hidden → C``).
    coord_gate : bool
        ``False`` builds no MLPs and every mask is 1: a plain NAFNet of the same widths.
    positional_encoding : bool
        ``False`` feeds the raw ``(v, u)`` to the MLPs.
    lens_specific_first_block : bool
        The first (view-dependent) block has one MLP per lens; ``False`` shares one.
    mask_spacing : int
        ``0`` evaluates the mask MLPs at every pixel (exact). ``p > 0`` evaluates them on a
        lattice of nodes ``p`` level-0 pixels apart and interpolates bilinearly to the
        pixels (:mod:`.lattice`): the masks then cost about as much as one extra
        element-wise pass, and no mask cache is needed. Model files written before this
        option existed load with ``0``, as they were trained.
        :func:`~.lattice.mask_spacing_for` gives the largest spacing whose encoding
        interpolation error is within a tolerance.
    pool_window : int
        ``0``: the channel attention of every block and the view fusion pool over the whole
        tile, as in NAFNet. ``P > 0``: they pool, per pixel, over a ``P``-pixel square
        (level-0 pixels; kept inside the tile), which is what they saw while training on
        ``P``-pixel patches, so a tile larger than ``P`` (a whole sub-view) is processed as
        the patches were and tiled and whole-sub-view outputs agree
        (:func:`~.blocks.pooled_mean`). On patches of at most ``P`` pixels both are the same,
        so this is an inference setting that training leaves alone. Model files written
        before this option existed load with ``0``, as they ran.
    lens_context : bool
        ``True``: the demixing stage sees, beside each lens's sub-view, the same crop moved
        by one lens pitch towards each of its eight neighbours
        (:func:`~svcode_core.physics.geometry.context_views`; nine inputs per lens, 81
        channels, combined by a first convolution of each lens's own), so a tile also holds
        the readings that the field's edge strips need and that lie a pitch away, beyond
        the patch. ``False``: the nine sub-views, one first convolution shared by them.
        Model files written before this option existed load with ``False``.
    context_reach : int
        With :attr:`lens_context`, how many pitches left and right the crops go
        (:func:`~svcode_core.physics.geometry.context_shifts`): 1, the neighbours' places
        (9 crops per lens), or 2, also two pitches left and right (11 crops per lens), where
        the one reading of the edge strips' equations that a single lens column sees alone
        lies. Must be 1 without lens context. Model files written before this option
        existed load with 1.
    output : {"sigmoid", "linear"}
        Output activation of both stages. ``"sigmoid"`` is the published design.
        ``"linear"`` leaves the last convolution unbounded while training and clamps it
        at zero in evaluation mode: trained from scratch on dark CM² scenes, sigmoid
        outputs can saturate at zero early on and never recover (measured on
        ``cm2-mini``: every demixed view ≈ 1e-6 after one epoch), linear ones cannot.
    padding : {"zeros", "reflect"}
        How every padded convolution of both stages extends its input past the tile's
        edge: ``"zeros"`` (NAFNet's) or ``"reflect"`` (mirrored, so that the sub-view's
        border does not look like a dark object beyond it). It changes no weights. Model
        files written before this option existed load with ``"zeros"``.
    view_margin : int
        ``m > 0``: both stages run on the sub-view grid enlarged by ``m`` pixels on every
        side (each lens's crop taken ``m`` pixels past its window, tile origins from
        ``-m``), so the light that a point near the field's edge spreads past the window
        reaches the reconstruction; the ``S × S`` field is kept. The demixing targets run
        past the window alike (a dataset made with ``--view-margin``). It changes no
        weights. ``0``: the sub-views as they are. Model files written before this option
        existed load with 0.
    """

    width: int = 32
    view_width: int = 8
    demix_enc_blocks: tuple[int, ...] = (1, 1, 1, 1)
    demix_middle_blocks: int = 1
    demix_dec_blocks: tuple[int, ...] = (1, 1, 1, 1)
    recon_enc_blocks: tuple[int, ...] = (1, 1, 1)
    recon_middle_blocks: int = 1
    recon_dec_blocks: tuple[int, ...] = (1, 1, 1)
    pe_bands: int = 4
    pe_scheme: str = "code"
    mlp_hidden: int = 48
    coord_gate: bool = True
    positional_encoding: bool = True
    lens_specific_first_block: bool = True
    output: str = "sigmoid"
    mask_spacing: int = 0
    pool_window: int = 0
    lens_context: bool = False
    context_reach: int = 1
    max_width: int = 0
    pixel_unshuffle: int = 1
    padding: str = "zeros"
    view_margin: int = 0

    block_lists = ("demix_enc_blocks", "demix_dec_blocks", "recon_enc_blocks",
                   "recon_dec_blocks")  # fmt: skip

    # ------------------------------------------------------------------ presets
    @classmethod
    def reference(cls) -> ModelConfig:
        """Sizes of the published model (width 32, Demix 4 levels, Recon 3 levels), masks on
        a 48-pixel lattice (within 1 % encoding interpolation error at ``S = 2400``)."""
        return cls(mask_spacing=48).validate()

    @classmethod
    def mini(cls) -> ModelConfig:
        """A small model for the ``cm2-mini`` CPU preset (width 16, 3 + 2 levels, linear
        outputs clamped at zero, masks on an 8-pixel lattice: within 1 % encoding
        interpolation error at ``S = 384``)."""
        return cls(
            width=16,
            view_width=4,
            demix_enc_blocks=(1, 1, 1),
            demix_dec_blocks=(1, 1, 1),
            recon_enc_blocks=(1, 1),
            recon_dec_blocks=(1, 1),
            mlp_hidden=32,
            output="linear",
            mask_spacing=8,
        ).validate()

    @property
    def coarse_levels(self) -> int:
        """``log2(pixel_unshuffle)``: the level of the sub-view's grid at which the stages'
        U-Nets start (their coordinates are those of that level, :mod:`.masks`)."""
        return self.pixel_unshuffle.bit_length() - 1

    @property
    def views_per_lens(self) -> int:
        """Input crops per lens of the demixing stage: with :attr:`lens_context` 9 at
        reach 1 and 11 at reach 2, else 1."""
        return len(context_shifts(self.context_reach)) if self.lens_context else 1

    def replace(self, **changes: Any) -> ModelConfig:
        """A validated copy with some fields changed."""
        return dataclasses.replace(self, **changes).validate()

    # --------------------------------------------------------------- validation
    def validate(self) -> ModelConfig:
        """Check every field; raise :class:`~svcode_core.config.ConfigError` naming it."""
        for name in ("width", "view_width", "pe_bands", "mlp_hidden", "context_reach"):
            check_int(name, getattr(self, name), minimum=1)
        for name in ("demix_middle_blocks", "recon_middle_blocks", "mask_spacing", "pool_window",
                     "max_width", "view_margin"):
            check_int(name, getattr(self, name), minimum=0)
        for name in self.block_lists:
            value = getattr(self, name)
            if not isinstance(value, tuple) or not value:
                raise ConfigError(f"{name}: must be a non-empty list of integers, got {value!r}")
            for item in value:
                check_int(name, item, minimum=0)
        for stage in ("demix", "recon"):
            enc, dec = getattr(self, f"{stage}_enc_blocks"), getattr(self, f"{stage}_dec_blocks")
            if len(enc) != len(dec):
                raise ConfigError(
                    f"{stage}_dec_blocks: needs as many levels as {stage}_enc_blocks "
                    f"({len(enc)}), got {len(dec)}"
                )
        if self.pe_scheme not in PE_SCHEMES:
            raise ConfigError(f"pe_scheme: must be one of {PE_SCHEMES}, got {self.pe_scheme!r}")
        if self.output not in OUTPUTS:
            raise ConfigError(f"output: must be one of {OUTPUTS}, got {self.output!r}")
        if self.padding not in PADDINGS:
            raise ConfigError(f"padding: must be one of {PADDINGS}, got {self.padding!r}")
        for name in ("coord_gate", "positional_encoding", "lens_specific_first_block",
                     "lens_context"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}: must be true or false, got {getattr(self, name)!r}")
        check_int("pixel_unshuffle", self.pixel_unshuffle, minimum=1)
        if self.pixel_unshuffle not in (1, 2, 4):
            raise ConfigError(f"pixel_unshuffle: must be 1, 2 or 4, got {self.pixel_unshuffle!r}")
        if 0 < self.max_width < self.width:
            raise ConfigError(f"max_width: {self.max_width} is below width {self.width}")
        if self.context_reach != 1 and not self.lens_context:
            raise ConfigError(f"context_reach: {self.context_reach} needs lens_context")
        return self
