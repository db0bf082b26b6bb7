"""The SV-CoDe network: CoordGate, CoDe blocks, Demixing-Net, Recon-Net.

Model files (safetensors weights with their configurations) are read and written by
:mod:`svcode_core.methods.model_file`."""

from .blocks import CoDeBlock, LayerNorm2d, SimpleChannelAttention, SimpleGate, ViewFusion
from .config import PE_SCHEMES, ModelConfig
from .coordgate import CoordGate, CoordGrid, CoordMLP, MaskCache
from .encoding import encoding_size, frequencies, level_coordinates, positional_encoding
from .models import DemixNet, MaskLayer, ReconNet, SVCoDe, UNet, with_lens_context

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
