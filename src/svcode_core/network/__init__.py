"""The SV-CoDe network: CoordGate, CoDe blocks, Demixing-Net, Recon-Net.

:mod:`.models` states the architecture; the masks of each call come from a provider of
:mod:`.masks` (the fast one, :mod:`.fast`, by default, with :mod:`.cache` and
:mod:`.lattice`), and :mod:`.base` holds what tiled inference needs beyond the formula.
Model files (safetensors weights with their configurations) are read and written by
:mod:`svcode_core.methods.model_file`."""

from .base import MaskLayer
from .blocks import LayerNorm2d, SimpleChannelAttention, SimpleGate, ViewFusion
from .cache import MaskCache
from .config import PE_SCHEMES, ModelConfig
from .encoding import encoding_size, frequencies, level_coordinates, positional_encoding
from .lens_context import with_lens_context
from .masks import CoordGrid
from .models import (
    CoDeBlock,
    CoordGate,
    CoordMLP,
    DemixNet,
    ReconNet,
    SVCoDe,
    UNet,
)

__all__ = [
    "PE_SCHEMES",
    "CoDeBlock",
    "CoordGate",
    "CoordGrid",
    "CoordMLP",
    "DemixNet",
    "LayerNorm2d",
    "MaskCache",
    "MaskLayer",
    "ModelConfig",
    "ReconNet",
    "SVCoDe",
    "SimpleChannelAttention",
    "SimpleGate",
    "UNet",
    "ViewFusion",
    "encoding_size",
    "frequencies",
    "level_coordinates",
    "positional_encoding",
    "with_lens_context",
]
