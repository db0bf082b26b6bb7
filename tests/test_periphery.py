"""The periphery refinement of SV-CoDe's reconstruction (:mod:`svcode_core.methods.periphery`):
the weight ramp, the blend against an independently run LSV-ADMM, what it does for the
periphery, and its option on the reconstructor."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from svcode_core.methods.base import FrameProgress
from svcode_core.methods.baselines import LsvAdmm, settings_for
from svcode_core.methods.periphery import (
    PERIPHERY_RAMP,
    REFINE_RANK,
    PeripheryRefinement,
    periphery_weight,
)
from svcode_core.methods.svcode import Reconstructor
from svcode_core.methods.tiling import Cancelled
from svcode_core.network import SVCoDe
from svcode_core.phantoms import make_object
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import crop_to_sensor, pad_sensor_frame

ITERATIONS = 3


def test_the_weight_rises_with_the_field_radius():
    size = 64
    weight = periphery_weight(size)
    # the first and last pixel centres at -1 and 1: the radius from the pixel indices
    axis = 2 * np.arange(size) / (size - 1) - 1
    radius = np.hypot(axis[:, None], axis[None, :])
    low, high = PERIPHERY_RAMP
    assert np.all(weight[radius <= low] == 0) and np.all(weight[radius >= high] == 1)
    between = (radius > low) & (radius < high)
    np.testing.assert_allclose(weight[between], (radius[between] - low) / (high - low),
                               rtol=1e-12)  # fmt: skip
    assert np.array_equal(weight, weight.T)
    np.testing.assert_allclose(weight, weight[::-1], rtol=0, atol=1e-12)  # mirrored rounding
    with pytest.raises(ValueError, match="ramp must rise"):
        periphery_weight(size, (0.8, 0.5))


@pytest.fixture(scope="module")
def scene(tiny_system):
    """A noiseless frame of a cells phantom and a poor start (the object dimmed, with an
    offset)."""
    operator = CM2Operator.from_system(tiny_system)
    truth = make_object("cells", tiny_system.sub_view_size, np.random.default_rng(3))
    truth = 0.3 * truth.astype(np.float64) / truth.max()
    padded = operator.forward(torch.as_tensor(truth, dtype=operator.lenses.dtype))
    frame = crop_to_sensor(padded, tiny_system).numpy()
    start = (0.6 * truth + 0.05).astype(np.float32)
    return truth, frame, start


def test_the_blend_of_lsv_admm_from_the_start(tiny_system, scene):
    """Inside half the field radius the start itself, in the corners LSV-ADMM run from it
    (here run directly with the solver), in between their mix by the weight."""
    _, frame, start = scene
    out = PeripheryRefinement(tiny_system, ITERATIONS)(frame, start)
    operator = CM2Operator.from_system(tiny_system, rank=REFINE_RANK)
    defaults = settings_for(tiny_system)
    solver = LsvAdmm(operator, defaults.tv_weight, defaults.rho, defaults.cg_iterations,
                     defaults.adaptive_rho, defaults.check_every)  # fmt: skip
    padded = pad_sensor_frame(torch.as_tensor(frame, dtype=operator.lenses.dtype), tiny_system)
    x0 = torch.as_tensor(start, dtype=operator.lenses.dtype)
    refined = solver.solve(padded, x0, ITERATIONS, tolerance=0.0).x.numpy()
    weight = periphery_weight(tiny_system.sub_view_size)
    expected = weight * refined + (1 - weight) * start
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[weight == 0], start[weight == 0])
    # float32 solver: a few units in the last place of values of order 1
    np.testing.assert_allclose(out, expected, rtol=0, atol=8 * np.finfo(np.float32).eps)


def test_the_periphery_comes_closer_to_the_truth(tiny_system, scene):
    truth, frame, start = scene
    out = PeripheryRefinement(tiny_system, ITERATIONS)(frame, start)
    edge = periphery_weight(tiny_system.sub_view_size) == 1
    before = np.mean((start[edge] - truth[edge]) ** 2)
    assert np.mean((out[edge] - truth[edge]) ** 2) < 0.5 * before


def test_the_reconstructor_refines_the_reconstruction_only(tiny_system, tiny_model_config,
                                                           scene):  # fmt: skip
    torch.manual_seed(0)
    model = SVCoDe(tiny_model_config)
    _, frame, _ = scene
    plain = Reconstructor(model, tiny_system).reconstruct(frame, return_views=True)
    refined = Reconstructor(model, tiny_system, refine_periphery=ITERATIONS).reconstruct(
        frame, return_views=True)
    centre = periphery_weight(tiny_system.sub_view_size) == 0
    np.testing.assert_array_equal(refined.reconstruction[centre], plain.reconstruction[centre])
    assert not np.array_equal(refined.reconstruction, plain.reconstruction)
    np.testing.assert_array_equal(refined.views, plain.views)
    assert refined.timings["refine"] > 0 and plain.timings["refine"] == 0
    assert np.isfinite(refined.reconstruction).all() and refined.reconstruction.min() >= 0


def test_progress_announces_the_refinement_and_cancel_skips_it(tiny_system, tiny_model_config,
                                                                scene):  # fmt: skip
    _, frame, _ = scene
    rec = Reconstructor(SVCoDe(tiny_model_config), tiny_system, refine_periphery=ITERATIONS)
    steps = list(rec.iter_reconstruct(np.stack([frame, frame])))
    assert [s.refining for s in steps].count(True) == 2
    assert steps[-1] == FrameProgress(1, 2, len(rec.grid), len(rec.grid), refining=True)
    calls = []
    rec.refinement = lambda *args: calls.append(args)
    cancel = threading.Event()
    run = rec.iter_reconstruct(frame, cancel=cancel)
    while not next(run).refining:
        pass
    cancel.set()  # while the consumer handles the announcement
    with pytest.raises(Cancelled):
        next(run)
    assert calls == []


@pytest.mark.parametrize("value", [-1, 2.5, True, None])
def test_bad_iteration_counts_are_refused(tiny_system, tiny_model_config, value):
    model = SVCoDe(tiny_model_config)
    with pytest.raises(ValueError, match="refine_periphery must be a whole number"):
        Reconstructor(model, tiny_system, refine_periphery=value)
    if value is not None:
        with pytest.raises(ValueError, match="positive integer"):
            PeripheryRefinement(tiny_system, value)


@pytest.mark.parametrize("case", ["constant", "one pixel", "saturated", "1e-4 dim", "uint16"])
def test_stiff_frames_give_a_finite_non_negative_blend(tiny_system, case):
    shape = tiny_system.sensor_shape
    frame = {"constant": np.full(shape, 0.3, dtype=np.float32),
             "one pixel": np.zeros(shape, dtype=np.float32),
             "saturated": np.ones(shape, dtype=np.float32),
             "1e-4 dim": np.full(shape, 1e-4, dtype=np.float32),
             "uint16": np.full(shape, 20_000, dtype=np.uint16)}[case]
    if case == "one pixel":
        frame[shape[0] // 2, shape[1] // 2] = 1.0
    start = np.full((tiny_system.sub_view_size,) * 2, 0.1, dtype=np.float32)
    out = PeripheryRefinement(tiny_system, ITERATIONS)(frame, start)
    assert np.isfinite(out).all() and out.min() >= 0
