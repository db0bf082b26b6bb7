"""svcode_core: the headless core of napari-svcode.

Physics simulation of computational miniature mesoscopes (CM²), the SV-CoDe network,
tiled inference, training, baselines and metrics. No Qt is imported anywhere here.
"""

from .config import ConfigError, NoiseConfig, OpticsConfig, SystemConfig, load_system
from .methods.svcode import Reconstructor
from .network import ModelConfig, SVCoDe
from .physics.cm2 import CM2Operator
from .physics.lowrank import LowRankSVOperator
from .physics.simulate import Simulator

__version__ = "0.1.0"

__all__ = [
    "CM2Operator",
    "ConfigError",
    "LowRankSVOperator",
    "ModelConfig",
    "NoiseConfig",
    "OpticsConfig",
    "Reconstructor",
    "SVCoDe",
    "Simulator",
    "SystemConfig",
    "load_system",
]
