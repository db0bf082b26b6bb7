"""The same-content comparison of the centre and the outer ring."""

from __future__ import annotations

import numpy as np
import pytest

from svcode_bench.field_position import (
    half_field_shifts,
    moved_scene,
    same_content_zones,
)
from svcode_core.evaluation.metrics import field_zones, psnr


def _scene(size: int) -> np.ndarray:
    """Bright in the middle, dark towards the edge: zone PSNRs differ by content alone."""
    rng = np.random.default_rng(1)
    axis = np.linspace(-1, 1, size)
    return np.exp(-4 * (axis[:, None] ** 2 + axis[None, :] ** 2)) * rng.random((size, size))


@pytest.mark.parametrize("size", [32, 33])  # odd: a move and its inverse differ
def test_a_position_bound_error_gives_its_analytic_gap(size):
    truth = _scene(size)
    zones = field_zones(size)
    error = 0.02 * zones["centre"] + 0.05 * zones["ring"]  # fixed to the field, not the scene
    moved = {s: moved_scene(truth, s) + error for s in half_field_shifts(size)}
    result = same_content_zones(truth, truth + error, moved)
    assert result.centre == pytest.approx(-20 * np.log10(0.02), abs=1e-9)
    assert result.ring == pytest.approx(-20 * np.log10(0.05), abs=1e-9)
    assert result.gap == pytest.approx(20 * np.log10(2.5), abs=1e-9)
    assert result.pixels > 0


def test_a_part_of_the_ring_is_compared_alone():
    """An error only in the right-hand columns: the ring's part there shows all of it, the
    rest of the ring none."""
    size = 32
    truth = _scene(size)
    right = np.zeros((size, size), dtype=bool)
    right[:, -6:] = True
    error = 0.01 + 0.04 * right
    moved = {s: moved_scene(truth, s) + error for s in half_field_shifts(size)}
    inside = same_content_zones(truth, truth + error, moved, ring=right)
    outside = same_content_zones(truth, truth + error, moved, ring=~right)
    assert inside.gap == pytest.approx(20 * np.log10(5), abs=1e-9)
    assert outside.gap == pytest.approx(0.0, abs=1e-9)
    assert inside.pixels + outside.pixels == same_content_zones(truth, truth + error,
                                                                moved).pixels
    with pytest.raises(ValueError, match="ring must be a boolean image"):
        same_content_zones(truth, truth, moved, ring=right[:8])


@pytest.mark.parametrize("size", [32, 33])
def test_an_error_bound_to_the_content_has_no_gap(size):
    """10 % too bright everywhere: the zone PSNRs differ (the centre holds the bright
    content), the same-content comparison does not."""
    truth = _scene(size)
    moved = {s: 1.1 * moved_scene(truth, s) for s in half_field_shifts(size)}
    result = same_content_zones(truth, 1.1 * truth, moved)
    assert result.gap == pytest.approx(0.0, abs=1e-9)
    zones = field_zones(size)
    zone_gap = (psnr(truth, 1.1 * truth, 1.0, zones["centre"])
                - psnr(truth, 1.1 * truth, 1.0, zones["ring"]))
    assert zone_gap < -10  # the bright centre scores far lower in the zone PSNRs


def test_a_misplaced_reconstruction_shows():
    """Moved estimates returned unmoved match no content: their error is large."""
    truth = _scene(32)
    unmoved = {s: truth for s in half_field_shifts(32)}
    assert same_content_zones(truth, truth + 1e-3, unmoved).ring < 30


def test_bad_input_raises():
    truth = _scene(32)
    with pytest.raises(ValueError, match="at least one moved scene"):
        same_content_zones(truth, truth, {})
    with pytest.raises(ValueError, match="one shape"):
        same_content_zones(truth, truth, {(16, 0): truth[:16]})
    with pytest.raises(ValueError, match="NaN"):
        same_content_zones(truth, truth, {(16, 0): np.full_like(truth, np.nan)})
    with pytest.raises(ValueError, match="no content pixel moves"):
        same_content_zones(truth, truth, {(0, 0): truth})
