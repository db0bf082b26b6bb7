"""svcode_core: the headless core of napari-svcode.

Physics simulation of computational miniature mesoscopes (CM²), the SV-CoDe network,
tiled inference, training, baselines and metrics. No Qt is imported anywhere here.
"""

from .lazy import lazy_exports

#: each exported name → the module that defines it, imported on first use (PEP 562), so
#: that ``import svcode_core`` (and the ``svcode`` command's help) loads no torch
_EXPORTS = {
    "ConfigError": ".config", "NoiseConfig": ".config", "OpticsConfig": ".config",
    "SystemConfig": ".config", "load_system": ".config",
    "Reconstructor": ".methods.svcode", "ModelConfig": ".network", "SVCoDe": ".network",
    "CM2Operator": ".physics.cm2", "LowRankSVOperator": ".physics.lowrank",
    "Simulator": ".physics.simulate",
}


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


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
