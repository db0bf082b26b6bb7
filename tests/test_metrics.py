import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from svcode_core.evaluation.metrics import edge_columns, field_zones, image_quality, psnr, ssim


@pytest.fixture
def pair():
    rng = np.random.default_rng(0)
    truth = rng.random((40, 40))
    return truth, truth + 0.05 * rng.standard_normal((40, 40))


def test_psnr_and_ssim_match_skimage(pair):
    truth, estimate = pair
    assert psnr(truth, estimate, 1.0) == pytest.approx(
        peak_signal_noise_ratio(truth, estimate, data_range=1.0), rel=1e-12
    )
    assert ssim(truth, estimate, 2.0) == pytest.approx(
        structural_similarity(truth, estimate, data_range=2.0), rel=1e-12
    )


def test_masked_psnr_is_psnr_of_the_selected_pixels(pair):
    truth, estimate = pair
    mask = np.zeros(truth.shape, bool)
    mask[5:15, 20:35] = True
    expected = peak_signal_noise_ratio(truth[mask], estimate[mask], data_range=1.0)
    assert psnr(truth, estimate, 1.0, mask) == pytest.approx(expected, rel=1e-12)


def test_identical_images_give_infinite_psnr_and_unit_ssim(pair):
    truth, _ = pair
    quality = image_quality(truth, truth, data_range=1.0)
    assert math.isinf(quality["psnr"]) and math.isinf(quality["psnr_ring"])
    assert quality["ssim"] == pytest.approx(1.0)


def test_field_zones_geometry():
    size = 301
    zones = field_zones(size)
    centre, ring = zones["centre"], zones["ring"]
    assert centre[150, 150] and not ring[150, 150]
    assert ring[0, 0] and ring[0, 150] and not centre[0, 0]
    assert not (centre & ring).any()
    # areas: a disc of radius 0.5, and the square minus a disc of radius 0.8 (side 2)
    assert centre.mean() == pytest.approx(math.pi * 0.25 / 4, abs=0.01)
    assert ring.mean() == pytest.approx(1 - math.pi * 0.64 / 4, abs=0.01)


def test_edge_columns_are_the_outer_columns_only():
    strips = edge_columns(64, 16)
    assert strips[:, :16].all() and strips[:, 48:].all() and not strips[:, 16:48].any()
    assert strips.mean() == 0.5
    for width in (0, 33):
        with pytest.raises(ValueError, match="do not fit"):
            edge_columns(64, width)


def test_ring_error_shows_only_in_ring_psnr():
    truth = np.zeros((64, 64))
    estimate = truth.copy()
    estimate[0, :] = 0.5  # an edge artefact
    quality = image_quality(truth, estimate, data_range=1.0)
    assert math.isinf(quality["psnr_centre"])
    assert quality["psnr_ring"] < quality["psnr"]


@pytest.mark.parametrize(
    "truth, estimate, data_range, message",
    [
        (np.zeros((8, 8)), np.full((8, 8), np.nan), 1.0, "NaN"),
        (np.zeros((8, 8)), np.zeros((8, 9)), 1.0, "shape"),
        (np.zeros((8, 8)), np.zeros((8, 8)), 0.0, "data_range"),
        (np.zeros((8, 8)), np.zeros((8, 8)), math.inf, "data_range"),
    ],
)
def test_bad_inputs_raise(truth, estimate, data_range, message):
    with pytest.raises(ValueError, match=message):
        image_quality(truth, estimate, data_range)
