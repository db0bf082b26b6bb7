"""Phantoms: range, determinism, spot rendering against a supersampled reference, real images."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import skimage.io
import tifffile
from scipy.special import erf, erfc
from skimage.measure import label

from svcode_core.phantoms import (
    KINDS,
    _render_spots,
    _render_tree,
    beads,
    from_image,
    isolated_cells,
    make_object,
    normalize_object,
)


@pytest.mark.parametrize("kind", list(KINDS))
def test_kinds_range_dtype_shape_and_determinism(kind):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a = make_object(kind, 72, 3)
    assert a.shape == (72, 72) and a.dtype == np.float32
    assert a.min() >= 0 and a.max() <= 1 and a.max() > 0
    np.testing.assert_array_equal(a, make_object(kind, 72, 3))
    np.testing.assert_array_equal(a, make_object(kind, 72, np.random.default_rng(3)))
    assert not np.array_equal(a, make_object(kind, 72, 4))


def test_unknown_kind_lists_kinds():
    with pytest.raises(ValueError, match="beads, cells, vessels, neurons, skimage, isolated-cells, "
                       "mixed, mixed-isolated"):
        make_object("galaxies", 64, 0)


def test_isolated_cells_are_few_large_objects_in_a_dark_field():
    for seed in range(5):
        obj = isolated_cells(384, np.random.default_rng(seed), count=(3.0, 3.0), radius=30.0)
        regions = label(obj > 0.05)
        assert 1 <= regions.max() <= 3  # three cells, some may touch
        assert (obj < 1e-3).mean() > 0.7  # dark around them
        # a cell of semi-axes (30, >= 18) covers >= pi 30 18 px at half its level or more
        assert np.bincount(regions.ravel())[1:].max() > np.pi * 30 * 18 * 0.5



def test_bad_size_and_ranges_raise():
    with pytest.raises(ValueError, match="size"):
        make_object("cells", 4, 0)
    with pytest.raises(ValueError, match="radius"):
        make_object("beads", 64, 0, radius=(2.0, 1.0))
    with pytest.raises(ValueError, match="brightness"):
        make_object("beads", 64, 0, brightness=(0.5, 2.0))
    with pytest.raises(ValueError, match="density"):
        make_object("cells", 64, 0, density=(1.0, 2.0, 3.0))


def _reference_spot(size, centre, sigma, oversample=41):
    """Pixel-box integral of a unit-peak Gaussian by brute-force supersampling."""
    offsets = (np.arange(oversample) + 0.5) / oversample - 0.5
    grid = (np.arange(size)[:, None] + offsets[None, :]).ravel()
    rows = np.exp(-0.5 * ((grid - centre[0]) / sigma) ** 2).reshape(size, oversample).mean(1)
    cols = np.exp(-0.5 * ((grid - centre[1]) / sigma) ** 2).reshape(size, oversample).mean(1)
    return np.outer(rows, cols)


@pytest.mark.parametrize("sigma", [0.15, 0.6, 2.5])
def test_spot_matches_supersampled_reference(sigma):
    centre = np.array([[10.3, 12.74]])
    spot = _render_spots(24, centre, np.array([sigma]), np.array([1.0]))
    reference = _reference_spot(24, centre[0], sigma)
    # Peak 1 for a centred spot: scale the reference the same way.
    reference /= _reference_spot(3, (1.0, 1.0), sigma)[1, 1]
    np.testing.assert_allclose(spot, reference, atol=2e-3 * reference.max())
    # The box integrals telescope: the total is 1 / erf(0.5 / (sqrt(2) sigma))^2, less the
    # tails beyond the 4-sigma window (at most erfc(2 sqrt(2)) per axis).
    expected = erf(0.5 / (np.sqrt(2) * sigma)) ** -2
    assert expected * (1 - 2 * erfc(2 * np.sqrt(2))) <= spot.sum() <= expected * (1 + 1e-12)
    if sigma >= 1:  # box sampling moves the centroid of narrower spots (aliasing)
        total = spot.sum()
        centroid = [(spot.sum(1) * np.arange(24)).sum() / total,
                    (spot.sum(0) * np.arange(24)).sum() / total]
        np.testing.assert_allclose(centroid, centre[0], atol=1e-4)  # window asymmetry


def test_spots_near_and_beyond_border():
    centres = np.array([[-0.4, 5.0], [5.0, 15.6], [-50.0, 3.0], [3.0, 200.0]])
    img = _render_spots(16, centres, np.full(4, 1.0), np.ones(4))
    assert img.shape == (16, 16) and np.isfinite(img).all()
    assert img[0, 5] > 0.5 and img[5, 15] > 0.5


def test_tube_cross_section_peaks_at_brightness():
    step = 0.5
    cols = np.arange(-20.0, 60.0, step)
    points = np.stack([np.full(cols.size, 20.0), cols], 1)
    for radius in (0.5, 1.0, 4.0):
        tree = (points, np.full(cols.size, radius), np.full(cols.size, step))
        img = _render_tree(40, tree, 0.7)
        assert img[:, 20].max() == pytest.approx(0.7, rel=1e-3)
        # Off the pixel centre the peak pixel holds less, never more.
        shifted = (points + [0.4, 0.0], *tree[1:])
        assert 0.35 < _render_tree(40, shifted, 0.7)[:, 20].max() < 0.7


def test_bead_density_spans_sparse_to_dense():
    def count(density):
        rng = np.random.default_rng(1)
        img = beads(128, rng, density=density, radius=1.2, brightness=1.0)
        return label(img > 0.2).max()

    sparse, dense = count(2.0), count(60.0)  # about 3 and 100 beads expected
    assert 1 <= sparse <= 8
    assert dense >= 50


def test_beads_keep_absolute_brightness():
    img = beads(64, np.random.default_rng(0), density=3.0, radius=2.0, brightness=0.01)
    # Peak 0.01 for a bead centred on a pixel; sub-pixel offsets lower the brightest pixel.
    assert 0.007 < img.max() <= 0.01


def _odd_test_image():
    """61 × 101 image: a bright stripe outside the centred square, a blob inside it."""
    image = np.full((61, 101), 10, dtype=np.uint16)
    image[:, :8] = 60000  # outside columns 20..80: must be cropped away
    image[25:36, 45:56] = 1000
    return image


def _check_centre_crop(obj, size):
    assert obj.shape == (size, size) and obj.dtype == np.float32
    assert obj[size // 2, size // 2] == pytest.approx(1.0, abs=1e-3)
    assert obj[:, : size // 4].max() < 1e-3  # no stripe: the left columns were cropped


def test_from_image_tiff_and_png_non_square(tmp_path):
    image = _odd_test_image()
    tifffile.imwrite(tmp_path / "odd.tif", image)
    skimage.io.imsave(tmp_path / "odd.png", (image // 256).astype(np.uint8), check_contrast=False)
    for name in ("odd.tif", "odd.png"):
        _check_centre_crop(from_image(tmp_path / name, 48), 48)
    _check_centre_crop(from_image(str(tmp_path / "odd.tif"), 200), 200)  # upsampling


def test_from_image_rgb_is_luminance():
    grey = np.random.default_rng(0).random((40, 50))
    rgb = np.zeros((40, 50, 3))
    rgb[..., 1] = grey
    expected = from_image(grey, 32)
    np.testing.assert_allclose(from_image(rgb, 32), expected, atol=1e-6)
    rgba = np.concatenate([rgb, np.full((40, 50, 1), 0.3)], -1)
    np.testing.assert_allclose(from_image(rgba, 32), expected, atol=1e-6)
    with pytest.raises(ValueError, match="2-D"):
        from_image(np.zeros((5, 40, 50)), 32)
    rgb8 = (rgb * 255).astype(np.uint8)
    np.testing.assert_allclose(from_image(rgb8, 32), from_image(rgb8[..., 1], 32), atol=1e-6)


@pytest.mark.parametrize("value", [0.0, 3.7, 255])
def test_constant_image_gives_zeros_without_warnings(value):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not normalize_object(np.full((20, 30), value)).any()
        assert not normalize_object(np.full((20, 30), value), background_sigma=3.0).any()
        assert not from_image(np.full((20, 30), value, dtype=np.float32), 16).any()


def test_non_finite_raises():
    bad = np.ones((10, 10))
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        normalize_object(bad)
    bad[3, 3] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        from_image(bad, 16)


def test_normalize_percentiles_analytic():
    img = np.arange(101, dtype=np.float64)  # percentile p is the value p
    out = normalize_object(img, background_percentile=10, upper_percentile=90)
    np.testing.assert_allclose(out, np.clip((img - 10) / 80, 0, 1), rtol=1e-6)
    with pytest.raises(ValueError, match="percentile"):
        normalize_object(img, background_percentile=50, upper_percentile=40)


def test_normalize_smooth_background_removes_uneven_illumination():
    rows, cols = np.mgrid[0:96, 0:96]
    illumination = 0.5 * np.exp(-((rows - 30) ** 2 + (cols - 60) ** 2) / (2 * 40.0**2))
    spots = _render_spots(96, np.array([[20.0, 20.0], [70.0, 50.0]]), np.full(2, 1.0),
                          np.ones(2))
    out = normalize_object(illumination + spots, background_sigma=6.0)
    assert out[20, 20] == pytest.approx(1.0, abs=0.1) and out[70, 50] > 0.85
    far = (np.hypot(rows - 20, cols - 20) > 8) & (np.hypot(rows - 70, cols - 50) > 8)
    assert out[far].max() < 0.05


@pytest.mark.parametrize("name", ["cell.png", "ihc.png", "microaneurysms.png"])
def test_held_out_images_are_dark_background_objects(name):
    from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image

    assert name in HELD_OUT_IMAGES
    obj = held_out_image(name, 64)
    assert obj.shape == (64, 64) and obj.dtype == np.float32
    assert obj.min() == 0 and obj.max() == 1
    assert np.median(obj) < 0.35  # mostly dark, like a fluorescence image
    with pytest.raises(ValueError, match="unknown held-out image"):
        held_out_image("camera.png", 64)
