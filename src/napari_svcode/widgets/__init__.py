"""Dock widgets: Calibration, Reconstruct, Coordinate masks, Simulate."""

from .calibration import CalibrationWidget
from .masks import MaskWidget
from .reconstruct import ReconstructWidget, reconstruct_frames
from .simulate import SimulateWidget

__all__ = [
    "CalibrationWidget",
    "MaskWidget",
    "ReconstructWidget",
    "SimulateWidget",
    "reconstruct_frames",
]
