"""The learned SV baselines of the paper: MultiWienerNet and SV-FourierNet (design.md §4)."""

from .config import FourierNetConfig, MultiWienerConfig
from .filters import (
    FourierFilterBank,
    WienerBank,
    crop_object_window,
    frame_psf_basis,
    lens_offsets,
    place_kernel,
    wiener_gain,
)
from .models import MultiWienerNet, RefinementNet, SVFourierNet
from .reconstruct import ARCHITECTURES, LearnedReconstructor, LearnedSpec

__all__ = [
    "ARCHITECTURES",
    "FourierFilterBank",
    "FourierNetConfig",
    "LearnedReconstructor",
    "LearnedSpec",
    "MultiWienerConfig",
    "MultiWienerNet",
    "RefinementNet",
    "SVFourierNet",
    "WienerBank",
    "crop_object_window",
    "frame_psf_basis",
    "lens_offsets",
    "place_kernel",
    "wiener_gain",
]
