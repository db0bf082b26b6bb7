"""The bar target and the line-pair criterion (svcode_bench.resolution)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from svcode_bench.resolution import (
    GROUP_GAP,
    PERIODS,
    PERIODS_AIRY_RADIUS,
    POSITIONS,
    RAYLEIGH_DIP,
    bar_dip,
    bar_target,
    finest_resolved,
    periods_for,
)
from svcode_core.config import SystemConfig


def test_every_group_of_the_truth_is_resolved_at_every_period():
    for period in PERIODS:
        image, groups = bar_target(384, period)
        assert set(groups) == set(POSITIONS)
        for pair in groups.values():
            for group in pair:
                # coverage-rendered bars: 1 at bar centres; gaps are 0 except where a
                # half-pixel bar edge shares the gap's pixel (2.5- and 5-px periods)
                assert bar_dip(image, group) >= 0.5


def test_blur_resolves_the_coarse_bars_and_merges_the_fine_ones():
    """A Gaussian blur of σ: bars of period p show a dip of about the fundamental's
    contrast, (4/π)·exp(-2π²σ²/p²): at σ = 1.5 px about 0.01 at 3 px and 0.6 at 8 px; merged
    bars give a hump whose gaps lie above the bars' mean (a negative dip)."""
    dips = {}
    for period in PERIODS:
        image, groups = bar_target(384, period, {"centre": (0.0, 0.0)})
        blurred = gaussian_filter(image.astype(np.float64), 1.5)
        dips[period] = min(bar_dip(blurred, g) for g in groups["centre"])
    assert dips[3.0] < RAYLEIGH_DIP < dips[8.0]
    assert finest_resolved(dips) in (4.0, 5.0, 6.0)
    coarse = PERIODS[2:]  # from 3 px on the dip grows with the period
    assert all(dips[p] < dips[q] for p, q in zip(coarse, coarse[1:], strict=False))


def test_a_flat_image_has_no_dip_and_an_empty_one_resolves_nothing():
    image, groups = bar_target(384, 4.0)
    vertical, _ = groups["ring"]
    assert bar_dip(np.ones_like(image), vertical) == pytest.approx(0.0)
    assert bar_dip(np.zeros_like(image), vertical) == 0.0
    assert finest_resolved({p: 0.0 for p in PERIODS}) is None


def test_a_target_that_does_not_fit_is_refused():
    with pytest.raises(ValueError, match="do not fit"):
        bar_target(48, 8.0)


def test_the_paper_scale_target_scales_with_the_psf_and_fits_the_field():
    """At cm2-v2 the Airy radius is 4× cm2-mini's: periods and spacing 4× the mini's, and
    the coarsest target still fits the 2400-px field with every group resolved."""
    system = SystemConfig.preset("cm2-v2")
    scale = system.optics.airy_radius / PERIODS_AIRY_RADIUS
    assert scale == 4.0
    periods = periods_for(system.optics.airy_radius)
    assert periods == tuple(4 * p for p in PERIODS)
    image, groups = bar_target(system.sub_view_size, periods[-1], gap=GROUP_GAP * scale)
    assert all(bar_dip(image, group) >= 0.5 for pair in groups.values() for group in pair)
