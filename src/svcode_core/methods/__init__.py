"""Reconstruction methods: SV-CoDe, the model-based and the learned baselines.

* :mod:`.registry`: every method and architecture by name (the one list of them);
* :mod:`.base`: the contract every reconstructor keeps, the input checks and precisions;
* :mod:`.build`: a reconstructor (or a picklable recipe of one) from a method name;
* :mod:`.svcode` (with :mod:`.tiling` and :mod:`.periphery`, the refinement of its
  reconstruction's periphery), :mod:`.baselines`, :mod:`.learned`: the methods;
* :mod:`.frames`: how raw frames are checked and scaled; :mod:`.model_file`: model files.
"""

from ..lazy import lazy_exports

#: each exported name → the module that defines it, imported on first use (PEP 562), so
#: that :mod:`.registry` is imported without torch
_EXPORTS = {
    **dict.fromkeys(("BaseReconstructor", "FrameProgress", "ReconstructionResult"), ".base"),
    **dict.fromkeys(("LEARNED_METHODS", "METHOD_TITLES", "METHODS", "MODEL_BASED_METHODS",
                     "MethodSpec", "build_reconstructor", "cli_arguments", "iter_method",
                     "reconstruct_with_method", "reconstructor_defaults"), ".build"),
}


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())


__all__ = [
    "LEARNED_METHODS",
    "METHODS",
    "METHOD_TITLES",
    "MODEL_BASED_METHODS",
    "BaseReconstructor",
    "FrameProgress",
    "MethodSpec",
    "ReconstructionResult",
    "build_reconstructor",
    "cli_arguments",
    "iter_method",
    "reconstruct_with_method",
    "reconstructor_defaults",
]
