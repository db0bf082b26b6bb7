"""Model-based baselines: LSV-ADMM and shift-invariant Wiener / Richardson–Lucy deconvolution.

The solvers (:mod:`.admm`, :mod:`.deconv`) invert the low-rank forward model directly, with
no training; :class:`BaselineReconstructor` (:mod:`.reconstructor`) runs them on raw frames
like any other method (design.md §4). Their options (defaults, bounds) are in
:mod:`~svcode_core.methods.registry`.
"""

from .admm import AdmmResult, AdmmSettings, LsvAdmm, settings_for
from .deconv import ShiftInvariantDeconvolution
from .reconstructor import (
    AdmmReconstructor,
    BaselineReconstructor,
    DeconvolutionReconstructor,
    build_operator,
    default_rank,
    reconstruct_with_baseline,
)

__all__ = [
    "AdmmReconstructor",
    "AdmmResult",
    "AdmmSettings",
    "BaselineReconstructor",
    "DeconvolutionReconstructor",
    "LsvAdmm",
    "ShiftInvariantDeconvolution",
    "build_operator",
    "default_rank",
    "reconstruct_with_baseline",
    "settings_for",
]
