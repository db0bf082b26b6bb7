"""The bundled model has no bands or edge strips, with or without the periphery refinement:
row and column means follow the truth as closely as the instrument allows (LSV-ADMM on the
same frame is the measure of that)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_svcode._sample_data import SAMPLE_KINDS, SAMPLE_SEED
from svcode_core import Reconstructor, SystemConfig
from svcode_core.methods.baselines import BaselineReconstructor
from svcode_core.phantoms import make_object
from svcode_core.physics.simulate import Simulator

BAND = 16  # pixels per band: profiles are compared band by band
#: a band may be this much brighter or darker than the frame's gain says ...
MAX_FACTOR = 1.5
#: ... or this much further off than LSV-ADMM's band: some bands are ambiguous for the
#: instrument itself (object rows 144 px apart share sensor rows through adjacent lens
#: rows), where LSV-ADMM is off by up to 3x on the samples
MAX_FACTOR_BEYOND_ADMM = 1.25
ADMM_ITERATIONS = 50
#: the network alone and with its periphery refined by 10 LSV-ADMM iterations
REFINEMENTS = (0, 10)


def band_ratios(estimate: np.ndarray, truth: np.ndarray, axis: int) -> np.ndarray:
    """Per band of rows (axis 1 averaged) or columns (axis 0 averaged), the ratio of the
    estimate's mean to the truth's, divided by the whole frame's ratio; bands whose truth
    holds less than a quarter of the average signal are left out (NaN).

    Examples
    --------
    >>> truth = np.ones((32, 32))
    >>> estimate = truth.copy()
    >>> estimate[:, 16:] *= 3.0  # the right band three times too bright
    >>> band_ratios(estimate, truth, axis=0).round(2).tolist()
    [0.5, 1.5]
    """
    est = estimate.mean(axis).reshape(-1, BAND).mean(1)
    ref = truth.mean(axis).reshape(-1, BAND).mean(1)
    gain = estimate.mean() / truth.mean()
    return np.where(ref >= 0.25 * truth.mean(), est / np.maximum(ref, 1e-12) / gain, np.nan)


def allowed_log_error(reference_ratios: np.ndarray) -> np.ndarray:
    """Per band, the largest ``|log ratio|`` accepted: ``log MAX_FACTOR``, or the reference
    method's own error plus ``log MAX_FACTOR_BEYOND_ADMM`` where that is larger.

    Examples
    --------
    >>> np.exp(allowed_log_error(np.array([1.0, 3.0, 0.5]))).round(3).tolist()
    [1.5, 3.75, 2.5]
    """
    own = np.abs(np.log(reference_ratios)) + np.log(MAX_FACTOR_BEYOND_ADMM)
    return np.maximum(np.log(MAX_FACTOR), np.nan_to_num(own, nan=0.0))


@pytest.fixture(scope="module")
def bundled():
    """The ``cm2-mini`` simulator, the bundled model's reconstructors without and with the
    periphery refinement, and LSV-ADMM's reconstruction of each sample (computed once)."""
    torch.set_num_threads(2)
    system = SystemConfig.preset("cm2-mini")
    admm = BaselineReconstructor("admm", system, rank=3, iterations=ADMM_ITERATIONS,
                                 tolerance=0.0)
    reconstructors = {refine: Reconstructor.pretrained(system, refine_periphery=refine)
                      for refine in REFINEMENTS}  # fmt: skip
    references: dict[str, np.ndarray] = {}

    def reference(kind: str, frame: np.ndarray) -> np.ndarray:
        if kind not in references:
            references[kind] = admm.reconstruct(frame).reconstruction
        return references[kind]

    return system, Simulator(system), reconstructors, reference


#: (sample, refinement) cases on which the bundled model is off by more than that (measured)
KNOWN_BANDS = {
    ("beads", 0): "rows 64-79 at 0.55 of the truth (0.62, 0.56 and 0.77 with the three "
    "models bundled before): less light is spread between the beads than in the truth's "
    "band",
}


@pytest.mark.parametrize("refine", REFINEMENTS)
@pytest.mark.parametrize("kind", SAMPLE_KINDS)
def test_row_and_column_profiles_follow_the_truth(kind, refine, bundled, request):
    if (kind, refine) in KNOWN_BANDS:
        request.applymarker(pytest.mark.xfail(
            strict=True, reason=KNOWN_BANDS[kind, refine] + "; see the model card"))
    system, simulator, reconstructors, admm_reference = bundled
    truth = make_object(kind, system.sub_view_size, SAMPLE_SEED)
    frame = simulator.simulate(truth, seed=0).measurement
    estimate = reconstructors[refine].reconstruct(frame).reconstruction
    reference = admm_reference(kind, frame)
    off = {}
    for axis, name in ((1, "row bands"), (0, "column bands")):
        ratios = band_ratios(estimate, truth, axis)
        assert np.isfinite(ratios).any()
        allowed = allowed_log_error(band_ratios(reference, truth, axis))
        bad = np.flatnonzero(np.abs(np.log(ratios)) > allowed)  # NaN bands compare False
        if bad.size:
            off[name] = {int(band): round(float(ratios[band]), 2) for band in bad}
    assert not off, off  # e.g. {'column bands': {0: 0.29, 23: 0.23}}: the edge strips
