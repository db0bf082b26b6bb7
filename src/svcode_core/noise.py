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
"""

from __future__ import annotations

import math

import torch

from .config import NoiseConfig

__all__ = ["apply_sensor_noise", "noise_floor", "noise_std"]


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
