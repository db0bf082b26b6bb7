"""The sensor noise model: mixed Poisson–Gaussian or exact Poisson, dark offset, clipping.

Frames are normalised to a peak signal of about 1 (see :class:`~svcode_core.config.NoiseConfig`).
With ``a = poisson_gain`` and ``b = gaussian_variance`` a reading of the noise-free signal
``y`` is

* mixed Poisson–Gaussian (default): ``y + sqrt(max(a·y + b, 0))·n`` with ``n ~ N(0, 1)``;
* exact Poisson, when a photon count ``p`` is given (argument or ``NoiseConfig.photons``):
  ``Poisson(p·max(y, 0)) / p + sqrt(b)·n``; the Poisson draw replaces the ``a·y`` term;

then ``dark_offset`` is added and the reading is clipped to ``[0, saturation]``. Clipping at
0 models an unsigned sensor (the ADC cannot report negative values); clipping at
``saturation`` models the full well. Negative ``y`` (from dark subtraction of real data) is
allowed: the variance is clamped at 0 before the square root and the Poisson rate at 0.

A real camera adds what :class:`SensorModel` describes: a per-pixel gain map (PRNU) and
dark-signal map (hot pixels, DSNU), fixed for the sensor (:func:`fixed_pattern`), and an
ADC that rounds the reading to ``2**bits - 1`` steps of the saturation level
(:func:`quantize`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..config import NoiseConfig

__all__ = [
    "SensorModel",
    "apply_sensor_noise",
    "estimate_noise_std",
    "fixed_pattern",
    "noise_floor",
    "noise_std",
    "quantize",
]


def _photons(noise: NoiseConfig, photons: float | None) -> float | None:
    value = noise.photons if photons is None else photons
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ValueError(f"photons must be a finite number > 0, got {value!r}")
    return value


def _check_frame(frame: torch.Tensor) -> None:
    if not isinstance(frame, torch.Tensor):
        raise TypeError(f"frame must be a torch.Tensor, got {type(frame).__name__}")
    if not frame.is_floating_point():
        raise TypeError(f"frame must be a floating-point tensor, got {frame.dtype}")
    if not bool(torch.isfinite(frame).all()):
        raise ValueError("frame holds NaN or Inf values")


def apply_sensor_noise(
    frame: torch.Tensor,
    noise: NoiseConfig,
    generator: torch.Generator | None = None,
    photons: float | None = None,
) -> torch.Tensor:
    """Draw one noisy sensor reading of the noise-free ``frame``.

    Parameters
    ----------
    frame : torch.Tensor
        Noise-free intensity of any shape, float32 or float64, on any device, normalised to
        a peak of about 1. Negative values are allowed.
    noise : NoiseConfig
        Sensor model (``poisson_gain``, ``gaussian_variance``, ``photons``, ``saturation``,
        ``dark_offset``).
    generator : torch.Generator, optional
        Source of randomness, on the device of ``frame``; the same seed gives the same draw.
        ``None`` uses torch's global generator.
    photons : float, optional
        Expected photo-electrons at intensity 1; overrides ``noise.photons`` and selects
        exact Poisson sampling.

    Returns
    -------
    torch.Tensor
        The reading, same shape, dtype and device as ``frame``, within ``[0, saturation]``.

    Raises
    ------
    ValueError
        If ``frame`` holds NaN or Inf, or ``photons`` is not a positive finite number.

    Examples
    --------
    >>> g = torch.Generator().manual_seed(0)
    >>> y = apply_sensor_noise(torch.full((4, 4), 0.5), NoiseConfig(), generator=g)
    >>> y.shape, bool((y >= 0).all() and (y <= 1).all())
    (torch.Size([4, 4]), True)
    """
    _check_frame(frame)
    count = _photons(noise, photons)
    read_noise = math.sqrt(noise.gaussian_variance)
    if count is None:
        std = noise_std(frame, noise)
        reading = frame + std * _normal(frame, generator)
    else:
        rate = frame.clamp(min=0) * count
        reading = torch.poisson(rate, generator=generator) / count
        if read_noise > 0:
            reading = reading + read_noise * _normal(frame, generator)
    return (reading + noise.dark_offset).clamp(0.0, noise.saturation)


def _normal(like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    return torch.randn(
        like.shape, generator=generator, dtype=like.dtype, device=like.device
    )


def noise_std(
    frame: torch.Tensor, noise: NoiseConfig, photons: float | None = None
) -> torch.Tensor:
    """Per-pixel standard deviation of a reading of ``frame`` (before clipping).

    ``sqrt(max(a·y + b, 0))`` in the mixed model, ``sqrt(max(y, 0) / p + b)`` with a photon
    count ``p``.

    Parameters
    ----------
    frame : torch.Tensor
        Noise-free intensity, floating point, finite.
    noise : NoiseConfig
        Sensor model.
    photons : float, optional
        Overrides ``noise.photons``.

    Returns
    -------
    torch.Tensor
        Same shape, dtype and device as ``frame``.
    """
    _check_frame(frame)
    count = _photons(noise, photons)
    if count is None:
        variance = noise.poisson_gain * frame + noise.gaussian_variance
    else:
        variance = frame / count + noise.gaussian_variance
    return variance.clamp(min=0).sqrt()


def noise_floor(noise: NoiseConfig, photons: float | None = None) -> float:
    """Standard deviation of the noise that a signal must exceed to be told from background.

    ``sqrt(b)`` (the read noise) in the mixed model. With a photon count ``p`` it is the
    standard deviation of a reading of one photo-electron, ``sqrt(1 / p² + b)``: a signal
    below one photon is not detectable even without read noise.

    Parameters
    ----------
    noise : NoiseConfig
        Sensor model.
    photons : float, optional
        Overrides ``noise.photons``.

    Returns
    -------
    float
        In units of the normalised intensity.

    Examples
    --------
    >>> noise_floor(NoiseConfig(gaussian_variance=1e-4))
    0.01
    """
    count = _photons(noise, photons)
    variance = noise.gaussian_variance
    if count is not None:
        variance += 1.0 / count**2
    return math.sqrt(variance)


def quantize(frame: torch.Tensor, full_scale: float, bits: int) -> torch.Tensor:
    """Round a reading in ``[0, full_scale]`` to the ``2**bits - 1`` steps of an ADC.

    Parameters
    ----------
    frame : torch.Tensor
        Reading, already clipped to ``[0, full_scale]``.
    full_scale : float
        The level of the largest code (the saturation level).
    bits : int
        ADC bit depth, 1 to 24.

    Returns
    -------
    torch.Tensor
        Multiples of ``full_scale / (2**bits - 1)``, same shape and dtype.

    Examples
    --------
    >>> quantize(torch.tensor([0.1, 0.4, 0.9]), 1.0, 1).tolist()
    [0.0, 0.0, 1.0]
    """
    if isinstance(bits, bool) or not isinstance(bits, int) or not 1 <= bits <= 24:
        raise ValueError(f"bits must be an integer in 1..24, got {bits!r}")
    if not (math.isfinite(full_scale) and full_scale > 0):
        raise ValueError(f"full_scale must be a finite number > 0, got {full_scale!r}")
    step = full_scale / (2**bits - 1)
    return torch.round(frame / step) * step


def fixed_pattern(
    shape: tuple[int, int],
    rng: np.random.Generator,
    gain_rms: float = 0.0,
    offset_rms: float = 0.0,
    hot_fraction: float = 0.0,
    hot_mean: float = 0.0,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The fixed-pattern maps of one sensor, in the units of the normalised frame.

    Parameters
    ----------
    shape : (int, int)
        Sensor shape.
    rng : numpy.random.Generator
        Fixes the pattern (the same sensor every time for the same seed).
    gain_rms : float
        RMS of the relative gain variation (PRNU); the gain map is ``1 + gain_rms · n``.
    offset_rms : float
        RMS of the dark-signal non-uniformity (DSNU), a zero-mean Gaussian offset map.
    hot_fraction : float
        Fraction of hot pixels, chosen independently per pixel.
    hot_mean : float
        Mean extra dark signal of a hot pixel; the values are exponentially distributed.

    Returns
    -------
    (gain, offset)
        float64 maps of ``shape``, each ``None`` when it would be trivial (1 or 0).
    """
    gain = 1.0 + gain_rms * rng.standard_normal(shape) if gain_rms > 0 else None
    offset = offset_rms * rng.standard_normal(shape) if offset_rms > 0 else np.zeros(shape)
    if hot_fraction > 0 and hot_mean > 0:
        hot = rng.random(shape) < hot_fraction
        offset = offset + hot * rng.exponential(hot_mean, shape)
    return gain, (offset if offset.any() else None)


@dataclass(frozen=True)
class SensorModel:
    """A camera: the noise model plus fixed-pattern maps and an ADC.

    Attributes
    ----------
    noise : NoiseConfig
        Shot and read noise, dark offset and saturation (:func:`apply_sensor_noise`).
    gain : numpy.ndarray or None
        Per-pixel gain (PRNU) of the sensor frame; ``None``: 1 everywhere.
    offset : numpy.ndarray or None
        Per-pixel dark signal (hot pixels and DSNU) in normalised intensity, added to the
        expected signal (so a hot pixel's dark current carries its shot noise).
    adc_bits : int or None
        ADC bit depth (:func:`quantize` over ``[0, noise.saturation]``); ``None``: none.
    """

    noise: NoiseConfig
    gain: np.ndarray | None = None
    offset: np.ndarray | None = None
    adc_bits: int | None = None

    def expected(self, frame: torch.Tensor) -> torch.Tensor:
        """The mean reading of a noise-free sensor ``frame``: gain times signal plus dark signal."""
        if self.gain is not None:
            frame = frame * torch.as_tensor(self.gain, dtype=frame.dtype, device=frame.device)
        if self.offset is not None:
            frame = frame + torch.as_tensor(self.offset, dtype=frame.dtype, device=frame.device)
        return frame

    def read(self, expected: torch.Tensor, generator: torch.Generator | None = None
             ) -> torch.Tensor:  # fmt: skip
        """One noisy, clipped and quantised reading of ``expected`` (any shape: pixel-wise)."""
        reading = apply_sensor_noise(expected, self.noise, generator)
        if self.adc_bits is None:
            return reading
        return quantize(reading, self.noise.saturation, self.adc_bits)


def estimate_noise_std(frame: np.ndarray) -> float:
    """Standard deviation of a frame's pixel noise, estimated from the frame alone.

    Immerkær's estimator: the second difference along the rows of the second difference
    along the columns (the 3 × 3 mask ``[[1, −2, 1], [−2, 4, −2], [1, −2, 1]]``) cancels
    every plane and most of a smooth image, and turns white noise of standard deviation
    ``σ`` into noise of standard deviation ``6σ``; the mean absolute value of Gaussian noise
    is ``√(2/π)`` of its standard deviation. For signal-dependent noise it is the root mean
    variance over the frame; fine structure (single bright pixels, sharp edges) adds to it.

    Parameters
    ----------
    frame : numpy.ndarray
        ``(H, W)``, both at least 3, finite, any real dtype.

    Returns
    -------
    float
        In the frame's units.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ramp = np.add.outer(np.arange(200.0), np.arange(300.0)) / 500
    >>> round(estimate_noise_std(ramp + rng.normal(0, 0.01, ramp.shape)), 3)
    0.01
    """
    values = np.asarray(frame, dtype=np.float64)
    if values.ndim != 2 or min(values.shape) < 3:
        raise ValueError(f"frame must be 2-D with both sides at least 3, got {values.shape}")
    if not np.isfinite(values).all():
        raise ValueError("frame has NaN or Inf values")
    curvature = np.diff(np.diff(values, 2, axis=0), 2, axis=1)
    return float(np.sqrt(np.pi / 2) * np.abs(curvature).mean() / 6)
