"""Model-based baselines: LSV-ADMM and shift-invariant Wiener / Richardson–Lucy deconvolution.

:func:`reconstruct_with_baseline` reconstructs one raw frame with a named method;
:class:`BaselineReconstructor` does the same for frames and stacks with the interface of
:class:`~svcode_core.reconstruct.Reconstructor` (so :func:`svcode_core.stream.reconstruct_file`
and the dask backends accept a :class:`BaselineSpec` as their factory), and
:func:`add_method_arguments` / :func:`baseline_options` give ``svcode reconstruct`` each
method's options.

Every method runs in float32 (``precision="fp32"``, default) or float64 (``"fp64"``) on
the CPU or CUDA. Half precision (``"bf16"``, ``"fp16"``) is refused with a
:class:`ValueError`: the methods are FFT-based and torch has no half-precision FFT on the
CPU (on CUDA only for power-of-two sizes). Half-precision *input* frames are fine: they are
converted. The returned ``views`` of a baseline are the nine lens images ``A_ℓ x̂`` of its
reconstruction re-imaged through the forward model (a model-based demixing).
"""

from __future__ import annotations

import argparse
import functools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..cm2 import CM2Operator
from ..config import SystemConfig
from ..geometry import pad_sensor_frame
from ..reconstruct import (
    ReconstructionResult,
    as_frame_stack,
    check_frame_shape,
    finite_frame,
    resolve_device,
)
from .admm import AdmmResult, AdmmSettings, LsvAdmm, settings_for
from .deconv import ShiftInvariantDeconvolution

__all__ = [
    "METHODS",
    "AdmmResult",
    "AdmmSettings",
    "BaselineReconstructor",
    "BaselineSpec",
    "LsvAdmm",
    "ShiftInvariantDeconvolution",
    "add_method_arguments",
    "baseline_options",
    "build_operator",
    "reconstruct_with_baseline",
]

METHODS = ("admm", "wiener", "rl")
PRECISIONS = {"fp32": torch.float32, "fp64": torch.float64}
WIENER_BALANCE = 1e-2
RL_ITERATIONS = 30

#: options each method accepts (besides ``operator``, ``device``, ``precision``)
METHOD_OPTIONS = {
    "admm": ("rank", "iterations", "tv_weight", "rho", "tolerance", "cg_iterations"),
    "wiener": ("rank", "balance", "boundary"),
    "rl": ("rank", "iterations"),
}


@functools.lru_cache(maxsize=2)
def build_operator(
    system: SystemConfig, rank: int | None = None, device: str = "cpu", precision: str = "fp32"
) -> CM2Operator:
    """The pupil-model operator of ``system`` (cached: the two most recent are kept)."""
    return CM2Operator.from_system(
        system, rank=rank, dtype=_dtype(precision), device=resolve_device(device)
    )


def _dtype(precision: str) -> torch.dtype:
    if precision in ("bf16", "fp16"):
        raise ValueError(
            f"precision: {precision} is not supported by the model-based baselines (they are "
            "FFT-based; torch has no half-precision FFT on the CPU and only power-of-two "
            "sizes on CUDA); use fp32 or fp64"
        )
    if precision not in PRECISIONS:
        raise ValueError(f"precision: {precision!r} is not one of {sorted(PRECISIONS)}")
    return PRECISIONS[precision]


class BaselineReconstructor:
    """Reconstruct raw CM² frames with a model-based baseline.

    Parameters
    ----------
    method : {"admm", "wiener", "rl"}
    system : SystemConfig
    operator : CM2Operator, optional
        Forward model to use (default :func:`build_operator`); fixes device and dtype.
    device : str
        Used when building the operator.
    precision : {"fp32", "fp64"}
        Used when building the operator; half precision raises :class:`ValueError`.
    **options
        The method's options (:data:`METHOD_OPTIONS`; ``None`` means the default):
        ``rank`` (low-rank order ``K`` of the operator built), ADMM ``iterations``,
        ``tv_weight``, ``rho``, ``tolerance``, ``cg_iterations`` (defaults
        :func:`~svcode_core.baselines.admm.settings_for`), Wiener ``balance`` (1e-2) and
        ``boundary`` ("reflect"), RL ``iterations`` (30).

    Notes
    -----
    For a stack, ADMM warm-starts every frame from the previous frame's result.
    """

    def __init__(
        self,
        method: str,
        system: SystemConfig,
        operator: CM2Operator | None = None,
        device: str = "cpu",
        precision: str = "fp32",
        **options: Any,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"method: {method!r} is not one of {METHODS}")
        _dtype(precision)  # refuse half precision before any work
        options = {key: value for key, value in options.items() if value is not None}
        unknown = sorted(set(options) - set(METHOD_OPTIONS[method]))
        if unknown:
            raise ValueError(
                f"{method}: unknown option(s) {unknown}; it accepts {list(METHOD_OPTIONS[method])}"
            )
        rank = options.pop("rank", None)
        if operator is None:
            operator = build_operator(system, rank, str(device), precision)
        elif rank is not None:
            raise ValueError("pass either an operator or a rank, not both")
        elif operator.system != system:
            raise ValueError("the operator was built for another system configuration")
        self.method = method
        self.system = system
        self.operator = operator
        self.options = options
        if method == "admm":
            defaults = settings_for(system)
            self.iterations = options.get("iterations", defaults.iterations)
            self.tolerance = options.get("tolerance", defaults.tolerance)
            self.solver = LsvAdmm(
                operator,
                tv_weight=options.get("tv_weight", defaults.tv_weight),
                rho=options.get("rho", defaults.rho),
                cg_iterations=options.get("cg_iterations", defaults.cg_iterations),
                adaptive_rho=defaults.adaptive_rho,
                check_every=defaults.check_every,
            )
        else:
            self.solver = ShiftInvariantDeconvolution(
                operator,
                method,
                balance=options.get("balance", WIENER_BALANCE),
                iterations=options.get("iterations", RL_ITERATIONS),
                boundary=options.get("boundary", "reflect"),
            )

    def _padded(self, frame: np.ndarray, index: int) -> torch.Tensor:
        values = finite_frame(frame, index, np.float64)
        lenses = self.operator.lenses
        tensor = torch.as_tensor(values, dtype=lenses.dtype, device=lenses.device)
        return pad_sensor_frame(tensor, self.system)

    def reconstruct_tensor(
        self, frame: np.ndarray, x0: torch.Tensor | None = None, index: int = 0
    ) -> torch.Tensor:
        """One raw frame ``(H, W)`` → the reconstruction ``(S, S)`` as a tensor."""
        check_frame_shape(np.shape(frame), self.system)
        padded = self._padded(frame, index)
        if self.method == "admm":
            return self.solver.solve(padded, x0, self.iterations, self.tolerance).x
        return self.solver(padded)

    def reconstruct(self, frames: Any, return_views: bool = False) -> ReconstructionResult:
        """Reconstruct a raw frame ``(H, W)`` or a stack ``(T, H, W)``.

        Returns
        -------
        ReconstructionResult
            Float32 reconstruction(s), the re-imaged lens views when asked, ``timings``
            with the ``total`` seconds; the tile counters are 0 (no tiling).
        """
        single = np.ndim(frames) == 2
        stack = as_frame_stack(frames)
        start = time.perf_counter()
        recons, views, previous = [], [], None
        for index, frame in enumerate(stack):
            estimate = self.reconstruct_tensor(frame, previous, index)
            previous = estimate if self.method == "admm" else None
            recons.append(estimate.detach().to("cpu", torch.float32).numpy())
            if return_views:
                lens = self.operator.lens_images(estimate)
                views.append(lens.detach().to("cpu", torch.float32).numpy())
        recon = np.stack(recons)
        view_array = np.stack(views) if return_views else None
        if single:
            recon = recon[0]
            view_array = None if view_array is None else view_array[0]
        return ReconstructionResult(
            recon, view_array, timings={"total": time.perf_counter() - start}
        )


def reconstruct_with_baseline(
    method: str, raw_frame: np.ndarray, system: SystemConfig, **options: Any
) -> np.ndarray:
    """Reconstruct one raw sensor frame with ``method`` ∈ {"admm", "wiener", "rl"}.

    Parameters
    ----------
    method : str
    raw_frame : numpy.ndarray
        Raw sensor frame ``system.sensor_shape`` (any real dtype).
    system : SystemConfig
    **options
        ``operator``, ``device``, ``precision`` and the method's options, see
        :class:`BaselineReconstructor`.

    Returns
    -------
    numpy.ndarray
        Float32 ``(S, S)``.

    Examples
    --------
    >>> recon = reconstruct_with_baseline("rl", frame, system, iterations=50)  # doctest: +SKIP
    """
    if np.ndim(raw_frame) != 2:
        raise ValueError(f"raw_frame must be one H×W frame, got shape {np.shape(raw_frame)}")
    return BaselineReconstructor(method, system, **options).reconstruct(raw_frame).reconstruction


@dataclass(frozen=True)
class BaselineSpec:
    """Picklable recipe for a :class:`BaselineReconstructor` (a factory for the streaming
    and dask back ends, like :class:`~svcode_core.parallel.ReconstructorSpec`)."""

    method: str
    system: SystemConfig
    options: dict[str, Any] = field(default_factory=dict)

    def __call__(self) -> BaselineReconstructor:
        return BaselineReconstructor(self.method, self.system, **self.options)

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description (recorded in outputs and resume state)."""
        return {"method": self.method, **self.options}


#: command-line flag → (option name, methods it applies to)
_FLAGS = {
    "rank": ("rank", ("admm", "wiener", "rl")),
    "iterations": ("iterations", ("admm", "rl")),
    "tv_weight": ("tv_weight", ("admm",)),
    "rho": ("rho", ("admm",)),
    "tolerance": ("tolerance", ("admm",)),
    "cg_iterations": ("cg_iterations", ("admm",)),
    "wiener_balance": ("balance", ("wiener",)),
    "wiener_boundary": ("boundary", ("wiener",)),
}


def add_method_arguments(parser: argparse.ArgumentParser) -> None:
    """Register the baselines' options on ``parser`` (all default to ``None``: preset value)."""
    mini = settings_for(SystemConfig.preset("cm2-mini"))
    group = parser.add_argument_group("model-based baselines (--method admm, wiener, rl)")
    group.add_argument(
        "--rank", type=int, metavar="K", help="low-rank order K of the forward model (all)"
    )
    group.add_argument(
        "--iterations",
        type=int,
        help=f"admm: at most this many (default {mini.iterations}); rl: (default {RL_ITERATIONS})",
    )
    group.add_argument(
        "--tv-weight", type=float, help=f"admm: TV weight lambda (default {mini.tv_weight:g})"
    )
    group.add_argument("--rho", type=float, help=f"admm: starting penalty (default {mini.rho:g})")
    group.add_argument(
        "--tolerance",
        type=float,
        help=f"admm: relative residual to stop at (default {mini.tolerance:g})",
    )
    group.add_argument(
        "--cg-iterations",
        type=int,
        help=f"admm: CG steps per x-update (default {mini.cg_iterations})",
    )
    group.add_argument(
        "--wiener-balance",
        type=float,
        help=f"wiener: Laplacian regularisation weight (default {WIENER_BALANCE:g})",
    )
    group.add_argument(
        "--wiener-boundary",
        choices=("reflect", "periodic"),
        help="wiener: view boundary handling (default reflect)",
    )


def baseline_options(args: argparse.Namespace) -> dict[str, Any]:
    """The options of ``args.method`` given on the command line, as keyword arguments.

    Raises
    ------
    ValueError
        If an option of another method was given.
    """
    options = {}
    for flag, (name, methods) in _FLAGS.items():
        value = getattr(args, flag, None)
        if value is None:
            continue
        if args.method not in methods:
            option = "--" + flag.replace("_", "-")
            raise ValueError(f"{option} does not apply to --method {args.method}")
        options[name] = value
    return options
