"""The true instrument: the nominal system with its :class:`~.departures.Departures` applied.

* **Geometry**: each lens's image moves by :meth:`Departures.lens_offsets`; the integer
  part moves the chief ray in a copy of the :class:`~.config.SystemConfig`, the sub-pixel
  remainder is a linear pupil phase in every PSF of that lens (:func:`.optics.system_psfs`).
* **Optics**: the Seidel coefficients and distortion of the copy carry the errors; defocus
  is the pupil's ``W020`` term; a thick sample averages the PSFs over its depth planes;
  the truth may use a finer PSF grid and a tighter low-rank tolerance than the model.
* **Haze**: out-of-focus light, the in-focus frame spread by a wide Gaussian, scaled.
* **Camera**: a :class:`~.noise.SensorModel` with the photon level, read noise and
  saturation converted from photo-electrons, the fixed-pattern maps and the ADC.

The measurement is the truth system's sensor frame, so sub-views are then cut at the
*nominal* chief rays, as a user who only has the nominal system would; the demixing
targets are registered to those nominal sub-views.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..config import ConfigError, NoiseConfig, SystemConfig
from .cm2 import CM2Operator
from .departures import Departures, load_departures
from .geometry import sensor_coverage
from .noise import SensorModel, fixed_pattern
from .optics import system_psfs

__all__ = [
    "Instrument",
    "departed_psfs",
    "departed_system",
    "electrons_per_unit",
    "haze",
    "sensor_model",
]


def departed_system(system: SystemConfig, departures: Departures
                    ) -> tuple[SystemConfig, np.ndarray]:  # fmt: skip
    """The truth system and the sub-pixel part of each lens's displacement.

    Parameters
    ----------
    system : SystemConfig
        The nominal system.
    departures : Departures

    Returns
    -------
    (SystemConfig, numpy.ndarray)
        A validated copy with the chief rays moved by the rounded lens offsets, the
        aberration and distortion errors added, and the truth PSF grid and rank tolerance;
        and the ``(9, 2)`` remainders in ``[-0.5, 0.5]`` pixels.

    Raises
    ------
    ConfigError
        If a lens leaves the padded frame or every lens leaves the sensor (naming the field).
    """
    departures.check_system(system)
    offsets = departures.lens_offsets(system)
    whole = np.round(offsets)
    moved = np.asarray(system.chief_rays) + whole.astype(int)
    rays = tuple((int(r), int(c)) for r, c in moved)
    optics = system.optics
    optics = dataclasses.replace(
        optics,
        spherical=optics.spherical + departures.spherical_error_waves,
        coma=optics.coma + departures.coma_error_waves,
        astigmatism=optics.astigmatism + departures.astigmatism_error_waves,
        field_curvature=optics.field_curvature + departures.field_curvature_error_waves,
        distortion=optics.distortion + departures.distortion_error_px,
        psf_grid=departures.truth_psf_grid or optics.psf_grid,
    )
    tolerance = departures.truth_rank_tolerance or system.rank_tolerance
    truth = dataclasses.replace(system, chief_rays=rays, optics=optics, rank_tolerance=tolerance)
    return truth.validate(), offsets - whole


def departed_psfs(truth: SystemConfig, departures: Departures, remainders: np.ndarray
                  ) -> np.ndarray:  # fmt: skip
    """PSFs ``(9, G·G, k, k)`` of the truth system, averaged over the sample's depth planes."""
    planes = departures.depth_planes()
    total = sum(system_psfs(truth, defocus=float(z), offsets=remainders) for z in planes)
    return total / len(planes)


def haze(frame: torch.Tensor, fraction: float, width: float) -> torch.Tensor:
    """Out-of-focus background: ``fraction`` of the frame's light, spread by a Gaussian.

    Parameters
    ----------
    frame : torch.Tensor
        In-focus sensor frame(s) ``(..., H, W)``.
    fraction : float
        Haze energy as a fraction of the frame's (light spread past the sensor is lost).
    width : float
        Gaussian standard deviation in pixels.

    Returns
    -------
    torch.Tensor
        The haze alone, same shape, dtype and device.
    """
    from scipy import ndimage  # here: it takes 0.4-0.5 s to import, and only haze needs it

    image = frame.detach().cpu().double().numpy()
    sigma = (0,) * (image.ndim - 2) + (width, width)
    spread = ndimage.gaussian_filter(image, sigma, mode="constant", truncate=4.0)
    return torch.as_tensor(fraction * spread, dtype=frame.dtype, device=frame.device)


def electrons_per_unit(noise: NoiseConfig, departures: Departures) -> float:
    """Photo-electrons at normalised intensity 1: the departures' or the nominal photon level.

    Without a photon count the nominal mixed model's shot-noise gain ``a`` gives ``1 / a``.

    Raises
    ------
    ConfigError
        If neither sets a photon level but the departures give electron quantities.
    """
    if departures.photons is not None:
        return float(departures.photons)
    if noise.photons is not None:
        return float(noise.photons)
    if noise.poisson_gain > 0:
        return 1.0 / noise.poisson_gain
    raise ConfigError("departures.photons: the nominal noise model has no shot noise, so "
                      "electron quantities need a photon level; set photons")  # fmt: skip


def sensor_model(noise: NoiseConfig, departures: Departures, shape: tuple[int, int]
                 ) -> SensorModel:  # fmt: skip
    """The camera of the departed instrument (nominal noise for a nominal camera).

    Parameters
    ----------
    noise : NoiseConfig
        The nominal sensor model.
    departures : Departures
    shape : (int, int)
        Sensor shape (of the fixed-pattern maps).
    """
    if not departures.has_sensor:
        return SensorModel(noise)
    electrons = electrons_per_unit(noise, departures)
    changes = {}
    if departures.photons is not None:
        changes["photons"] = departures.photons
    if departures.read_noise_e is not None:
        changes["gaussian_variance"] = (departures.read_noise_e / electrons) ** 2
    if departures.full_well_e is not None:
        changes["saturation"] = departures.full_well_e / electrons
    gain, offset = fixed_pattern(
        shape, np.random.default_rng([departures.seed, 0xF1C5]),
        gain_rms=departures.prnu_percent / 100.0,
        offset_rms=departures.dsnu_e / electrons,
        hot_fraction=departures.hot_pixel_fraction,
        hot_mean=departures.hot_pixel_e / electrons,
    )  # fmt: skip
    return SensorModel(dataclasses.replace(noise, **changes), gain, offset, departures.adc_bits)


@dataclass
class Instrument:
    """The true instrument behind a nominal system.

    Attributes
    ----------
    nominal : SystemConfig
        What the user (and every reconstructor) has.
    departures : Departures
    truth : SystemConfig
        The nominal system with the geometric and optical departures applied.
    operator : CM2Operator
        Forward model of ``truth`` (its PSFs include the sub-pixel offsets and defocus).
    sensor : SensorModel
    """

    nominal: SystemConfig
    departures: Departures
    truth: SystemConfig
    operator: CM2Operator
    sensor: SensorModel

    @classmethod
    def build(
        cls,
        nominal: SystemConfig,
        departures: Departures | str,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = "cpu",
        reuse: Instrument | None = None,
    ) -> Instrument:
        """Build the instrument; the forward model is the costly part.

        Parameters
        ----------
        nominal : SystemConfig
        departures : Departures or str
            Departures, a named set or a JSON path (:func:`.departures.load_departures`).
        dtype, device
            Of the forward operator.
        reuse : Instrument, optional
            An instrument whose operator is taken over when its optical departures are
            the same (only haze and camera differ): per-frame draws share one operator.
        """
        nominal = nominal.validate()
        departures = load_departures(departures, nominal)
        if reuse is not None and reuse.nominal == nominal and (
            reuse.departures.optical_key() == departures.optical_key()
        ):
            truth, operator = reuse.truth, reuse.operator
        else:
            truth, remainders = departed_system(nominal, departures)
            psfs = departed_psfs(truth, departures, remainders)
            operator = CM2Operator.from_psfs(truth, psfs, dtype=dtype, device=device)
        sensor = sensor_model(nominal.noise, departures, nominal.sensor_shape)
        return cls(nominal, departures, truth, operator, sensor)

    @property
    def view_offsets(self) -> np.ndarray:
        """``(9, 2)`` integer moves of each lens's chief ray from nominal to truth."""
        return np.asarray(self.truth.chief_rays) - np.asarray(self.nominal.chief_rays)

    def observe(self, x: torch.Tensor, past: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Expected sensor frame and nominal-registered demixing targets of object ``x``.

        Returns
        -------
        (expected, targets)
            The mean camera reading ``(..., H, W)`` (in-focus light plus haze, through
            the gain and dark-signal maps, before noise), and each lens's noiseless image
            in its *nominal* sub-view, sensor-truncated, ``(..., 9, S, S)``; with ``past``
            each image runs on that many pixels past the sub-view
            (:meth:`~svcode_core.physics.cm2.CM2Operator.lens_images`).
        """
        clean, targets = self.operator.measure_with_targets(x, past)
        if self.departures.background_fraction > 0:
            clean = clean + haze(clean, self.departures.background_fraction,
                                 self.departures.background_width_px)  # fmt: skip
        return self.sensor.expected(clean), self._register(targets)

    def _register(self, targets: torch.Tensor) -> torch.Tensor:
        """Move each lens's target from its true sub-view into its nominal one (sub-views
        enlarged alike when the targets run past them)."""
        moves = self.view_offsets
        if not moves.any():
            return targets
        size = targets.shape[-1]
        past = (size - self.nominal.sub_view_size) // 2
        out = torch.zeros_like(targets)
        for lens, (dr, dc) in enumerate(moves.tolist()):
            src_r, dst_r = _span(dr, size)
            src_c, dst_c = _span(dc, size)
            out[..., lens, dst_r, dst_c] = targets[..., lens, src_r, src_c]
        return out * sensor_coverage(self.nominal, targets.dtype, targets.device, margin=past)


def _span(move: int, size: int) -> tuple[slice, slice]:
    """Source and destination slices of a shift by ``move`` pixels of a length-``size`` axis."""
    if abs(move) >= size:
        raise ConfigError(f"departures: a lens moved {move} px, beyond its {size}-px sub-view")
    if move >= 0:
        return slice(0, size - move), slice(move, size)
    return slice(-move, size), slice(0, size + move)
