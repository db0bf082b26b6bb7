"""The bundled model has no bands or edge strips: row and column means follow the truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_svcode._sample_data import SAMPLE_KINDS, SAMPLE_SEED
from svcode_core import Reconstructor, SystemConfig
from svcode_core.phantoms import make_object
from svcode_core.physics.simulate import Simulator

BAND = 16  # pixels per band: profiles are compared band by band
MAX_FACTOR = 1.5  # a band may be at most 1.5x brighter or darker than the frame's gain says


def band_ratios(estimate: np.ndarray, truth: np.ndarray, axis: int) -> np.ndarray:
    """Per band of rows (axis 1 averaged) or columns (axis 0 averaged), the ratio of the
    estimate's mean to the truth's, divided by the whole frame's ratio; bands whose truth
    holds less than a quarter of the average signal are left out (NaN)."""
    est = estimate.mean(axis).reshape(-1, BAND).mean(1)
    ref = truth.mean(axis).reshape(-1, BAND).mean(1)
    gain = estimate.mean() / truth.mean()
    return np.where(ref >= 0.25 * truth.mean(), est / np.maximum(ref, 1e-12) / gain, np.nan)


@pytest.fixture(scope="module")
def bundled():
    """The ``cm2-mini`` simulator and the bundled model's reconstructor, built once."""
    torch.set_num_threads(2)
    system = SystemConfig.preset("cm2-mini")
    return system, Simulator(system), Reconstructor.pretrained(system)


@pytest.mark.xfail(strict=True, reason="the bundled model (4 epochs, 160 matched frames) "
                   "shows a bright band and a dark right edge; see its model card")
@pytest.mark.parametrize("kind", SAMPLE_KINDS)
def test_row_and_column_profiles_follow_the_truth(kind, bundled):
    system, simulator, reconstructor = bundled
    truth = make_object(kind, system.sub_view_size, SAMPLE_SEED)
    frame = simulator.simulate(truth, seed=0).measurement
    estimate = reconstructor.reconstruct(frame).reconstruction
    for axis in (0, 1):
        ratios = band_ratios(estimate, truth, axis)
        ratios = ratios[np.isfinite(ratios)]
        assert ratios.size and np.all(ratios <= MAX_FACTOR) and np.all(ratios >= 1 / MAX_FACTOR)
