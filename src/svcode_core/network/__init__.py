"""The SV-CoDe network: CoordGate, CoDe blocks, Demixing-Net, Recon-Net and safe weights."""

from .blocks import CoDeBlock, LayerNorm2d, SimpleChannelAttention, SimpleGate, ViewFusion
from .config import PE_SCHEMES, ModelConfig
from .coordgate import CoordGate, CoordGrid, CoordMLP, MaskCache
from .encoding import encoding_size, frequencies, level_coordinates, positional_encoding
from .models import DemixNet, MaskLayer, ReconNet, SVCoDe, UNet
from .weights import load_model, read_model_metadata, save_model

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
    "load_model",
    "positional_encoding",
    "read_model_metadata",
    "save_model",
]
