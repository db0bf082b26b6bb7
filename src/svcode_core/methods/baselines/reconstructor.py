"""Reconstructing raw frames with a model-based baseline: LSV-ADMM, Wiener or Richardson–Lucy.

:class:`BaselineReconstructor` keeps the contract of every method
(:class:`~svcode_core.methods.base.BaseReconstructor`), so the streaming command line, the
dask back end and the plugin run it like the others; :func:`reconstruct_with_baseline`
reconstructs one raw frame in one call.

Every method runs in float32 (``precision="fp32"``, default) or float64 (``"fp64"``) on
the CPU or CUDA. Half precision (``"bf16"``, ``"fp16"``) is refused with a
:class:`ValueError`: the methods are FFT-based and torch has no half-precision FFT on the
CPU (on CUDA only for power-of-two sizes). Half-precision *input* frames are fine: they are
converted. The returned ``views`` of a baseline are the nine lens images ``A_ℓ x̂`` of its
reconstruction re-imaged through the forward model (a model-based demixing).
"""

from __future__ import annotations

import functools
from abc import abstractmethod
from collections.abc import Generator
from typing import Any

import numpy as np
import torch

from ...config import SystemConfig
from ...physics.cm2 import CM2Operator
from ...physics.geometry import pad_sensor_frame
from ...physics.lowrank import decompose_psfs
from ...physics.psf_io import model_psfs
from .. import registry
from ..base import FrameByFrame, check_frame_shape, precision_dtype, resolve_device
from ..frames import finite_frame
from ..registry import MODEL_BASED_METHODS
from ..tiling import exhaust
from .admm import LsvAdmm, settings_for
from .deconv import ShiftInvariantDeconvolution

__all__ = [
    "AdmmReconstructor",
    "BaselineReconstructor",
    "DeconvolutionReconstructor",
    "build_operator",
    "default_rank",
    "reconstruct_with_baseline",
]

_HALF = (
    "they are FFT-based; torch has no half-precision FFT on the CPU and only "
    "power-of-two sizes on CUDA"
)


def default_rank(system: SystemConfig, psfs: np.ndarray | None = None) -> int | None:
    """The low-rank order the model-based methods use unless given one:
    :data:`~svcode_core.methods.registry.DEFAULT_RANK`, or ``None`` (the system's own ``K``,
    each lens its own) when that is not larger.

    ``psfs`` are the system's PSFs (:func:`~svcode_core.physics.psf_io.model_psfs`), when
    already at hand.

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> default_rank(SystemConfig.tiny())  # its lenses need K = 6 to 8
    3
    >>> default_rank(SystemConfig.tiny().replace(rank=2)) is None
    True
    """
    cap = registry.DEFAULT_RANK
    if system.rank is not None:
        return None if system.rank <= cap else cap
    psfs = model_psfs(system) if psfs is None else psfs
    own = max(decompose_psfs(lens, None, system.rank_tolerance).rank for lens in psfs)
    return None if own <= cap else cap


@functools.lru_cache(maxsize=2)
def build_operator(
    system: SystemConfig,
    rank: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    memory_budget: int | None = None,
) -> CM2Operator:
    """The operator of ``system`` (its PSF model; cached: the two most recent are kept).

    ``rank`` ``None`` takes :func:`default_rank`. ``memory_budget`` bounds the bytes of its
    kept spectra and working chunks (:meth:`CM2Operator.from_system`; default 1 GiB).
    """
    dtype = precision_dtype(precision, "admm", _HALF)
    psfs = model_psfs(system)
    if rank is None:
        rank = default_rank(system, psfs)
    return CM2Operator.from_psfs(
        system,
        psfs,
        rank=rank,
        dtype=dtype,
        device=resolve_device(device),
        memory_budget=memory_budget,
    )


class BaselineReconstructor(FrameByFrame):
    """Reconstruct raw CM² frames with a model-based baseline.

    ``BaselineReconstructor(method, ...)`` makes the method's own class (the registry's,
    :func:`~svcode_core.methods.registry.reconstructor_class`): :class:`AdmmReconstructor`
    or :class:`DeconvolutionReconstructor`.

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
        The method's options (its table in :mod:`~svcode_core.methods.registry`, which
        checks them; ``None`` means the method's default): ``rank`` (low-rank order ``K``
        of the operator built, default :func:`default_rank`), ``memory_budget`` (bytes of
        the operator's spectra and working chunks, default 1 GiB), ADMM ``iterations``,
        ``tv_weight`` (a number, or ``"auto"``: from each frame's noise and level,
        :func:`~svcode_core.methods.baselines.admm.auto_tv_weight`), ``rho``,
        ``tolerance``, ``cg_iterations``, Wiener ``balance`` and ``boundary``, RL
        ``iterations``.
    """

    def __new__(cls, method: str | None = None, *args: Any, **kwargs: Any):
        if cls is BaselineReconstructor:
            if method not in MODEL_BASED_METHODS:
                raise ValueError(f"method: {method!r} is not one of {MODEL_BASED_METHODS}")
            cls = registry.reconstructor_class(method)
        return super().__new__(cls)

    def __init__(
        self,
        method: str,
        system: SystemConfig,
        operator: CM2Operator | None = None,
        device: str = "cpu",
        precision: str = "fp32",
        **options: Any,
    ) -> None:
        if method not in MODEL_BASED_METHODS:
            raise ValueError(f"method: {method!r} is not one of {MODEL_BASED_METHODS}")
        if not isinstance(self, registry.reconstructor_class(method)):
            raise ValueError(f"method: {type(self).__name__} does not run {method!r}")
        entry = registry.method(method)
        precision_dtype(precision, method, _HALF)  # refuse half precision before any work
        options = {key: value for key, value in options.items() if value is not None}
        entry.check(options)
        rank = options.pop("rank", None)
        budget = options.pop("memory_budget", None)
        if operator is None:
            operator = build_operator(system, rank, str(device), precision, budget)
        elif rank is not None or budget is not None:
            raise ValueError("pass either an operator or a rank and memory budget, not both")
        elif operator.system != system:
            raise ValueError("the operator was built for another system configuration")
        self.method = method
        self.system = system
        self.precision = precision
        self.operator = operator
        self.options = options
        settings = {**entry.defaults, **options}
        settings.pop("rank", None)
        self._start(settings)

    @classmethod
    def build(
        cls,
        method: str,
        system: SystemConfig | None,
        weights: Any = None,
        model: Any = None,
        **options: Any,
    ) -> BaselineReconstructor:
        """``cls(method, system, **options)``; the model-based methods take no model file."""
        if system is None:
            raise ValueError(f"{registry.method(method).title} needs the system configuration")
        return cls(method, system, **options)

    @abstractmethod
    def _start(self, settings: dict[str, Any]) -> None:
        """Make the solver from the method's settings (options with their defaults)."""

    @abstractmethod
    def iter_reconstruct_tensor(
        self, frame: np.ndarray, x0: torch.Tensor | None = None, index: int = 0
    ) -> Generator[int, None, torch.Tensor]:
        """Generator form of :meth:`reconstruct_tensor`: yields the iterations done after
        every one (ADMM, RL; Wiener yields nothing) and returns the reconstruction."""

    def _padded(self, frame: np.ndarray, index: int) -> torch.Tensor:
        check_frame_shape(np.shape(frame), self.system)
        values = finite_frame(frame, index, np.float64)
        lenses = self.operator.lenses
        tensor = torch.as_tensor(values, dtype=lenses.dtype, device=lenses.device)
        return pad_sensor_frame(tensor, self.system)

    def reconstruct_tensor(
        self, frame: np.ndarray, x0: torch.Tensor | None = None, index: int = 0
    ) -> torch.Tensor:
        """One raw frame ``(H, W)`` → the reconstruction ``(S, S)`` as a tensor."""
        return exhaust(self.iter_reconstruct_tensor(frame, x0, index))

    def reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """One raw frame → float32 reconstruction and, when asked, the re-imaged lens views."""
        return exhaust(self.iter_reconstruct_frame(frame, index, return_views))

    def iter_reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> Generator[int, None, tuple[np.ndarray, np.ndarray | None]]:
        """Generator form of :meth:`reconstruct_frame`, yielding the iterations done."""
        estimate = yield from self.iter_reconstruct_tensor(frame, None, index)
        return self._outputs(estimate, return_views)

    def _outputs(
        self, estimate: torch.Tensor, return_views: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        views = None
        if return_views:
            lens = self.operator.lens_images(estimate)
            views = lens.detach().to("cpu", torch.float32).numpy()
        return estimate.detach().to("cpu", torch.float32).numpy(), views


class AdmmReconstructor(BaselineReconstructor):
    """LSV-ADMM (:class:`~svcode_core.methods.baselines.admm.LsvAdmm`) on raw frames; see
    :class:`BaselineReconstructor`. For a stack, every frame warm-starts from the previous
    frame's result."""

    def _start(self, settings: dict[str, Any]) -> None:
        system_settings = settings_for(self.system)  # the knobs that are no options
        self.iterations = settings["iterations"]
        self.tolerance = settings["tolerance"]
        self.solver = LsvAdmm(self.operator, tv_weight=settings["tv_weight"],
                              rho=settings["rho"], cg_iterations=settings["cg_iterations"],
                              adaptive_rho=system_settings.adaptive_rho,
                              check_every=system_settings.check_every)  # fmt: skip
        self.frame_steps = self.iterations
        self._previous: torch.Tensor | None = None

    def iter_reconstruct_tensor(
        self, frame: np.ndarray, x0: torch.Tensor | None = None, index: int = 0
    ) -> Generator[int, None, torch.Tensor]:
        padded = self._padded(frame, index)
        steps = self.solver.iter_solve(padded, x0, self.iterations, self.tolerance)
        return (yield from steps).x

    def start_stack(self) -> None:
        """Every frame of a stack warm-starts from the previous one, not across calls."""
        self._previous = None

    def iter_reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> Generator[int, None, tuple[np.ndarray, np.ndarray | None]]:
        """Generator form of :meth:`reconstruct_frame`, yielding the iterations done; a frame
        stopped part way leaves the warm start of the next as it was."""
        estimate = yield from self.iter_reconstruct_tensor(frame, self._previous, index)
        self._previous = estimate
        return self._outputs(estimate, return_views)


class DeconvolutionReconstructor(BaselineReconstructor):
    """Wiener or Richardson–Lucy per view, fused
    (:class:`~svcode_core.methods.baselines.deconv.ShiftInvariantDeconvolution`), on raw
    frames; see :class:`BaselineReconstructor`."""

    def _start(self, settings: dict[str, Any]) -> None:
        self.solver = ShiftInvariantDeconvolution(self.operator, self.method, **settings)
        self.frame_steps = self.solver.steps

    def iter_reconstruct_tensor(
        self, frame: np.ndarray, x0: torch.Tensor | None = None, index: int = 0
    ) -> Generator[int, None, torch.Tensor]:
        """Generator form of :meth:`reconstruct_tensor` (``x0`` is not used): yields the RL
        iterations done after every one (Wiener nothing) and returns the reconstruction."""
        return (yield from self.solver.iter_solve(self._padded(frame, index)))


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
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> frame = np.random.default_rng(0).uniform(0, 0.5, (60, 80))
    >>> reconstruct_with_baseline("rl", frame, tiny, iterations=5).shape
    (48, 48)
    """
    if np.ndim(raw_frame) != 2:
        raise ValueError(f"raw_frame must be one H×W frame, got shape {np.shape(raw_frame)}")
    return BaselineReconstructor(method, system, **options).reconstruct(raw_frame).reconstruction
