"""Every reconstruction method by name: SV-CoDe, the model-based and the learned baselines.

One entry point per task, so a front end (the command line, the napari plugin, the
benchmark, a notebook) never repeats the dispatch over methods:

* :func:`build_reconstructor` makes the reconstructor of a named method;
* :class:`MethodSpec` is the same as a picklable recipe (for the streaming and dask back
  ends, which build the reconstructor where the frames are reconstructed);
* :func:`iter_method` runs any of them frame by frame, yielding
  :class:`~svcode_core.methods.base.FrameProgress` (tile by tile for SV-CoDe);
* :func:`reconstruct_with_method` reconstructs a frame or a stack in one call;
* :func:`reconstructor_defaults` gives the tiling defaults of
  :class:`~svcode_core.methods.svcode.Reconstructor` (read from its signature);
* :func:`cli_arguments` gives the ``svcode reconstruct`` flags of a method and options.

The names, the class of each method and the table of its options come from
:mod:`svcode_core.methods.registry`.
"""

from __future__ import annotations

import inspect
from collections.abc import Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..config import SystemConfig
from . import registry
from .base import BaseReconstructor, FrameProgress, ReconstructionResult
from .registry import LEARNED_METHODS, METHOD_TITLES, METHODS, MODEL_BASED_METHODS, check_method
from .svcode import Reconstructor

__all__ = [
    "LEARNED_METHODS",
    "METHODS",
    "METHOD_TITLES",
    "MODEL_BASED_METHODS",
    "MethodSpec",
    "build_reconstructor",
    "cli_arguments",
    "iter_method",
    "reconstruct_with_method",
    "reconstructor_defaults",
]

#: the options of every method, besides those of its table, and their flags
_COMMON_FLAGS = {"weights": "--weights", "device": "--device", "precision": "--precision"}


def reconstructor_defaults() -> dict[str, Any]:
    """Keyword defaults of :class:`~svcode_core.methods.svcode.Reconstructor` (``tile_size``,
    ``stride``, ``batch_size``, ``skip_empty``, ...), read from its signature."""
    parameters = inspect.signature(Reconstructor.__init__).parameters.values()
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def build_reconstructor(
    method: str,
    system: SystemConfig | None,
    weights: str | Path | None = None,
    model: torch.nn.Module | None = None,
    **options: Any,
) -> BaseReconstructor:
    """The reconstructor of ``method`` for ``system``.

    Parameters
    ----------
    method : str
        One of :data:`~svcode_core.methods.registry.METHODS`.
    system : SystemConfig or None
        The instrument; ``None`` takes the one stored in ``weights`` (not for the
        model-based methods, which have no model file).
    weights : path, optional
        Model file: SV-CoDe (default: the bundled model of ``system``) or a learned baseline
        (required).
    model : torch.nn.Module, optional
        SV-CoDe or a learned baseline: an already built model, used instead of ``weights``.
    **options
        Keyword arguments of the method's reconstructor: ``device``, ``precision`` and
        :class:`~svcode_core.methods.svcode.Reconstructor`'s tiling options (SV-CoDe), the
        method's options of :class:`~svcode_core.methods.baselines.BaselineReconstructor`.

    Raises
    ------
    ValueError
        Unknown method, options or weights missing for a learned baseline.
    FileNotFoundError
        No bundled SV-CoDe model for ``system``.
    """
    cls = registry.reconstructor_class(method)  # the registry's class of the method
    return cls.build(method, system, weights, model, **options)


@dataclass(frozen=True)
class MethodSpec:
    """Picklable recipe of a reconstructor: :func:`build_reconstructor` when called.

    Attributes
    ----------
    method : str
        One of :data:`~svcode_core.methods.registry.METHODS`.
    system : SystemConfig or None
        The instrument; ``None`` takes the one stored with the model.
    weights : str or None
        Path of the model file (SV-CoDe, learned baselines).
    options : dict
        Keyword options of the method's reconstructor (device, precision, tile_size ...).
    """

    method: str
    system: SystemConfig | None = None
    weights: str | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_method(self.method)

    def __call__(self) -> BaseReconstructor:
        return build_reconstructor(self.method, self.system, self.weights, **self.options)

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description (recorded in outputs and resume state).

        Examples
        --------
        >>> MethodSpec("rl", None, options={"iterations": 5}).describe()
        {'method': 'rl', 'iterations': 5}
        """
        weights = {} if self.weights is None else {"weights": str(Path(self.weights).resolve())}
        return {"method": self.method, **weights, **self.options}


def iter_method(
    reconstructor: BaseReconstructor, frames: Any, return_views: bool = False
) -> Generator[FrameProgress, None, ReconstructionResult]:
    """Reconstruct a frame or a stack with any reconstructor, yielding progress.

    SV-CoDe yields after every batch of tiles, LSV-ADMM and RL before each frame and after
    every iteration (``tiles_done`` counting iterations), the others once before each frame
    (``tiles_done`` 0 of 1). Closing the generator stops it at the next yield. The result
    is the generator's return value, shaped like that of ``reconstructor.reconstruct``.
    """
    return (yield from reconstructor.iter_reconstruct(frames, return_views))


def reconstruct_with_method(
    method: str,
    frames: Any,
    system: SystemConfig,
    return_views: bool = False,
    **options: Any,
) -> ReconstructionResult:
    """Reconstruct a raw frame ``(H, W)`` or a stack ``(T, H, W)`` with a named method.

    ``options`` are those of :func:`build_reconstructor` (``weights``, ``device``, ...).

    Examples
    --------
    >>> import numpy as np
    >>> from svcode_core.config import SystemConfig
    >>> system = SystemConfig.tiny()
    >>> frame = np.full(system.sensor_shape, 0.1, dtype=np.float32)
    >>> result = reconstruct_with_method("wiener", frame, system, rank=1)
    >>> result.reconstruction.shape
    (48, 48)
    """
    reconstructor = build_reconstructor(method, system, **options)
    return reconstructor.reconstruct(frames, return_views)


def cli_arguments(method: str, weights: str | Path | None = None, **options: Any) -> list[str]:
    """The ``svcode reconstruct`` flags that select ``method`` with ``options``.

    ``options`` are named as for :func:`build_reconstructor`; ``None`` values are left out
    (the command line's default applies). The flags come from the method's table
    (:class:`~svcode_core.methods.registry.Option`).

    Examples
    --------
    >>> cli_arguments("admm", iterations=50, tv_weight=1e-3)
    ['--method', 'admm', '--iterations', '50', '--tv-weight', '0.001']
    >>> cli_arguments("svcode", skip_empty=False, mask_cache_bytes=0)
    ['--method', 'svcode', '--no-skip', '--mask-cache', '0']
    """
    table = {option.name: option for option in registry.method(method).options}
    arguments = ["--method", method]
    for name, value in {"weights": weights, **options}.items():
        if value is None:
            continue
        if name in _COMMON_FLAGS:
            arguments += [_COMMON_FLAGS[name], str(value)]
        elif name in table:
            arguments += table[name].to_flag(value)
        else:
            raise ValueError(f"{method}: option {name!r} has no `svcode reconstruct` flag")
    return arguments
