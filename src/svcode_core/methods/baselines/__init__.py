"""Model-based baselines: LSV-ADMM and shift-invariant Wiener / Richardson–Lucy deconvolution.

The solvers (:mod:`.admm`, :mod:`.deconv`) invert the low-rank forward model directly, with
no training; :class:`BaselineReconstructor` (:mod:`.reconstructor`) runs them on raw frames
like any other method (design.md §4).
"""

from .admm import AdmmResult, AdmmSettings, LsvAdmm, settings_for
from .deconv import ShiftInvariantDeconvolution
from .reconstructor import (
    RL_ITERATIONS,
    WIENER_BALANCE,
    BaselineReconstructor,
    build_operator,
    reconstruct_with_baseline,
)

__all__ = [
    "RL_ITERATIONS",
    "WIENER_BALANCE",
    "AdmmResult",
    "AdmmSettings",
    "BaselineReconstructor",
    "LsvAdmm",
    "ShiftInvariantDeconvolution",
    "build_operator",
    "reconstruct_with_baseline",
    "settings_for",
]
