"""Departures of the true instrument: validation, JSON, named sets and their effect on frames."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from svcode_core.cli import main
from svcode_core.config import ConfigError, NoiseConfig
from svcode_core.io import read_tiff
from svcode_core.physics.departures import NAMED_SETS, Departures, load_departures
from svcode_core.physics.instrument import Instrument, haze, sensor_model
from svcode_core.physics.noise import SensorModel, quantize
from svcode_core.physics.simulate import Simulator


@pytest.fixture(scope="module")
def tiny():
    from svcode_core.config import SystemConfig, system_from_scale

    base = SystemConfig.preset("cm2-mini")
    optics = dataclasses.replace(base.optics, psf_grid=3, kernel_size=15, airy_radius=1.5,
                                 pupil_samples=32, distortion=0.5)
    return system_from_scale("tiny", (60, 80), 48, 18, 16, optics, 1e-2).validate()


@pytest.fixture(scope="module")
def nominal(tiny):
    return Simulator(tiny)


def bead(size: int) -> np.ndarray:
    obj = np.zeros((size, size), np.float32)
    obj[size // 2, size // 2] = 1.0
    return obj


def spot(frame: np.ndarray, centre: tuple[int, int], radius: int = 7) -> np.ndarray:
    r, c = centre
    return frame[r - radius:r + radius + 1, c - radius:c + radius + 1]


def moments(patch: np.ndarray) -> tuple[float, float, float]:
    """Centroid (row, col) and mean squared radius of a non-negative patch."""
    k = np.arange(patch.shape[0]) - patch.shape[0] // 2
    total = patch.sum()
    row = float(patch.sum(1) @ k / total)
    col = float(patch.sum(0) @ k / total)
    spread = float((patch * ((k[:, None] - row) ** 2 + (k[None, :] - col) ** 2)).sum() / total)
    return row, col, spread


def lens4_centre(system) -> tuple[int, int]:
    """Raw-sensor pixel where lens 4 images the object centre."""
    r, c = system.chief_rays[4]
    return r - system.padding[0], c - system.padding[1]


# ------------------------------------------------------------------ configuration
@pytest.mark.parametrize("name", list(NAMED_SETS))
def test_named_sets_round_trip_through_json(name, tiny, tmp_path):
    departures = Departures.named(name, tiny)
    assert Departures.from_json(departures.to_json()) == departures
    path = departures.save(tmp_path / "d.json")
    assert load_departures(path, tiny) == departures
    assert json.loads(path.read_text())["name"] == name
    assert departures.is_nominal == (name == "none")


def test_pixel_magnitudes_scale_with_the_airy_radius(tiny):
    reference = Departures.named("calibration")
    scaled = Departures.named("calibration", tiny)  # airy radius 1.5 px, reference 2 px
    assert scaled.mla_shift_px == pytest.approx(tuple(0.75 * v for v in reference.mla_shift_px))
    assert scaled.lens_jitter_px == pytest.approx(0.75 * reference.lens_jitter_px)
    assert scaled.mla_rotation_deg == reference.mla_rotation_deg  # an angle: not scaled


@pytest.mark.parametrize("field, value", [
    ("photons", -10.0), ("photons", 0.0), ("coma_error_waves", math.nan),
    ("defocus_waves", math.inf), ("read_noise_e", -1.0), ("hot_pixel_fraction", 1.5),
    ("adc_bits", 0), ("adc_bits", 12.5), ("truth_psf_grid", 1), ("seed", -1),
    ("background_width_px", 0.0), ("mla_rotation_deg", 60.0), ("full_well_e", -5.0),
])  # fmt: skip
def test_bad_values_name_the_field(field, value):
    with pytest.raises(ConfigError, match=f"departures.{field}"):
        Departures(**{field: value}).validate()
    with pytest.raises(ConfigError, match=f"departures.{field}"):
        Departures.from_dict({field: value})


def test_unknown_field_and_bad_shift_are_named():
    with pytest.raises(ConfigError, match="departures.photon_count: unknown field"):
        Departures.from_json('{"photon_count": 100}')
    with pytest.raises(ConfigError, match="departures.mla_shift_px"):
        Departures.from_dict({"mla_shift_px": [1.0]})
    with pytest.raises(ConfigError, match="departures.mla_shift_px"):
        Departures.from_dict({"mla_shift_px": [1.0, math.nan]})
    with pytest.raises(ConfigError, match="'dusk' is neither a named set"):
        load_departures("dusk")


def test_a_shift_that_moves_every_lens_off_the_sensor_is_named(tiny):
    far = Departures(mla_shift_px=(0.0, 70.0))  # every chief ray past the 80-px sensor
    with pytest.raises(ConfigError, match="departures.mla_shift_px: moves every lens"):
        load_departures(far, tiny)
    outside = Departures(mla_shift_px=(0.0, 110.0))  # out of the padded frame too
    with pytest.raises(ConfigError, match="departures.mla_shift_px"):
        Simulator(tiny, departures=outside)


def test_sample_stays_within_the_ranges_and_is_seeded():
    ranges = Departures.named("realistic")
    draws = [ranges.sample(np.random.default_rng([7, i])) for i in range(50)]
    assert draws[3] == ranges.sample(np.random.default_rng([7, 3]))
    for draw in draws:
        for mine, theirs in zip(draw.mla_shift_px, ranges.mla_shift_px, strict=True):
            assert abs(mine) <= abs(theirs)
        assert abs(draw.coma_error_waves) <= abs(ranges.coma_error_waves)
        assert 0 <= draw.background_fraction <= ranges.background_fraction
        assert ranges.photons / 2 <= draw.photons <= 2 * ranges.photons
        assert draw.truth_psf_grid == ranges.truth_psf_grid and draw.adc_bits == 12
    # signs are random: both signs of the defocus occur in 50 draws (chance 2 · 2**-50)
    signs = {np.sign(d.defocus_waves) for d in draws}
    assert {-1.0, 1.0} <= signs
    assert len({d.seed for d in draws}) == len(draws)


# ---------------------------------------------------------------- bit identity
def test_none_is_bit_identical_to_the_nominal_simulator(tiny, nominal):
    obj = np.random.default_rng(0).random((48, 48)).astype(np.float32)
    today = nominal.simulate(obj, seed=4, frames=2)
    none = Simulator(tiny, departures="none").simulate(obj, seed=4, frames=2)
    for name in ("measurement", "views", "demixed", "object"):
        np.testing.assert_array_equal(getattr(none, name), getattr(today, name))


def test_cli_departures_none_is_bit_identical(tiny, tmp_path):
    system_json = tiny.save(tmp_path / "tiny.json")
    common = ["simulate", "--system", str(system_json), "--object", "cells", "--seed", "2"]
    assert main([*common, "--out", str(tmp_path / "today")]) == 0
    assert main([*common, "--departures", "none", "--out", str(tmp_path / "none")]) == 0
    for name in ("measurement", "views", "demixed", "object"):
        today, _, _ = read_tiff(tmp_path / "today" / f"{name}.tif")
        none, system, meta = read_tiff(tmp_path / "none" / f"{name}.tif")
        np.testing.assert_array_equal(none, today)
        assert system == tiny and meta["departures"]["name"] == "none"
    assert Departures.load(tmp_path / "none" / "departures.json").is_nominal


def test_cli_records_departures_and_keeps_the_nominal_system(tiny, tmp_path):
    system_json = tiny.save(tmp_path / "tiny.json")
    custom = Departures(mla_shift_px=(1.0, 0.0), photons=500.0).save(tmp_path / "mine.json")
    out = tmp_path / "out"
    assert main(["simulate", "--system", str(system_json), "--departures", str(custom),
                 "--out", str(out)]) == 0
    _, system, meta = read_tiff(out / "measurement.tif")
    assert system == tiny and meta["departures"]["photons"] == 500.0
    assert Departures.load(out / "departures.json") == Departures.load(custom)
    assert (out / "system.json").read_text() == system_json.read_text()


# -------------------------------------------------------------------- effects
def test_a_shift_moves_the_spots(tiny, nominal):
    shift = (1.3, -0.6)
    obj = bead(48)
    before = nominal.simulate(obj, noise=False).measurement
    after = Simulator(tiny, departures=Departures(mla_shift_px=shift)).simulate(
        obj, noise=False).measurement
    centre = lens4_centre(tiny)
    r0, c0, _ = moments(spot(before, centre))
    r1, c1, _ = moments(spot(after, centre))
    # The shift is a pupil phase: exact but for the light the 15-px window cuts (< 2 %),
    # which can move a centroid by at most 2 % of the 7-px half-window: 0.15 px.
    assert (r1 - r0, c1 - c0) == pytest.approx(shift, abs=0.15)


def test_rotation_moves_outer_lenses_about_the_centre(tiny):
    departures = Departures(mla_rotation_deg=3.0)
    offsets = departures.lens_offsets(tiny)
    np.testing.assert_allclose(offsets[4], 0.0, atol=1e-12)
    radius = 18 * math.sqrt(2)  # corner lens at one pitch diagonally
    np.testing.assert_allclose(np.hypot(*offsets[0]), 2 * radius * math.sin(math.radians(1.5)))


def test_defocus_widens_the_spots(tiny, nominal):
    obj = bead(48)
    centre = lens4_centre(tiny)
    spreads = [moments(spot(nominal.simulate(obj, noise=False).measurement, centre))[2]]
    for waves in (0.5, 1.0):
        sim = Simulator(tiny, departures=Departures(defocus_waves=waves))
        spreads.append(moments(spot(sim.simulate(obj, noise=False).measurement, centre))[2])
    assert spreads[0] < spreads[1] < spreads[2]


def test_background_raises_the_floor(tiny, nominal):
    obj = bead(48)
    clean = nominal.simulate(obj, noise=False).measurement
    hazy = Simulator(tiny, departures=Departures(background_fraction=0.5,
                                                 background_width_px=6.0))
    frame = hazy.simulate(obj, noise=False).measurement
    dark = np.abs(clean) < 1e-6 * clean.max()  # far from the nine spots
    assert dark.sum() > 0.5 * dark.size
    raised = (frame - clean)[dark]
    assert raised.min() > 0 and raised.mean() > 1e-4
    # the haze holds half the light, less what the Gaussian spreads past the sensor edges
    extra = frame.sum() - clean.sum()
    assert 0.3 * clean.sum() < extra <= 0.5 * clean.sum() * (1 + 1e-5)
    np.testing.assert_allclose(haze(torch.ones(3, 40, 40), 0.5, 2.0)[:, 20, 20], 0.5, rtol=1e-6)


def test_integer_shift_keeps_targets_registered_to_the_nominal_views(tiny, nominal):
    obj = np.random.default_rng(1).random((48, 48)).astype(np.float32)
    base = nominal.simulate(obj, noise=False)
    moved = Simulator(tiny, departures=Departures(mla_shift_px=(2.0, 0.0))).simulate(
        obj, noise=False)
    np.testing.assert_allclose(moved.demixed[4, 10:38, 5:43], base.demixed[4, 8:36, 5:43],
                               rtol=1e-4, atol=1e-6)


def test_photon_count_sets_the_noise_variance():
    photons, level, shape = 200.0, 0.5, (400, 400)
    sensor = SensorModel(NoiseConfig(photons=photons, gaussian_variance=0.0, saturation=10.0))
    generator = torch.Generator().manual_seed(0)
    reading = sensor.read(torch.full(shape, level, dtype=torch.float64), generator)
    n, rate = reading.numel(), photons * level
    expected = level / photons
    # sample variance of n Poisson(λ)/p draws: relative s.d. sqrt((2 + 1/λ) / (n - 1))
    tolerance = 5 * expected * math.sqrt((2 + 1 / rate) / (n - 1))
    assert float(reading.var()) == pytest.approx(expected, abs=tolerance)
    assert float(reading.mean()) == pytest.approx(level, abs=5 * math.sqrt(expected / n))


def test_departed_camera_noise_matches_the_photon_level(tiny):
    departures = Departures(photons=300.0, read_noise_e=2.0, full_well_e=3000.0)
    sim = Simulator(tiny, departures=departures)
    obj = np.full((48, 48), 0.3, np.float32)
    clean = torch.as_tensor(sim.simulate(obj, noise=False).measurement, dtype=torch.float64)
    assert float(clean.max()) < 5  # far from the saturation level 10: no clipping
    readings = torch.as_tensor(sim.simulate(obj, seed=3, frames=20).measurement,
                               dtype=torch.float64)
    lit = clean > 0.05
    variance = clean / 300.0 + (2.0 / 300.0) ** 2
    z2 = ((readings - clean) ** 2 / variance)[:, lit]
    # mean of n squared standardised residuals: 1 ± sqrt((2 + 1/λ_min) / n) per s.d.
    n, rate = z2.numel(), 300.0 * float(clean[lit].min())
    assert float(z2.mean()) == pytest.approx(1.0, abs=5 * math.sqrt((2 + 1 / rate) / n))


def test_hot_pixels_fixed_pattern_and_adc(tiny):
    departures = Departures(photons=1000.0, hot_pixel_fraction=0.02, hot_pixel_e=500.0,
                            prnu_percent=2.0, adc_bits=8, full_well_e=2000.0, seed=5)
    shape = (200, 300)
    sensor = sensor_model(tiny.noise, departures, shape)
    n = shape[0] * shape[1]
    hot = sensor.offset > 0
    assert abs(hot.sum() - 0.02 * n) < 5 * math.sqrt(n * 0.02 * 0.98)
    assert float(sensor.offset[hot].mean()) == pytest.approx(0.5, rel=5 / math.sqrt(hot.sum()))
    assert float(sensor.gain.std()) == pytest.approx(0.02, rel=5 * math.sqrt(0.5 / n))
    assert sensor.noise.saturation == 2.0
    again = sensor_model(tiny.noise, departures, shape)
    np.testing.assert_array_equal(again.offset, sensor.offset)  # fixed for the sensor
    reading = sensor.read(torch.full(shape, 1.5, dtype=torch.float64),
                          torch.Generator().manual_seed(0))
    steps = reading / (2.0 / 255)
    np.testing.assert_allclose(steps, torch.round(steps), atol=1e-9)
    assert float(reading.max()) <= 2.0
    assert quantize(torch.tensor([0.74, 0.76]), 1.0, 1).tolist() == [1.0, 1.0]


def test_instrument_reuses_the_operator_when_only_the_camera_changes(tiny):
    optics = Departures(defocus_waves=0.3)
    first = Instrument.build(tiny, optics)
    second = Instrument.build(tiny, dataclasses.replace(optics, photons=100.0), reuse=first)
    assert second.operator is first.operator
    third = Instrument.build(tiny, Departures(defocus_waves=0.2), reuse=first)
    assert third.operator is not first.operator
    sim = Simulator(tiny, departures=optics)
    assert sim.with_departures(dataclasses.replace(optics, photons=50.0)).operator is sim.operator


def test_pupil_offset_and_defocus_of_one_psf(tiny):
    from svcode_core.physics.optics import lens_psfs, system_psfs

    base = lens_psfs(tiny, 4, [(0.0, 0.0)])[0]
    np.testing.assert_array_equal(lens_psfs(tiny, 4, [(0.0, 0.0)], defocus=0.0)[0], base)
    moved = lens_psfs(tiny, 4, [(0.0, 0.0)], offset=(0.4, -0.3))[0]
    r0, c0, s0 = moments(base)
    r1, c1, _ = moments(moved)
    # a pupil phase moves the PSF exactly; only the light cut by the window (< 2 %) can
    # pull the centroid, by at most 2 % of the 7-px half-window
    assert (r1 - r0, c1 - c0) == pytest.approx((0.4, -0.3), abs=0.15)
    assert moments(lens_psfs(tiny, 4, [(0.0, 0.0)], defocus=0.7)[0])[2] > s0
    with pytest.raises(ValueError, match="defocus must be finite"):
        lens_psfs(tiny, 4, defocus=math.nan)
    with pytest.raises(ValueError, match="offsets must have shape"):
        system_psfs(tiny, offsets=np.zeros((3, 2)))
