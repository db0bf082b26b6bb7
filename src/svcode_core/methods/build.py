"""Every reconstruction method by name: SV-CoDe, the model-based and the learned baselines.

One entry point per task, so a front end (the napari plugin, a notebook) never repeats the
dispatch over methods:

* :func:`build_reconstructor` makes the reconstructor of a named method;
* :func:`iter_method` runs any of them frame by frame, yielding
  :class:`~svcode_core.reconstruct.FrameProgress` (tile by tile for SV-CoDe);
* :func:`reconstruct_with_method` reconstructs a frame or a stack in one call;
* :func:`reconstructor_defaults` gives the tiling defaults of
  :class:`~svcode_core.reconstruct.Reconstructor` (read from its signature);
* :func:`cli_arguments` gives the ``svcode reconstruct`` flags of a method and options.
"""

from __future__ import annotations

import inspect
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .baselines import _FLAGS as BASELINE_FLAGS
from .baselines import METHOD_OPTIONS as BASELINE_OPTIONS
from .baselines import METHODS as BASELINES
from .baselines import BaselineReconstructor
from .config import SystemConfig
from .learned_baselines import ARCHITECTURES as LEARNED
from .learned_baselines import LearnedReconstructor
from .reconstruct import FrameProgress, ReconstructionResult, Reconstructor, as_frame_stack

__all__ = [
    "LEARNED_METHODS",
    "METHODS",
    "METHOD_TITLES",
    "MODEL_BASED_METHODS",
    "build_reconstructor",
    "cli_arguments",
    "iter_method",
    "reconstruct_with_method",
    "reconstructor_defaults",
]

MODEL_BASED_METHODS: tuple[str, ...] = tuple(BASELINES)
LEARNED_METHODS: tuple[str, ...] = tuple(LEARNED)
#: every method of ``svcode reconstruct --method``
METHODS: tuple[str, ...] = ("svcode", *MODEL_BASED_METHODS, *LEARNED_METHODS)
METHOD_TITLES = {
    "svcode": "SV-CoDe (network)",
    "admm": "LSV-ADMM (TV)",
    "wiener": "Wiener (per view, fused)",
    "rl": "Richardson-Lucy (per view, fused)",
    "multiwiener": "MultiWienerNet (learned)",
    "fouriernet": "SV-FourierNet (learned)",
}

AnyReconstructor = Reconstructor | BaselineReconstructor | LearnedReconstructor


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method: {method!r} is not one of {', '.join(METHODS)}")


def reconstructor_defaults() -> dict[str, Any]:
    """Keyword defaults of :class:`~svcode_core.reconstruct.Reconstructor` (``tile_size``,
    ``stride``, ``batch_size``, ``skip_empty``, ...), read from its signature."""
    parameters = inspect.signature(Reconstructor.__init__).parameters.values()
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def build_reconstructor(
    method: str,
    system: SystemConfig,
    weights: str | Path | None = None,
    model: torch.nn.Module | None = None,
    **options: Any,
) -> AnyReconstructor:
    """The reconstructor of ``method`` for ``system``.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`.
    system : SystemConfig
    weights : path, optional
        Model file: SV-CoDe (default: the bundled model of ``system``) or a learned baseline
        (required).
    model : torch.nn.Module, optional
        SV-CoDe only: an already loaded model, used instead of ``weights``.
    **options
        Keyword arguments of the method's reconstructor: ``device``, ``precision`` and
        :class:`~svcode_core.reconstruct.Reconstructor`'s tiling options (SV-CoDe), the
        method's options of :class:`~svcode_core.baselines.BaselineReconstructor`.

    Raises
    ------
    ValueError
        Unknown method, options or weights missing for a learned baseline.
    FileNotFoundError
        No bundled SV-CoDe model for ``system``.
    """
    _check_method(method)
    if method in MODEL_BASED_METHODS:
        return BaselineReconstructor(method, system, **options)
    if method in LEARNED_METHODS:
        if weights is None:
            raise ValueError(f"{METHOD_TITLES[method]} needs a trained model file: none is "
                             f"bundled; train one with `svcode train --method {method}`")
        return LearnedReconstructor.from_weights(weights, system, method, **options)
    if model is not None:
        return Reconstructor(model, system, **options)
    if weights is None:
        from .pretrained import require_bundled_weights

        weights = require_bundled_weights(system)
    return Reconstructor.from_weights(weights, system, **options)


def iter_method(
    reconstructor: AnyReconstructor, frames: Any, return_views: bool = False
) -> Generator[FrameProgress, None, ReconstructionResult]:
    """Reconstruct a frame or a stack with any reconstructor, yielding progress.

    SV-CoDe yields after every batch of tiles; the other methods once before each frame
    (``tiles_done`` 0 of 1). Closing the generator stops it at the next yield. The result
    is the generator's return value, shaped like that of ``reconstructor.reconstruct``.
    """
    if isinstance(reconstructor, Reconstructor):
        return (yield from reconstructor.iter_reconstruct(frames, return_views))
    stack = as_frame_stack(frames)
    results = []
    for index, frame in enumerate(stack):
        yield FrameProgress(index, len(stack), 0, 1)
        results.append(reconstructor.reconstruct(frame, return_views))
    recon = np.stack([result.reconstruction for result in results])
    views = np.stack([result.views for result in results]) if return_views else None
    timings = {"total": sum(result.timings.get("total", 0.0) for result in results)}
    if np.ndim(frames) == 2:
        return ReconstructionResult(recon[0], None if views is None else views[0], timings)
    return ReconstructionResult(recon, views, timings)


def reconstruct_with_method(
    method: str, frames: Any, system: SystemConfig, return_views: bool = False, **options: Any
) -> ReconstructionResult:
    """Reconstruct a raw frame ``(H, W)`` or a stack ``(T, H, W)`` with a named method.

    ``options`` are those of :func:`build_reconstructor` (``weights``, ``device``, ...).

    Examples
    --------
    >>> result = reconstruct_with_method("wiener", frame, system)  # doctest: +SKIP
    >>> result.reconstruction.shape  # doctest: +SKIP
    (384, 384)
    """
    reconstructor = build_reconstructor(method, system, **options)
    return reconstructor.reconstruct(frames, return_views)


#: SV-CoDe / learned option → ``svcode reconstruct`` flag
_COMMON_FLAGS = {
    "weights": "--weights",
    "device": "--device",
    "precision": "--precision",
    "tile_size": "--tile",
    "stride": "--stride",
    "batch_size": "--batch-size",
}


def cli_arguments(method: str, weights: str | Path | None = None, **options: Any) -> list[str]:
    """The ``svcode reconstruct`` flags that select ``method`` with ``options``.

    ``options`` are named as for :func:`build_reconstructor`; ``None`` values are left out
    (the command line's default applies).

    Examples
    --------
    >>> cli_arguments("admm", iterations=50, tv_weight=1e-3)
    ['--method', 'admm', '--iterations', '50', '--tv-weight', '0.001']
    """
    _check_method(method)
    flags = {**_COMMON_FLAGS}
    if method in MODEL_BASED_METHODS:
        flags.update({option: "--" + flag.replace("_", "-")
                      for flag, (option, methods) in BASELINE_FLAGS.items()
                      if method in methods and option in BASELINE_OPTIONS[method]})
    arguments = ["--method", method]
    for name, value in {"weights": weights, **options}.items():
        if value is None:
            continue
        if name == "skip_empty":
            arguments += [] if value else ["--no-skip"]
        elif name == "mask_cache_bytes":
            arguments += ["--mask-cache", str(int(value) >> 20)]
        elif name in flags:
            arguments += [flags[name], f"{value:g}" if isinstance(value, float) else str(value)]
        else:
            raise ValueError(f"{method}: option {name!r} has no `svcode reconstruct` flag")
    return arguments
