"""svcode_core: the headless core of napari-svcode.

Physics simulation of computational miniature mesoscopes (CM²), the SV-CoDe network,
tiled inference, training, baselines and metrics. No Qt is imported anywhere here.
"""

from .config import ConfigError, NoiseConfig, OpticsConfig, SystemConfig, load_system

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "NoiseConfig",
    "OpticsConfig",
    "SystemConfig",
    "load_system",
]
