"""Every reconstruction method and model architecture by name: the one list of them.

The command line (``--method``), the napari plugin, training, the benchmark, the footprint
measurement and the model files all take their names from here, so a method is added in
one place. This module imports nothing of the package: any module may use it.

Examples
--------
>>> METHODS
('svcode', 'admm', 'wiener', 'rl', 'multiwiener', 'fouriernet')
>>> method("fouriernet").architecture, method("fouriernet").precisions
('SVFourierNet', ('fp32', 'bf16'))
>>> method_of_architecture("MultiWienerNet")
'multiwiener'
>>> method("admm").defaults["iterations"], method("rl").defaults["iterations"]
(50, 10)
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = [
    "ARCHITECTURES",
    "DEFAULT_RANK",
    "LEARNED_METHODS",
    "METHODS",
    "METHOD_TITLES",
    "MODEL_BASED_METHODS",
    "OPTION_FLAGS",
    "TRAINABLE_METHODS",
    "Method",
    "check_method",
    "method",
    "method_of_architecture",
]

SVCODE = "svcode"
MODEL_BASED = "model-based"
LEARNED = "learned"


@dataclass(frozen=True)
class Method:
    """One reconstruction method.

    Attributes
    ----------
    name : str
        Its ``--method`` name.
    title : str
        For people (menus, reports).
    label : str
        Short name in tables and figures.
    family : {"svcode", "model-based", "learned"}
        SV-CoDe; solvers of the forward model (no training); trained baselines.
    precisions : tuple of str
        The ``precision`` values it accepts, the default first.
    options : tuple of str
        Its own keyword options, besides ``device``, ``precision`` and (SV-CoDe) the
        tiling options.
    architecture : str or None
        The model class its model files hold (trained methods).
    defaults : mapping
        The value each of its ``options`` takes when not given (those without one here
        default elsewhere: ``memory_budget`` to the operator's 1 GiB). The one place these
        are defined: the solvers, ``svcode reconstruct`` and the plugin read them here.
        ``rank`` is a ceiling: the system's own ``K`` when that is smaller.
    """

    name: str
    title: str
    label: str
    family: str
    precisions: tuple[str, ...]
    options: tuple[str, ...] = ()
    architecture: str | None = None
    defaults: Mapping[str, Any] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "defaults", MappingProxyType(dict(self.defaults)))

    @property
    def needs_weights(self) -> bool:
        """Whether it runs from a model file (SV-CoDe falls back on a bundled one)."""
        return self.architecture is not None


#: the model-based methods' default low-rank order ``K``: at most this, the system's own
#: ``K`` when that is smaller
DEFAULT_RANK = 3

# The model-based defaults sit at the knee of the work–precision curve of the committed
# benchmark (bench/results/regimes.md, realistic regime, one CPU thread, cm2-mini):
# LSV-ADMM at K = 3, 50 iterations, λ from the frame: 28.03 dB in 11.6 s a frame, against
# 28.31 dB in 772 s at the system's K (15) and up to 200 iterations with the fixed λ;
# Wiener's balance 0.1 and Richardson–Lucy's 10 iterations score best in every regime of
# the sweep (balance 1e-3..0.1; 10 and 30 iterations), the latter at a third of the time.
_ALL = (
    Method(SVCODE, "SV-CoDe (network)", "SV-CoDe", SVCODE, ("fp32", "bf16", "fp16"),
           options=("pool_window", "refine_periphery"), architecture="SVCoDe"),
    Method("admm", "LSV-ADMM (TV)", "LSV-ADMM", MODEL_BASED, ("fp32", "fp64"),
           options=("rank", "memory_budget", "iterations", "tv_weight", "rho", "tolerance",
                    "cg_iterations"),
           defaults={"rank": DEFAULT_RANK, "iterations": 50, "tv_weight": "auto", "rho": 0.1,
                     "tolerance": 1e-4, "cg_iterations": 1}),
    Method("wiener", "Wiener (per view, fused)", "Wiener", MODEL_BASED, ("fp32", "fp64"),
           options=("rank", "memory_budget", "balance", "boundary"),
           defaults={"rank": DEFAULT_RANK, "balance": 0.1, "boundary": "reflect"}),
    Method("rl", "Richardson-Lucy (per view, fused)", "Richardson-Lucy", MODEL_BASED,
           ("fp32", "fp64"), options=("rank", "memory_budget", "iterations"),
           defaults={"rank": DEFAULT_RANK, "iterations": 10}),
    Method("multiwiener", "MultiWienerNet (learned)", "MultiWienerNet", LEARNED,
           ("fp32", "bf16"), architecture="MultiWienerNet"),
    Method("fouriernet", "SV-FourierNet (learned)", "SV-FourierNet", LEARNED,
           ("fp32", "bf16"), architecture="SVFourierNet"),
)  # fmt: skip
_BY_NAME = {entry.name: entry for entry in _ALL}

#: every method of ``svcode reconstruct --method``
METHODS: tuple[str, ...] = tuple(_BY_NAME)
MODEL_BASED_METHODS: tuple[str, ...] = tuple(m.name for m in _ALL if m.family == MODEL_BASED)
LEARNED_METHODS: tuple[str, ...] = tuple(m.name for m in _ALL if m.family == LEARNED)
#: the methods ``svcode train --method`` trains
TRAINABLE_METHODS: tuple[str, ...] = (SVCODE, *LEARNED_METHODS)
METHOD_TITLES: dict[str, str] = {m.name: m.title for m in _ALL}
#: model class stored in a model file → its method
ARCHITECTURES: dict[str, str] = {m.architecture: m.name for m in _ALL if m.architecture}

#: keyword option → its ``svcode reconstruct`` flag
OPTION_FLAGS: dict[str, str] = {
    "weights": "--weights",
    "device": "--device",
    "precision": "--precision",
    "tile_size": "--tile",
    "stride": "--stride",
    "batch_size": "--batch-size",
    "skip_empty": "--no-skip",
    "mask_cache_bytes": "--mask-cache",
    "pool_window": "--pool-window",
    "refine_periphery": "--refine-periphery",
    "rank": "--rank",
    "memory_budget": "--memory-budget",
    "iterations": "--iterations",
    "tv_weight": "--tv-weight",
    "rho": "--rho",
    "tolerance": "--tolerance",
    "cg_iterations": "--cg-iterations",
    "balance": "--wiener-balance",
    "boundary": "--wiener-boundary",
}


def check_method(name: str) -> None:
    """Raise :class:`ValueError` unless ``name`` is one of :data:`METHODS`."""
    if name not in _BY_NAME:
        raise ValueError(f"method: {name!r} is not one of {', '.join(METHODS)}")


def method(name: str) -> Method:
    """The entry of method ``name``.

    Raises
    ------
    ValueError
        For a name that is not one of :data:`METHODS`.
    """
    check_method(name)
    return _BY_NAME[name]


def method_of_architecture(architecture: str) -> str:
    """The method whose model files hold ``architecture`` (a model class name).

    Raises
    ------
    ValueError
        For a class that is no method's model (e.g. one SV-CoDe stage alone).
    """
    if architecture not in ARCHITECTURES:
        raise ValueError(f"a {architecture} is not the model of any method "
                         f"({', '.join(ARCHITECTURES)})")  # fmt: skip
    return ARCHITECTURES[architecture]
