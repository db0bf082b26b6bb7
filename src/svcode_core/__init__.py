"""svcode_core: the headless core of napari-svcode.

Physics simulation of computational miniature mesoscopes (CM²), the SV-CoDe network,
tiled inference, training, baselines and metrics. No Qt is imported anywhere here.
"""

import importlib

#: each exported name → the module that defines it, imported on first use (PEP 562), so
#: that ``import svcode_core`` (and the ``svcode`` command's help) loads no torch
_EXPORTS = {
    "ConfigError": ".config", "NoiseConfig": ".config", "OpticsConfig": ".config",
    "SystemConfig": ".config", "load_system": ".config",
    "Reconstructor": ".methods.svcode", "ModelConfig": ".network", "SVCoDe": ".network",
    "CM2Operator": ".physics.cm2", "LowRankSVOperator": ".physics.lowrank",
    "Simulator": ".physics.simulate",
}


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name], __name__), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


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
