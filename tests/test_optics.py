import dataclasses
import json

import numpy as np
import pytest
import tifffile
from scipy.special import j1, jn_zeros

from svcode_core.config import OpticsConfig, SystemConfig
from svcode_core.physics.optics import (
    AIRY_ZERO,
    lens_psf,
    lens_psfs,
    psf_grid_positions,
    system_psfs,
    transmission,
)
from svcode_core.physics.psf_io import load_measured_psfs, positions_path, save_psfs

NO_ABERRATIONS = dict(
    spherical=0.0,
    coma=0.0,
    astigmatism=0.0,
    field_curvature=0.0,
    distortion=0.0,
    vignetting_angle=0.0,
    pupil_clip=0.0,
)


def with_optics(system: SystemConfig, **changes) -> SystemConfig:
    return system.replace(optics=dataclasses.replace(system.optics, **changes))


def ideal(system: SystemConfig, **changes) -> SystemConfig:
    return system.replace(optics=OpticsConfig(**{**NO_ABERRATIONS, **changes}))


def offsets(k: int) -> np.ndarray:
    return np.arange(k) - k // 2


def centroid(psf: np.ndarray) -> np.ndarray:
    x = offsets(psf.shape[0])
    return np.array([psf.sum(1) @ x, psf.sum(0) @ x]) / psf.sum()


def field(system: SystemConfig, lens: int, point) -> tuple[float, np.ndarray]:
    f = np.asarray(point, dtype=float) - np.asarray(system.lens_axes[lens])
    return float(np.hypot(*f)) / system.optics.field_radius, f / np.hypot(*f)


# ---------------------------------------------------------------- diffraction
def test_airy_zero_is_the_first_zero_of_j1_over_pi():
    assert AIRY_ZERO == pytest.approx(jn_zeros(1, 1)[0] / np.pi, rel=4 * np.finfo(float).eps)
    assert abs(j1(np.pi * AIRY_ZERO)) < 1e-15


@pytest.mark.parametrize("samples", [128, 256])
def test_on_axis_psf_is_the_airy_pattern(mini_system, samples):
    airy = 3.0  # first zero on a pixel centre
    system = ideal(mini_system, kernel_size=25, airy_radius=airy, pupil_samples=samples)
    psf = lens_psf(system, 4, (0.0, 0.0))
    x = offsets(25)
    v = np.pi * AIRY_ZERO * np.hypot(*np.meshgrid(x, x, indexing="ij")) / airy
    safe = np.where(v > 0, v, 1.0)
    pattern = np.where(v > 0, (2 * j1(safe) / safe) ** 2, 1.0)
    scale = AIRY_ZERO / (2 * airy)  # pupil units per pixel, energy π spread over 1/scale² px
    pattern *= np.pi * scale**2
    # The sampled pupil's soft edge is an O(1/M) perturbation (measured 0.66/M of the peak).
    assert np.abs(psf - pattern).max() < 1.0 / samples * pattern.max()
    assert psf[12, 12 + 3] < 1e-3 * psf.max()  # the first dark ring at airy_radius


def test_energy_over_one_period_is_the_transmission(mini_system):
    # With the window exactly one period of the sampled-pupil field, the discrete Parseval
    # identity holds to round-off; airy_radius 0.9 also exercises sub-pixel oversampling.
    for period, samples in ((45, 32), (23, 32)):
        airy = period * AIRY_ZERO / samples
        system = ideal(
            mini_system,
            kernel_size=period,
            airy_radius=airy,
            pupil_samples=samples,
            coma=0.3,
            astigmatism=0.2,
            field_curvature=0.1,
            distortion=0.7,
            vignetting_angle=20.0,
            pupil_clip=0.5,
        )
        points = np.array([[0.0, 0.0], [0.3, -0.4], [1.0, 1.0], [-1.0, 0.2]])
        energy = lens_psfs(system, 4, points).sum(axis=(1, 2))
        expected = transmission(system, 4, points)
        np.testing.assert_allclose(energy, expected, rtol=1e-12)
        assert expected[0] == 1.0 and np.all(expected[1:] < 1)


def test_transmission_formula(mini_system):
    system = with_optics(mini_system, vignetting_angle=30.0, pupil_clip=0.5)
    h, _ = field(system, 4, (0.0, 1.0))
    cos4 = np.cos(np.arctan(h * np.tan(np.radians(30.0)))) ** 4
    d = 0.5 * h  # centre distance of two unit discs
    lens_area = 2 * np.arccos(d / 2) - d / 2 * np.sqrt(4 - d * d)
    got = transmission(system, 4, [(0.0, 1.0)])[0]
    assert got == pytest.approx(cos4 * lens_area / np.pi, rel=1e-14)
    # discs that no longer meet let nothing through, and the PSF is zero, not NaN
    dark = with_optics(
        mini_system, pupil_clip=2.0, coma=0.0, astigmatism=0.0, field_curvature=0.0, distortion=0.0
    )
    assert transmission(dark, 0, [(1.0, 1.0)])[0] == 0.0
    psf = lens_psf(dark, 0, (1.0, 1.0))
    assert np.all(psf == 0.0)


# ----------------------------------------------------------------- symmetries
def test_psf_on_the_lens_axis_is_symmetric(mini_system):
    psf = lens_psf(mini_system, 0, mini_system.lens_axes[0])
    np.testing.assert_allclose(psf, psf[::-1], atol=1e-15)
    np.testing.assert_allclose(psf, psf[:, ::-1], atol=1e-15)
    np.testing.assert_allclose(psf, psf.T, atol=1e-15)
    assert np.unravel_index(np.argmax(psf), psf.shape) == (16, 16)


def test_mirrored_field_points_give_mirrored_psfs(mini_system):
    points = np.array([[0.4, 0.7], [0.4, -0.7], [-0.4, 0.7]])
    psfs = lens_psfs(mini_system, 4, points)
    np.testing.assert_allclose(psfs[1], psfs[0][:, ::-1], atol=1e-15)
    np.testing.assert_allclose(psfs[2], psfs[0][::-1], atol=1e-15)
    assert np.abs(psfs[0] - psfs[0][:, ::-1]).max() > 0.1 * psfs[0].max()


def test_lenses_see_the_same_psf_at_the_same_field(mini_system):
    # the PSF depends on r - a_ℓ only: lens 0 at a_0 + f equals lens 4 at a_4 + f
    f = np.array([0.2, -0.3])
    a0 = np.asarray(mini_system.lens_axes[0])
    np.testing.assert_allclose(
        lens_psf(mini_system, 0, a0 + f), lens_psf(mini_system, 4, f), atol=1e-15
    )


# ---------------------------------------------------------------- aberrations
def test_coma_shifts_the_centroid_along_the_field(mini_system):
    system = ideal(mini_system, kernel_size=101, pupil_samples=128, coma=0.5)
    point = (0.5, -0.8)
    h, direction = field(system, 4, point)
    c = centroid(lens_psf(system, 4, point))
    # centroid = mean wavefront slope / scale; for W131 h ρ³cosθ the mean slope is W131 h
    expected = 0.5 * h * direction * 2 * system.optics.airy_radius / AIRY_ZERO
    np.testing.assert_allclose(c, expected, rtol=0.03)  # the window truncates coma's tail
    assert abs(c[0] * direction[1] - c[1] * direction[0]) < 0.01 * np.hypot(*c)


def test_distortion_moves_the_centroid(mini_system):
    system = ideal(mini_system, kernel_size=101, pupil_samples=128, distortion=3.0)
    point = (0.5, -0.8)
    h, direction = field(system, 4, point)
    psf = lens_psf(system, 4, point)
    np.testing.assert_allclose(centroid(psf), 3.0 * h**3 * direction, atol=2e-3)
    # a pure shift: the same Airy pattern, moved by a sub-pixel amount
    assert psf.sum() == pytest.approx(lens_psf(system, 4, (0.0, 0.0)).sum(), abs=2e-3)


def test_astigmatism_elongates_along_the_field(mini_system):
    system = ideal(mini_system, astigmatism=0.8)
    psf = lens_psf(system, 1, (1.0, 0.0))  # field along +v from lens 1's axis
    x = offsets(psf.shape[0])
    var_v = psf.sum(1) @ x**2 / psf.sum()
    var_u = psf.sum(0) @ x**2 / psf.sum()
    assert var_v > 2 * var_u


def test_clipped_pupil_makes_the_psf_asymmetric(mini_system):
    # Without aberrations |FT(pupil)|² is point-symmetric even when clipped; with defocus the
    # clipped pupil (centred d/2 along the field) sees a tilted wavefront and the spot moves.
    system = ideal(mini_system, pupil_clip=0.8, field_curvature=0.4)
    point = (1.0, 0.0)  # field along +v from lens 1's axis
    h, _ = field(system, 1, point)
    psf = lens_psf(system, 1, point)
    np.testing.assert_allclose(psf, psf[:, ::-1], atol=1e-15)  # mirror across the field line
    assert np.abs(psf - psf[::-1]).max() > 0.05 * psf.max()
    # mean slope 2·W220·h²·(d/2), d = pupil_clip·h, over pixels per pupil unit scale
    scale = AIRY_ZERO / (2 * system.optics.airy_radius)
    assert centroid(psf)[0] == pytest.approx(0.4 * h**2 * 0.8 * h / scale, rel=0.02)
    unclipped = lens_psf(with_optics(system, pupil_clip=0.0), 1, point)
    np.testing.assert_allclose(unclipped, unclipped[::-1], atol=1e-15)


def test_transmission_and_energy_fall_with_field(mini_system):
    t = np.linspace(0.0, 1.0, 8)
    points = np.stack([t, 0.7 * t], axis=1)  # a radial line from lens 4's axis
    trans = transmission(mini_system, 4, points)
    energy = lens_psfs(mini_system, 4, points).sum(axis=(1, 2))
    assert trans[0] == 1.0
    assert np.all(np.diff(trans) < 0)
    assert np.all(np.diff(energy) < 0)
    assert np.all(energy <= trans)


def test_default_psfs_fit_the_window(mini_system):
    centre = lens_psf(mini_system, 4, (0.0, 0.0)).sum()
    assert 0.98 < centre <= 1.0  # Airy rings beyond 8 radii are lost, honestly
    psfs = system_psfs(mini_system)
    grid = mini_system.optics.psf_grid
    assert psfs.shape == (9, grid * grid, 33, 33) and psfs.dtype == np.float64
    assert np.all(psfs >= 0) and np.isfinite(psfs).all()


def test_grid_positions(mini_system):
    grid = psf_grid_positions(mini_system)
    assert grid.shape == (49, 2)
    t = np.linspace(-1, 1, 7)
    np.testing.assert_array_equal(grid[8], [t[1], t[1]])
    np.testing.assert_array_equal(grid[:7, 0], -1.0)  # v is the outer index
    np.testing.assert_array_equal(grid[:7, 1], t)


# ---------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("lens", [-1, 9, 1.0, True, "4"])
def test_bad_lens_raises(mini_system, lens):
    with pytest.raises(ValueError, match="lens"):
        lens_psf(mini_system, lens, (0.0, 0.0))


@pytest.mark.parametrize("position", [(np.nan, 0.0), (0.0, np.inf), (0.1,), "ab", [[0, 0]]])
def test_bad_position_raises(mini_system, position):
    with pytest.raises(ValueError, match="position"):
        lens_psf(mini_system, 4, position)
    with pytest.raises(ValueError, match="positions"):
        transmission(mini_system, 4, [position])


def test_undersampled_pupil_raises(mini_system):
    system = with_optics(mini_system, pupil_samples=16)
    with pytest.raises(ValueError, match="pupil_samples"):
        lens_psf(system, 0, (1.0, 1.0))


# ----------------------------------------------------------------- PSF import
def test_save_load_round_trip(tiny_system, tmp_path):
    psfs = system_psfs(tiny_system)
    psfs[3, 2] = 0.0  # a PSF truncated away entirely is allowed
    tiff, positions = save_psfs(tmp_path / "psfs.tif", psfs, tiny_system)
    assert positions == positions_path(tiff)
    loaded = load_measured_psfs(tiff, positions, tiny_system)
    assert loaded.shape == psfs.shape and loaded.dtype == np.float64
    np.testing.assert_allclose(loaded, psfs.astype(np.float32), rtol=0, atol=0)
    # the positions also come as CSV with a header, or as an array; the stack flattened
    grid = psf_grid_positions(tiny_system)
    csv = tmp_path / "positions.csv"
    csv.write_text("v,u\n" + "\n".join(f"{v!r},{u!r}" for v, u in grid.tolist()) + "\n")
    flat = tmp_path / "flat.tif"
    tifffile.imwrite(flat, psfs.reshape(-1, *psfs.shape[2:]).astype(np.float32))
    np.testing.assert_array_equal(load_measured_psfs(flat, csv, tiny_system), loaded)
    np.testing.assert_array_equal(load_measured_psfs(flat, grid, tiny_system), loaded)


def test_tiny_negatives_are_clipped_large_ones_raise(tiny_system, tmp_path):
    psfs = system_psfs(tiny_system)
    grid = psf_grid_positions(tiny_system)
    psfs[0, 0, 0, 0] = -1e-4 * psfs.max()
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, psfs.astype(np.float32))
    assert load_measured_psfs(path, grid, tiny_system)[0, 0, 0, 0] == 0.0
    psfs[2, 5, 1, 3] = -0.01 * psfs.max()
    tifffile.imwrite(path, psfs.astype(np.float32))
    with pytest.raises(ValueError, match=r"negative .* \(lens, node, row, col\) = \(2, 5, 1, 3\)"):
        load_measured_psfs(path, grid, tiny_system)


def test_bad_stacks_raise(tiny_system, tmp_path):
    psfs = system_psfs(tiny_system)
    grid = psf_grid_positions(tiny_system)
    path = tmp_path / "bad.tif"
    cases = [
        (psfs[:, :, 1:-1, 1:-1], "optics.kernel_size"),
        (psfs[:, :, :-1, :-1], "odd"),
        (psfs[:8], "shape"),
        (np.where(np.arange(9)[:, None, None, None] == 4, np.nan, psfs), "NaN"),
    ]
    for stack, message in cases:
        tifffile.imwrite(path, stack.astype(np.float32))
        with pytest.raises(ValueError, match=message):
            load_measured_psfs(path, grid, tiny_system)


def test_bad_positions_raise(tiny_system, tmp_path):
    psfs = system_psfs(tiny_system)
    tiff, _ = save_psfs(tmp_path / "psfs.tif", psfs, tiny_system)
    grid = psf_grid_positions(tiny_system)
    moved = grid.copy()
    moved[4, 1] += 1e-4
    with pytest.raises(ValueError, match=r"positions\[4\]"):
        load_measured_psfs(tiff, moved, tiny_system)
    with pytest.raises(ValueError, match="PSF grid"):
        load_measured_psfs(tiff, grid[:-1], tiny_system)
    bad_json = tmp_path / "p.json"
    bad_json.write_text(json.dumps({"points": grid.tolist()}))
    with pytest.raises(ValueError, match="positions"):
        load_measured_psfs(tiff, bad_json, tiny_system)
    with pytest.raises(FileNotFoundError):
        load_measured_psfs(tiff, tmp_path / "missing.json", tiny_system)
