"""Bead detection and sizing (svcode_bench.beads) on cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from svcode_bench.beads import (
    BeadPhantom,
    BeadScore,
    bead_phantom,
    detect_beads,
    fit_bead_sigma,
    match_beads,
    score_beads,
)
from svcode_core.phantoms import _render_spots


def _field(centres, sigma=1.0, size=48) -> BeadPhantom:
    """A phantom with beads exactly where the test puts them."""
    centres = np.asarray(centres, dtype=np.float64)
    sigmas = np.full(len(centres), sigma)
    image = _render_spots(size, centres, sigmas, np.ones(len(centres)))
    return BeadPhantom(image.astype(np.float32), centres, sigmas)


def test_phantom_is_seeded_exact_and_apart():
    one, again = bead_phantom(200, 20, seed=3), bead_phantom(200, 20, seed=3)
    np.testing.assert_array_equal(one.image, again.image)
    np.testing.assert_array_equal(one.centres, again.centres)
    assert len(one.centres) == 80  # 20 per 100 × 100 on 200 × 200, exactly
    gaps = np.hypot(*(one.centres[:, None] - one.centres[None]).transpose(2, 0, 1))
    assert gaps[np.triu_indices(80, 1)].min() >= 4.0  # two radii of a sigma-1 bead
    assert np.all((one.centres >= 1.5) & (one.centres <= 200 - 2.5))
    assert bead_phantom(200, 20, seed=4).centres[0, 0] != one.centres[0, 0]
    # an unplaceable request says so instead of looping
    with pytest.raises(ValueError, match="cannot place"):
        bead_phantom(20, 1000, seed=0)


def test_truth_itself_is_all_found_at_the_right_size():
    field = bead_phantom(128, 20, seed=0)
    score = score_beads(field.image, field)
    assert score.n_true == score.n_found == score.n_matched == len(field.centres)
    assert (score.recall, score.precision, score.f1) == (1.0, 1.0, 1.0)
    assert score.size_errors.size == len(field.centres)
    # exact but for the tails of close neighbours inside a fit window
    assert score.size_error < 1e-4 and np.abs(score.size_errors).max() < 5e-3


def test_empty_image_finds_nothing():
    field = bead_phantom(64, 10, seed=1)
    score = score_beads(np.zeros_like(field.image), field)
    assert score.n_found == score.n_matched == 0
    assert score.recall == 0.0 and score.f1 == 0.0
    # no detection made: precision is undefined (NaN), not a perfect 1
    assert math.isnan(score.precision) and math.isnan(score.size_error)
    # a uniform haze is background too, whatever its level
    assert detect_beads(np.full((64, 64), 0.3)).shape == (0, 2)


def test_pair_closer_than_the_resolution_counts_once():
    # two beads 2.5 px apart, blurred by a point spread of sigma 1.5: one peak between them
    field = _field([[24.0, 22.75], [24.0, 25.25]], size=48)
    blurred = ndimage.gaussian_filter(field.image.astype(np.float64), 1.5)
    found = detect_beads(blurred)
    assert len(found) == 1 and np.allclose(found[0], [24, 24], atol=1)
    score = score_beads(blurred, field)
    assert (score.n_found, score.n_matched) == (1, 1)
    assert score.recall == 0.5 and score.precision == 1.0
    assert score.size_bias > 0.5  # the merged spot is far wider than one bead
    # resolved (8 px apart) the same blur leaves both
    apart = _field([[24.0, 20.0], [24.0, 28.0]], size=48)
    assert score_beads(ndimage.gaussian_filter(apart.image, 1.5), apart).recall == 1.0


def test_spurious_peaks_lower_precision_only():
    field = _field([[10.0, 10.0], [10.0, 38.0], [38.0, 10.0]], size=48)
    extra = _field([[38.0, 38.0], [24.0, 24.0]], size=48)  # nowhere near a true bead
    score = score_beads(field.image + extra.image, field)
    assert (score.n_true, score.n_found, score.n_matched) == (3, 5, 3)
    assert score.recall == 1.0 and score.precision == pytest.approx(3 / 5)
    assert score.f1 == pytest.approx(2 * 3 / (3 + 5))


def test_matching_is_one_to_one_within_the_radius():
    truth = np.array([[10.0, 10.0], [10.0, 13.0]])
    # one detection between two beads serves only one of them
    beads, hits = match_beads(np.array([[10.0, 11.5]]), truth, 2.0)
    assert len(beads) == len(hits) == 1
    # two detections, each closest to the other's bead, are still both paired
    beads, hits = match_beads(np.array([[10.0, 11.2], [10.0, 12.0]]), truth, 2.0)
    assert sorted(beads.tolist()) == [0, 1]
    # just outside the radius is a miss; a per-bead radius is honoured
    assert len(match_beads(np.array([[10.0, 12.01]]), truth[:1], 2.0)[0]) == 0
    assert len(match_beads(np.array([[10.0, 12.5]]), truth[:1], np.array([3.0]))[0]) == 1
    assert len(match_beads(np.empty((0, 2)), truth, 2.0)[0]) == 0


def test_size_fit_reads_blur_and_ignores_scale_and_offset():
    field = _field([[20.3, 19.6]], sigma=1.0, size=40)
    blurred = ndimage.gaussian_filter(field.image.astype(np.float64), 1.0)
    # pixel-integrated sigma 1, blurred by sigma 1 (up to the sampling): about sqrt(2)
    assert fit_bead_sigma(blurred, (20, 20)) == pytest.approx(math.sqrt(2), rel=0.03)
    assert fit_bead_sigma(5.0 * field.image + 2.0, (20, 20)) == pytest.approx(1.0, abs=1e-3)


def test_pooled_score_adds_counts():
    a = BeadScore(10, 8, 7, np.array([0.1, 0.2]))
    b = BeadScore(5, 0, 0, np.empty(0))
    pooled = BeadScore.pooled([a, b])
    assert (pooled.n_true, pooled.n_found, pooled.n_matched) == (15, 8, 7)
    assert pooled.recall == pytest.approx(7 / 15) and pooled.precision == pytest.approx(7 / 8)
    assert pooled.size_error == pytest.approx(0.15)
