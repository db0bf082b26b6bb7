"""SV-CoDe as the paper draws it: CoordGate, CoDe block, U-Net, the two stages, the model.

Every model takes the nine stacked sub-view tiles ``(B, 9, H, W)`` (``(B, 9 k, H, W)``,
lens-major, for a demixing stage with ``k`` crops per lens: ``ModelConfig.lens_context``),
the integer ``(row, col)`` origin of each tile inside its ``S × S`` sub-view, and ``S``.
Pixel ``(i, j)`` of a tile sits at the normalised coordinate ``2(origin + (i, j))/(S-1) - 1``.
Inputs of any size are zero-padded at the bottom and right to a multiple of the U-Net
stride (the coordinates continue over the padding) and the outputs are cropped back.

The classes here state the formula. Each call asks a mask provider (:mod:`.masks`) for
each block's masks. By default that is :class:`~.fast.FastMasks`, whose folded, cached or
lattice-interpolated masks run the same formula rearranged for speed (:mod:`.fast`);
:mod:`.base` holds input checks, the mask cache and the sizes tiled inference needs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ..config import N_LENSES
from .base import TiledModel, set_pooling
from .blocks import LayerNorm2d, SimpleChannelAttention, SimpleGate, ViewFusion
from .config import ModelConfig
from .encoding import encoding_size
from .fast import FoldedMasks
from .masks import MaskProvider

__all__ = ["CoDeBlock", "CoordGate", "CoordMLP", "DemixNet", "ReconNet", "SVCoDe", "UNet"]


class CoordMLP(nn.Module):
    """The mask ``M(v, u) = sigmoid(W₂ relu(W₁ [γ(v), γ(u)] + b₁) + b₂)`` of ``channels``
    channels from ``axis_features`` encoding features per axis, one MLP per lens (or one
    for all, ``lenses=1``). ``W₁`` acts on the concatenated row and column encodings, so
    it splits exactly into a row term plus a column term, evaluated on the ``h + w`` axis
    samples and broadcast: only the output layer runs per pixel."""

    def __init__(self, axis_features: int, hidden: int, channels: int, lenses: int = 1) -> None:
        super().__init__()
        self.lenses, self.channels = lenses, channels
        self.w_row = nn.Parameter(torch.empty(lenses, hidden, axis_features))
        self.w_col = nn.Parameter(torch.empty(lenses, hidden, axis_features))
        self.b_hidden = nn.Parameter(torch.empty(lenses, hidden, 1, 1))
        self.w_out = nn.Parameter(torch.empty(lenses, channels, hidden))
        self.b_out = nn.Parameter(torch.empty(lenses, channels, 1))
        fan_in = 2 * axis_features, 2 * axis_features, 2 * axis_features, hidden, hidden
        for weight, n in zip(self.parameters(), fan_in, strict=True):
            nn.init.uniform_(weight, -1.0 / math.sqrt(n), 1.0 / math.sqrt(n))  # as nn.Linear

    def forward(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor, channels: slice | None = None
    ) -> torch.Tensor:
        """Masks ``(B, lenses, C, h, w)`` in ``(0, 1)``, channels varying fastest in memory,
        at encodings ``(B, h, E)`` and ``(B, w, E)``; ``channels`` selects mask channels."""
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


class CoordGate(nn.Module):
    """``M(r) ⊙ (W ∗ x)``: a convolution gated by a coordinate mask, one value per output
    channel and pixel. ``mlp_hidden=None`` builds no MLP: the plain convolution
    (``coord_gate=False``). The convolution is zero padded by ``kernel_size // 2``; the
    other parameters are those of :class:`CoordMLP` and ``nn.Conv2d``."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 1, groups: int = 1,
                 axis_features: int = 8, mlp_hidden: int | None = 64,
                 lenses: int = 1) -> None:  # fmt: skip
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2,
                              groups=groups)  # fmt: skip
        self.mlp = None
        if mlp_hidden is not None:
            self.mlp = CoordMLP(axis_features, mlp_hidden, out_channels, lenses)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``M ⊙ conv(x)``: ``x`` ``(B·V, C_in, h, w)`` with ``V`` views per tile, ``mask``
        ``(B, lenses, C, h, w)`` with ``lenses`` ``V`` or 1 (one mask for every view)."""
        y = self.conv(x)
        if self.mlp is None:
            return y
        if mask is None:
            raise ValueError("a CoordGate with a mask MLP needs the mask of its tiles")
        return (y.unflatten(0, (mask.shape[0], -1)) * mask.to(y.dtype)).flatten(0, 1)

    def masks(
        self, enc_row: torch.Tensor, enc_col: torch.Tensor, channels: slice | None = None
    ) -> torch.Tensor:
        """``M`` at encodings ``(B, h, E)``, ``(B, w, E)``: ``(B, lenses, C, h, w)``, in the
        MLP's dtype whatever autocast says (the masks are computed once, then reused)."""
        if self.mlp is None:
            raise ValueError("this layer has no coordinate mask (coord_gate=False)")
        dtype = self.mlp.w_out.dtype
        with torch.autocast(enc_row.device.type, enabled=False):
            return self.mlp(enc_row.to(dtype), enc_col.to(dtype), channels)


class CoDeBlock(nn.Module):
    """A NAFNet block in which every convolution is a :class:`CoordGate`::

        z   = SimpleGate(M₂ ⊙ conv2(M₁ ⊙ conv1(LN(x))))
        y   = x + β ⊙ M₃ ⊙ conv3(SCA(z))
        out = y + γ ⊙ M₅ ⊙ conv5(SimpleGate(M₄ ⊙ conv4(LN(y))))

    ``β`` and ``γ`` start at zero; ``c = channels`` features, ``2c`` out of conv1, conv2,
    conv4. ``mlp_hidden=None`` builds a plain NAFBlock; ``lenses`` as in :class:`CoordMLP`.
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
        self.conv2 = gate(2 * c, 2 * c, 3, groups=2 * c)  # depthwise
        self.gate = SimpleGate()
        self.sca = SimpleChannelAttention(c)
        self.conv3 = gate(c, c)
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.norm2 = LayerNorm2d(c)
        self.conv4 = gate(c, 2 * c)
        self.conv5 = gate(c, c)
        self.gamma = nn.Parameter(torch.zeros(1, c, 1, 1))

    def forward(self, x: torch.Tensor, masks: Sequence | FoldedMasks | None = None) -> torch.Tensor:
        """``masks``: M₁ … M₅ (``None`` without coordinate gates), or the fast route's
        :class:`~.fast.FoldedMasks`, which runs this formula rearranged."""
        if isinstance(masks, FoldedMasks):
            return masks.run(self, x)
        m1, m2, m3, m4, m5 = (None,) * 5 if masks is None else masks
        z = self.gate(self.conv2(self.conv1(self.norm1(x), m1), m2))
        y = torch.addcmul(x, self.beta, self.conv3(self.sca(z), m3))
        z = self.gate(self.conv4(self.norm2(y), m4))
        return torch.addcmul(y, self.gamma, self.conv5(z, m5))


def _block(channels: int, config: ModelConfig, lenses: int = 1) -> CoDeBlock:
    hidden = config.mlp_hidden if config.coord_gate else None
    features = encoding_size(config.pe_bands, config.positional_encoding)
    return CoDeBlock(channels, features, hidden, lenses)


def _blocks(count: int, channels: int, config: ModelConfig) -> nn.ModuleList:
    return nn.ModuleList(_block(channels, config) for _ in range(count))


class UNet(nn.Module):
    """NAFNet-style encoder–decoder of CoDe blocks with additive skips.

    Level ``k`` has ``width · 2^k`` channels (at most ``max_width``); down-sampling is a
    2×2 stride-2 convolution, up-sampling a 1×1 convolution and a pixel shuffle.
    """

    def __init__(self, config: ModelConfig, enc_blocks: Sequence[int], middle_blocks: int,
                 dec_blocks: Sequence[int]) -> None:  # fmt: skip
        super().__init__()
        self.levels = len(enc_blocks)
        widths = [config.width * 2**k for k in range(self.levels + 1)]
        if config.max_width:
            widths = [min(w, config.max_width) for w in widths]
        self.encoders = nn.ModuleList(
            _blocks(n, widths[k], config) for k, n in enumerate(enc_blocks)
        )
        self.downs = nn.ModuleList(
            nn.Conv2d(widths[k], widths[k + 1], 2, stride=2) for k in range(self.levels)
        )
        self.middle = _blocks(middle_blocks, widths[-1], config)
        self.ups = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(widths[k + 1], 4 * widths[k], 1, bias=False), nn.PixelShuffle(2)
            )
            for k in range(self.levels)
        )
        self.decoders = nn.ModuleList(
            _blocks(n, widths[k], config) for k, n in enumerate(dec_blocks)
        )

    def forward(self, x: torch.Tensor, masks: MaskProvider | None = None) -> torch.Tensor:
        """``x`` ``(B, width, H, W)``, ``H`` and ``W`` divisible by ``2**levels``; ``masks``
        a mask provider (:mod:`.masks`), ``None`` without coordinate gates."""

        def run(blocks: nn.ModuleList, x: torch.Tensor, level: int) -> torch.Tensor:
            for block in blocks:
                x = block(x, None if masks is None else masks(block, level))
            return x

        skips = []
        for level, (blocks, down) in enumerate(zip(self.encoders, self.downs, strict=True)):
            x = run(blocks, x, level)
            skips.append(x)
            x = down(x)
        x = run(self.middle, x, self.levels)
        for level in reversed(range(self.levels)):
            x = run(self.decoders[level], self.ups[level](x) + skips[level], level)
        return x

    def named_blocks(self) -> list[tuple[str, CoDeBlock, int]]:
        """``(name, block, level)`` for every CoDe block, names like ``enc0.0``."""
        out = []
        for tag, groups in (("enc", self.encoders), ("dec", self.decoders)):
            for level, blocks in enumerate(groups):
                out += [(f"{tag}{level}.{i}", b, level) for i, b in enumerate(blocks)]
        return out + [(f"middle.{i}", b, self.levels) for i, b in enumerate(self.middle)]


class _ViewNet(nn.Module):
    """One stage: per view a 3×3 convolution to ``view_width`` channels and the
    view-dependent CoDe block (shared convolutions, a mask MLP per lens), the views fused
    into ``width`` channels (:class:`~.blocks.ViewFusion`), the U-Net, a 3×3 convolution
    and the output activation (:attr:`ModelConfig.output`). With
    :attr:`ModelConfig.pixel_unshuffle` ``f > 1`` all of it runs on a grid ``f`` times
    coarser: the views enter as ``f²`` channels per view and the output leaves by a pixel
    shuffle."""

    stage = ""

    def __init__(self, config: ModelConfig, out_channels: int, enc_blocks: Sequence[int],
                 middle_blocks: int, dec_blocks: Sequence[int]) -> None:  # fmt: skip
        super().__init__()
        self.config = config.validate()
        lenses = N_LENSES if config.lens_specific_first_block else 1
        self.views_per_lens = config.views_per_lens if self.stage == "demix" else 1
        self.unshuffle = config.pixel_unshuffle
        inputs = self.views_per_lens * self.unshuffle**2  # channels per lens
        if self.views_per_lens == 1:  # one convolution shared by the nine views
            self.intro = nn.Conv2d(inputs, config.view_width, 3, padding=1)
        else:  # each lens combines its own crops: which of them matter depends on the lens
            crops, width = N_LENSES * inputs, N_LENSES * config.view_width
            self.intro = nn.Conv2d(crops, width, 3, padding=1, groups=N_LENSES)
        self.view_block = _block(config.view_width, config, lenses)
        self.fusion = ViewFusion(N_LENSES, config.view_width, config.width)
        self.unet = UNet(config, enc_blocks, middle_blocks, dec_blocks)
        self.ending = nn.Conv2d(config.width, out_channels * self.unshuffle**2, 3, padding=1)
        set_pooling(self, config.pool_window)
        for conv in self.modules():  # every padded convolution extends its input alike
            if isinstance(conv, nn.Conv2d) and any(conv.padding):
                conv.padding_mode = config.padding

    @property
    def levels(self) -> int:
        """Down-sampling steps of the U-Net (the stride is ``2**levels``)."""
        return self.unet.levels

    def run(self, views: torch.Tensor, masks: MaskProvider | None) -> torch.Tensor:
        """The stage on padded views ``(B, 9 · views_per_lens, H, W)``; ``masks`` a mask
        provider (:mod:`.masks`)."""
        if self.unshuffle > 1:  # each view's pixels to channels, lens-major order kept
            views = F.pixel_unshuffle(views, self.unshuffle)
        batch, channels, h, w = views.shape
        # the view block's few channels per lens run channels first (see LayerNorm2d)
        if self.views_per_lens == 1:
            x = self.intro(views.reshape(batch * N_LENSES, channels // N_LENSES, h, w).contiguous())
        else:
            x = self.intro(views.contiguous()).reshape(batch * N_LENSES, -1, h, w)
        x = self.view_block(x, None if masks is None else masks(self.view_block, 0))
        x = x.reshape(batch, -1, h, w).contiguous(memory_format=torch.channels_last)
        out = self.ending(self.unet(self.fusion(x), masks))
        if self.unshuffle > 1:
            out = F.pixel_shuffle(out, self.unshuffle)
        if self.config.output == "sigmoid":
            return torch.sigmoid(out)
        return out if self.training else out.clamp_min(0)

    def named_blocks(self) -> list[tuple[str, CoDeBlock, int]]:
        """``(name, block, level)`` for every CoDe block of this stage."""
        return [("view", self.view_block, 0), *self.unet.named_blocks()]


class _Stage(_ViewNet, TiledModel):
    """One stage as a model of its own, its U-Net sized by the config's
    ``{stage}_enc_blocks``, ``{stage}_middle_blocks`` and ``{stage}_dec_blocks``."""

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
        padded, masks = self._prepare(views, origins, sub_view_size)
        return self.run(padded, masks)[..., : views.shape[-2], : views.shape[-1]]


class DemixNet(_Stage):
    """Demixing-Net: nine multiplexed sub-view tiles in, nine demixed tiles out."""

    stage = "demix"
    out_channels = N_LENSES


class ReconNet(_Stage):
    """Recon-Net: nine demixed tiles in, one tile of the object out."""

    stage = "recon"


class SVCoDe(TiledModel):
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
        """``(demixed (B, 9, H, W), reconstruction (B, 1, H, W))`` from ``views``."""
        padded, masks = self._prepare(views, origins, sub_view_size)
        demixed = self.demix.run(padded, masks)
        recon = self.recon.run(demixed, masks)
        h, w = views.shape[-2:]
        return demixed[..., :h, :w], recon[..., :h, :w]
