"""Sensor noise: moments against the model, clipping, offsets, seeding, extreme inputs."""

from __future__ import annotations

import math

import pytest
import torch

from svcode_core.config import NoiseConfig
from svcode_core.physics.noise import apply_sensor_noise, noise_floor, noise_std

N_DRAWS = 200_000
Z = 5.0  # tolerance in standard errors


def _draw(value: float, noise: NoiseConfig, photons: float | None = None, seed: int = 0):
    frame = torch.full((N_DRAWS,), value, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    return apply_sensor_noise(frame, noise, generator=g, photons=photons)


def _check_moments(x: torch.Tensor, mean: float, variance: float) -> None:
    """Sample mean and variance agree with the model within Z standard errors.

    The standard error of the sample variance is estimated from the sample's fourth
    central moment, ``sqrt((m4 - s⁴) / n)``, which holds for any distribution.
    """
    n = x.numel()
    m = x.mean().item()
    centred = x - m
    s2 = centred.pow(2).mean().item()
    m4 = centred.pow(4).mean().item()
    assert abs(m - mean) < Z * math.sqrt(variance / n)
    assert abs(s2 - variance) < Z * math.sqrt((m4 - s2**2) / n)


@pytest.mark.parametrize("y", [0.1, 0.3, 0.9])  # >= 6 sigma above the clip at 0
def test_mixed_model_mean_and_variance(y):
    noise = NoiseConfig(poisson_gain=2e-3, gaussian_variance=1e-4, saturation=10.0)
    _check_moments(_draw(y, noise), y, 2e-3 * y + 1e-4)


def test_default_calibration_moments():
    noise = NoiseConfig(saturation=10.0)
    y = 0.5
    _check_moments(_draw(y, noise), y, noise.poisson_gain * y + noise.gaussian_variance)


@pytest.mark.parametrize("photons", [1.0, 20.0, 1e5])
def test_poisson_mode_mean_and_variance(photons):
    b = 1e-6
    noise = NoiseConfig(gaussian_variance=b, saturation=1e3)
    y = 0.4
    _check_moments(_draw(y, noise, photons=photons), y, y / photons + b)


def test_poisson_mode_from_config_is_integer_counts():
    noise = NoiseConfig(gaussian_variance=0.0, photons=3.0, saturation=100.0)
    x = _draw(1.0, noise)
    counts = x * 3.0
    assert torch.equal(counts, counts.round())
    # One photon per pixel: P(0 photons) = e^-1.
    zeros = (_draw(1.0, noise, photons=1.0) == 0).double().mean().item()
    p = math.exp(-1.0)
    assert abs(zeros - p) < Z * math.sqrt(p * (1 - p) / N_DRAWS)


def test_noise_std_matches_empirical():
    noise = NoiseConfig(poisson_gain=1e-3, gaussian_variance=4e-4, saturation=10.0)
    frame = torch.tensor([0.0, 0.5, 2.0], dtype=torch.float64)
    expected = torch.sqrt(1e-3 * frame + 4e-4)
    torch.testing.assert_close(noise_std(frame, noise), expected)
    torch.testing.assert_close(
        noise_std(frame, noise, photons=10.0), torch.sqrt(frame / 10.0 + 4e-4)
    )
    assert noise_std(torch.tensor([-1.0]), noise).item() == 0.0


def test_noise_floor():
    assert noise_floor(NoiseConfig(gaussian_variance=1e-4)) == pytest.approx(1e-2)
    assert noise_floor(NoiseConfig(gaussian_variance=0.0, photons=100.0)) == pytest.approx(1e-2)
    assert noise_floor(NoiseConfig(gaussian_variance=3e-4), photons=10.0) == pytest.approx(
        math.sqrt(1e-2 + 3e-4)
    )


def test_saturation_clips():
    noise = NoiseConfig(saturation=0.8)
    x = _draw(2.0, noise)
    assert x.max().item() == 0.8
    assert (x == 0.8).all()
    # Poisson mode clips too.
    assert _draw(2.0, noise, photons=50.0).max().item() == 0.8


def test_dark_offset_adds():
    noiseless = NoiseConfig(poisson_gain=0.0, gaussian_variance=0.0, dark_offset=0.05)
    frame = torch.linspace(0.0, 0.9, 11)
    torch.testing.assert_close(apply_sensor_noise(frame, noiseless), frame + 0.05)
    noise = NoiseConfig(poisson_gain=1e-3, gaussian_variance=1e-4, dark_offset=0.1, saturation=5)
    _check_moments(_draw(0.3, noise), 0.4, 1e-3 * 0.3 + 1e-4)


def test_same_seed_same_draw_different_seed_differs():
    noise = NoiseConfig()
    frame = torch.rand(32, 32, generator=torch.Generator().manual_seed(1))
    for photons in (None, 100.0):
        a = apply_sensor_noise(frame, noise, torch.Generator().manual_seed(5), photons)
        b = apply_sensor_noise(frame, noise, torch.Generator().manual_seed(5), photons)
        c = apply_sensor_noise(frame, noise, torch.Generator().manual_seed(6), photons)
        assert torch.equal(a, b)
        assert not torch.equal(a, c)


def test_zero_frame_is_clipped_read_noise():
    x = _draw(0.0, NoiseConfig(gaussian_variance=1e-4))
    assert x.min().item() == 0.0
    # Half the draws are negative and clipped; the rest are half-normal with sigma 1e-2.
    zeros = (x == 0).double().mean().item()
    assert abs(zeros - 0.5) < Z * math.sqrt(0.25 / N_DRAWS)
    assert x.mean().item() == pytest.approx(1e-2 / math.sqrt(2 * math.pi), rel=0.02)


def test_negative_input_gives_no_nan():
    noise = NoiseConfig(poisson_gain=1e-2, gaussian_variance=1e-6)
    frame = torch.tensor([-1.0, -1e-3, -1e-30, 0.0], dtype=torch.float64)
    for photons in (None, 10.0):
        x = apply_sensor_noise(frame, noise, torch.Generator().manual_seed(0), photons)
        assert torch.isfinite(x).all()
        assert (x >= 0).all()
    assert apply_sensor_noise(torch.tensor([-1.0]), noise).item() == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("photons", [None, 1.0, 1e5])
def test_dtype_and_shape_preserved(dtype, photons):
    frame = torch.rand(3, 5, 7, dtype=dtype)
    x = apply_sensor_noise(frame, NoiseConfig(), torch.Generator().manual_seed(0), photons)
    assert x.dtype == dtype and x.shape == frame.shape
    assert torch.isfinite(x).all()


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_input_raises(bad):
    frame = torch.zeros(4)
    frame[2] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        apply_sensor_noise(frame, NoiseConfig())
    with pytest.raises(ValueError, match="NaN or Inf"):
        noise_std(frame, NoiseConfig())


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="photons"):
        apply_sensor_noise(torch.zeros(3), NoiseConfig(), photons=0.0)
    with pytest.raises(ValueError, match="photons"):
        noise_floor(NoiseConfig(), photons=float("nan"))
    with pytest.raises(TypeError, match="floating"):
        apply_sensor_noise(torch.zeros(3, dtype=torch.int64), NoiseConfig())
