"""The CM² forward model: nine low-rank SV lens images, placed and cut by the sensor.

``y = crop_sensor( Σ_ℓ place_ℓ( v_ℓ ) )`` with ``v_ℓ = Σ_k h_{ℓ,k} ∗ (w_{ℓ,k} ⊙ x)``
(design.md §1). Each lens image is computed on the object grid enlarged by the kernel
radius (``margin``), so the blur reaching past the object's edge is kept: the lens
convolution is the full linear one. The padded frame returned by :meth:`CM2Operator.forward`
is zero outside the sensor window, which is exactly what the reconstruction pipeline
builds from a raw frame with :func:`~svcode_core.physics.geometry.pad_sensor_frame`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..config import N_LENSES, SystemConfig
from .geometry import (
    crop_to_sensor,
    extract_sub_views,
    pad_sensor_frame,
    place_sub_views,
    sensor_coverage,
)
from .lowrank import LowRankSVOperator, PSFDecomposition, decompose_psfs, fft_shape, plan_chunks

__all__ = ["CM2Operator", "SimulationCost", "simulation_cost"]


class CM2Operator:
    """Linear forward model of a CM² instrument, with its exact adjoint.

    Parameters
    ----------
    system : SystemConfig
        Geometry of the instrument.
    lenses : LowRankSVOperator
        The nine lens blurs on the object grid enlarged by ``margin`` on every side:
        kernels ``(9, K, h, w)`` and weights ``(9, K, S + 2m, S + 2m)``.
    margin : int
        Enlargement of the object grid, at least the kernel radius.
    decompositions : sequence of PSFDecomposition, optional
        Kept for reports (rank and captured energy per lens).

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> op = CM2Operator.from_system(tiny)
    >>> op.forward(torch.rand(48, 48, dtype=op.lenses.dtype)).shape  # the padded frame
    torch.Size([84, 84])
    """

    def __init__(
        self,
        system: SystemConfig,
        lenses: LowRankSVOperator,
        margin: int,
        decompositions: Sequence[PSFDecomposition] = (),
    ) -> None:
        size = system.sub_view_size + 2 * margin
        if lenses.n_lenses != N_LENSES or lenses.shape != (size, size):
            raise ValueError(
                f"lenses must hold {N_LENSES} lenses of shape {size}×{size}, got "
                f"{lenses.n_lenses} of shape {lenses.shape}"
            )
        if min(lenses.kernel_shape) // 2 > margin:
            raise ValueError(f"margin {margin} is smaller than the kernel radius")
        self.system = system
        self.lenses = lenses
        self.margin = margin
        self.decompositions = tuple(decompositions)
        sensor = torch.ones(system.sensor_shape, dtype=lenses.dtype, device=lenses.device)
        self._sensor_mask = pad_sensor_frame(sensor, system)
        self._own_view_mask = sensor_coverage(system, lenses.dtype, lenses.device)

    # ------------------------------------------------------------ construction
    @classmethod
    def from_psfs(
        cls,
        system: SystemConfig,
        psfs: np.ndarray,
        rank: int | None = None,
        tolerance: float | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
        memory_budget: int | None = None,
    ) -> CM2Operator:
        """Decompose each lens's PSF grid and build the operator.

        Parameters
        ----------
        system : SystemConfig
        psfs : numpy.ndarray
            ``(9, G·G, h, w)`` PSFs registered to their ideal image points.
        rank : int, optional
            Low-rank order ``K``; default ``system.rank``. When both are ``None`` each lens
            uses the smallest ``K`` meeting ``tolerance`` (default ``system.rank_tolerance``).
        tolerance : float, optional
            Largest fraction of PSF energy left out.
        dtype, device
            Of the operator.
        memory_budget : int, optional
            Bytes for the lens blur's kept spectra and working memory
            (:class:`~svcode_core.physics.lowrank.LowRankSVOperator`; default
            :data:`~svcode_core.physics.lowrank.DEFAULT_MEMORY_BUDGET`).
        """
        psfs = np.asarray(psfs)
        if psfs.ndim != 4 or psfs.shape[0] != N_LENSES:
            raise ValueError(f"psfs must have shape (9, G*G, h, w), got {psfs.shape}")
        rank = system.rank if rank is None else rank
        tolerance = system.rank_tolerance if tolerance is None else tolerance
        decompositions = [decompose_psfs(lens_psfs, rank, tolerance) for lens_psfs in psfs]
        margin = max(psfs.shape[-2:]) // 2
        lenses = LowRankSVOperator.from_decomposition(
            decompositions, system.sub_view_size, margin=margin, dtype=dtype, device=device,
            memory_budget=memory_budget,
        )
        return cls(system, lenses, margin, decompositions)

    @classmethod
    def from_system(
        cls,
        system: SystemConfig,
        rank: int | None = None,
        tolerance: float | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
        memory_budget: int | None = None,
    ) -> CM2Operator:
        """The operator of ``system``: PSFs from its ``psf_model`` stack if it names one
        (a calibrated system), else from its pupil model (:func:`.psf_io.model_psfs`)."""
        from .psf_io import model_psfs

        return cls.from_psfs(
            system, model_psfs(system), rank, tolerance, dtype, device, memory_budget
        )

    # --------------------------------------------------------------- reports
    @property
    def rank(self) -> int:
        """Low-rank order ``K`` (the largest over lenses)."""
        return self.lenses.rank

    # ---------------------------------------------------------------- algebra
    def _check_object(self, x: torch.Tensor) -> None:
        size = self.system.sub_view_size
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"object must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim < 2 or tuple(x.shape[-2:]) != (size, size):
            raise ValueError(f"object must have shape (..., {size}, {size}), got {tuple(x.shape)}")

    def _enlarge(self, x: torch.Tensor) -> torch.Tensor:
        m = self.margin
        return torch.nn.functional.pad(x, (m, m, m, m))

    def _shrink(self, x: torch.Tensor, past: int = 0) -> torch.Tensor:
        """The enlarged grid cut down to the sub-view, or to the sub-view enlarged by
        ``past``."""
        cut = self.margin - past
        return x[..., cut : x.shape[-2] - cut, cut : x.shape[-1] - cut]

    def lens_blur(self, x: torch.Tensor) -> torch.Tensor:
        """The nine blurred lens images on the enlarged grid, ``(..., 9, S+2m, S+2m)``."""
        self._check_object(x)
        return self.lenses.forward(self._enlarge(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Noiseless padded sensor frame of object ``x``.

        Parameters
        ----------
        x : torch.Tensor
            Object(s) ``(..., S, S)``.

        Returns
        -------
        torch.Tensor
            ``(..., H_pad, W_pad)``, zero outside the sensor window.
        """
        return self._frame_of(self.lens_blur(x))

    __call__ = forward

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint of :meth:`forward`: padded frame(s) ``(..., H_pad, W_pad)`` → ``(..., S, S)``."""
        views = extract_sub_views(y * self._sensor_mask, self.system, self.margin)
        return self._shrink(self.lenses.adjoint(views))

    def measure(self, x: torch.Tensor) -> torch.Tensor:
        """Noiseless raw sensor frame(s) ``(..., *sensor_shape)`` of object ``x``."""
        return crop_to_sensor(self.forward(x), self.system)

    def lens_images(self, x: torch.Tensor, past: int = 0) -> torch.Tensor:
        """The demixing targets: what each lens alone puts inside its own sub-view.

        Lens ``ℓ``'s noiseless image, cut to sub-view ``ℓ`` and truncated by the sensor
        like the measurement, shape ``(..., 9, S, S)``. Placing these nine images back
        reproduces the measurement inside each lens's own sub-view, minus the crosstalk
        of the other lenses. With ``past`` > 0 (at most :attr:`margin`) each image runs on
        ``past`` px beyond its sub-view on every side, as far as the sensor holds it:
        ``(..., 9, S + 2·past, S + 2·past)``, the light of the border's points that a
        sub-view's window cuts off.
        """
        return self._targets_of(self.lens_blur(x), past)

    def measure_with_targets(
        self, x: torch.Tensor, past: int = 0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`measure` and :meth:`lens_images` of ``x`` from one pass of the lens blur."""
        blur = self.lens_blur(x)
        return crop_to_sensor(self._frame_of(blur), self.system), self._targets_of(blur, past)

    def _frame_of(self, blur: torch.Tensor) -> torch.Tensor:
        return place_sub_views(blur, self.system, self.margin) * self._sensor_mask

    def _targets_of(self, blur: torch.Tensor, past: int = 0) -> torch.Tensor:
        if past == 0:
            on_sensor = self._own_view_mask
        elif isinstance(past, bool) or not isinstance(past, int) or not 0 < past <= self.margin:
            raise ValueError(f"past must be an integer from 0 to the margin {self.margin}, "
                             f"got {past!r}")  # fmt: skip
        else:
            on_sensor = sensor_coverage(self.system, blur.dtype, blur.device, margin=past)
        return self._shrink(blur, past) * on_sensor


@dataclass(frozen=True)
class SimulationCost:
    """Estimated cost of building a system's operator and simulating one frame with it.

    Attributes
    ----------
    memory : int
        Peak bytes above what the process held before (PSFs, operator, the frame's images).
    seconds : float
        Wall time on this machine (from timed samples of the work, see
        :func:`simulation_cost`).
    rank : int
        Low-rank order ``K`` assumed.
    """

    memory: int
    seconds: float
    rank: int


def simulation_cost(
    system: SystemConfig, memory_budget: int | None = None, dtype: torch.dtype = torch.float32
) -> SimulationCost:
    """Estimate, before building anything large, what :class:`~.simulate.Simulator` needs.

    Computes and decomposes the PSFs of one lens (for their time, times nine, and for ``K``
    when ``system.rank`` is unset: that of corner lens 0, the largest in the presets) and
    times one FFT of the lens grid; the memory is the sum of the largest arrays: the PSFs
    (float64, with the SVD's copies), the kept kernel spectra and the working chunk of the
    lens blur (:func:`~.lowrank.plan_chunks`), and the frame's images (lens blur, targets,
    padded frames, noise, the returned arrays). Not all are alive together, so it is an
    upper estimate (at ``cm2-v2``: 2.8 GiB, while the whole ``svcode simulate`` process
    peaks at 1.7 GiB resident).

    Parameters
    ----------
    system : SystemConfig
    memory_budget : int, optional
        Of the operator (default :data:`~svcode_core.physics.lowrank.DEFAULT_MEMORY_BUDGET`).
    dtype : torch.dtype
        Of the operator.
    """
    from .optics import lens_psfs

    start = time.perf_counter()
    psfs = lens_psfs(system, 0)
    decomposition = decompose_psfs(psfs, system.rank, system.rank_tolerance)
    psf_seconds = N_LENSES * (time.perf_counter() - start)
    rank = decomposition.rank
    kernel = psfs.shape[-2:]
    size = system.sub_view_size + 2 * (max(kernel) // 2)
    plan = plan_chunks((size, size), kernel, N_LENSES, rank, dtype, memory_budget)
    fft = fft_shape((size, size), kernel)
    sample = torch.zeros(fft, dtype=dtype)
    start = time.perf_counter()
    torch.fft.irfft2(torch.fft.rfft2(sample), s=fft)
    fft_seconds = (time.perf_counter() - start) / 2
    # forward FFT per term, kernel spectrum (about half an FFT) per term not kept, inverse per lens
    recomputed = (N_LENSES - plan.kept_lenses) * rank
    blur_seconds = fft_seconds * (N_LENSES * rank + recomputed / 2 + N_LENSES)
    item = torch.finfo(dtype).bits // 8
    rows, cols = system.padded_shape
    images = item * (
        2 * N_LENSES * size * size  # lens blur, its cut targets
        + 8 * rows * cols  # placed, masked, cropped, noisy and re-padded frames
        + 3 * N_LENSES * system.sub_view_size**2  # targets, views, their float32 copies
    )
    psf_bytes = 3 * N_LENSES * psfs.nbytes  # the grid, its stack and the SVD's copies
    return SimulationCost(
        memory=psf_bytes + plan.bytes + images, seconds=psf_seconds + blur_seconds, rank=rank
    )
