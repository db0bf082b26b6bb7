"""The learned SV baselines: MultiWienerNet and SV-FourierNet (design.md §4).

The models, their configurations and filter banks; reconstructing raw frames with a
trained one is :class:`~svcode_core.methods.learned.reconstruct.LearnedReconstructor`.
"""

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
from .models import LEARNED_MODELS, MultiWienerNet, RefinementNet, SVFourierNet

__all__ = [
    "LEARNED_MODELS",
    "FourierFilterBank",
    "FourierNetConfig",
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
