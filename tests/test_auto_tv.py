"""LSV-ADMM's TV weight from the frame (``tv_weight="auto"``): the noise estimate, the
weight's scaling, the reconstructor and the command line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svcode_core.cli import build_parser
from svcode_core.methods.baselines import BaselineReconstructor, LsvAdmm, settings_for
from svcode_core.methods.baselines.admm import AUTO_TV_GAIN, auto_tv_weight
from svcode_core.methods.build import cli_arguments
from svcode_core.phantoms import make_object
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import crop_to_sensor, pad_sensor_frame
from svcode_core.physics.noise import estimate_noise_std


def _smooth(shape: tuple[int, int]) -> np.ndarray:
    rows, cols = np.indices(shape, dtype=np.float64)
    return 0.5 + 0.3 * np.exp(-((rows - shape[0] / 2) ** 2 + (cols - shape[1] / 3) ** 2)
                              / (2 * 40.0**2))  # fmt: skip


@pytest.mark.parametrize("sigma", [1e-3, 1e-2, 0.1])
def test_noise_estimate_of_white_noise_on_a_smooth_image(sigma):
    shape = (300, 400)
    noisy = _smooth(shape) + np.random.default_rng(1).normal(0, sigma, shape)
    # about 117,000 samples of |k|: the estimate's relative spread is about 0.4 %
    assert estimate_noise_std(noisy) == pytest.approx(sigma, rel=0.03)


def test_noise_estimate_of_planes_and_bad_frames():
    plane = np.add.outer(3.0 * np.arange(50), -2.0 * np.arange(60))
    assert estimate_noise_std(plane) < 64 * np.finfo(float).eps * np.abs(plane).max()
    assert estimate_noise_std(np.full((5, 5), 7, dtype=np.uint16)) == 0.0
    with pytest.raises(ValueError, match="at least 3"):
        estimate_noise_std(np.zeros((2, 10)))
    with pytest.raises(ValueError, match="NaN or Inf"):
        estimate_noise_std(np.full((4, 4), np.nan))


def test_auto_weight_is_the_noise_gain_times_gamma_and_scales_with_the_frame():
    rng = np.random.default_rng(2)
    photons = 200
    frame = rng.poisson(photons * 0.3 * np.ones((200, 300))) / photons
    # shot noise: variance / mean = 1 / photons
    assert auto_tv_weight(frame) == pytest.approx(AUTO_TV_GAIN / photons, rel=0.05)
    assert auto_tv_weight(40 * frame) / auto_tv_weight(frame) == pytest.approx(40, rel=1e-12)
    assert auto_tv_weight(np.zeros((10, 10))) == 0.0


@pytest.fixture(scope="module")
def dim_frame(tiny_system):
    """A cells phantom seen with 30 photons a pixel at intensity 1 (float64)."""
    operator = CM2Operator.from_system(tiny_system)
    truth = make_object("cells", tiny_system.sub_view_size, np.random.default_rng(3))
    truth = 0.8 * truth.astype(np.float64) / truth.max()
    clean = crop_to_sensor(operator.forward(torch.as_tensor(truth, dtype=operator.lenses.dtype)),
                           tiny_system).double().numpy()  # fmt: skip
    photons = 30
    frame = np.random.default_rng(4).poisson(photons * np.clip(clean, 0, None)) / photons
    return truth, frame


def test_the_reconstructor_solves_with_the_frames_weight(tiny_system, dim_frame):
    _, frame = dim_frame
    rec = BaselineReconstructor("admm", tiny_system, tv_weight="auto", iterations=5,
                                tolerance=0.0)  # fmt: skip
    auto = rec.reconstruct(frame).reconstruction
    defaults = settings_for(tiny_system)
    padded = pad_sensor_frame(torch.as_tensor(frame, dtype=rec.operator.lenses.dtype),
                              tiny_system)  # fmt: skip

    def solve(tv_weight):
        solver = LsvAdmm(rec.operator, tv_weight, defaults.rho, defaults.cg_iterations,
                         defaults.adaptive_rho, defaults.check_every)  # fmt: skip
        return solver.solve(padded, None, 5, tolerance=0.0)

    direct = solve("auto")
    np.testing.assert_array_equal(auto, direct.x.float().numpy())
    # the frame's weight, from the operator-precision frame; the fixed one gives the same
    eps = torch.finfo(rec.operator.lenses.dtype).eps
    assert direct.tv_weight == pytest.approx(auto_tv_weight(frame), rel=100 * eps)
    assert direct.tv_weight > 10 * defaults.tv_weight  # the weight is not the default
    fixed = solve(direct.tv_weight)
    np.testing.assert_array_equal(fixed.x.numpy(), direct.x.numpy())
    assert fixed.objective == direct.objective


def test_the_solver_takes_the_weight_from_the_sensor_part_only(tiny_system, dim_frame):
    _, frame = dim_frame
    operator = CM2Operator.from_system(tiny_system)
    solver = LsvAdmm(operator, "auto")
    padded = pad_sensor_frame(torch.as_tensor(frame, dtype=operator.lenses.dtype), tiny_system)
    sensor = pad_sensor_frame(torch.ones(tiny_system.sensor_shape, dtype=padded.dtype),
                              tiny_system)  # fmt: skip
    assert (sensor == 0).any()
    outside = torch.where(sensor == 0, 5.0, padded)  # ignored by the solver, λ included
    first = solver.solve(padded, iterations=2)
    second = solver.solve(outside, iterations=2)
    assert first.tv_weight == second.tv_weight
    x = first.x
    assert solver.objective(x, padded) == solver.objective(x, outside)


def test_at_few_photons_the_frames_weight_beats_the_fixed_default(tiny_system, dim_frame):
    truth, frame = dim_frame

    def error(tv_weight) -> float:
        out = BaselineReconstructor("admm", tiny_system, tv_weight=tv_weight, iterations=50,
                                    tolerance=0.0).reconstruct(frame).reconstruction  # fmt: skip
        return float(np.mean((out - truth) ** 2))

    assert error("auto") < 0.8 * error(settings_for(tiny_system).tv_weight)


def test_the_benchmark_row_scores_what_the_reconstructor_gives(tiny_system, dim_frame):
    from svcode_bench.regimes import Scene, admm_rows
    from svcode_core.evaluation.metrics import psnr

    truth, frame = dim_frame
    rec = BaselineReconstructor("admm", tiny_system, tv_weight="auto", iterations=7,
                                tolerance=0.0)  # fmt: skip
    rows = admm_rows(rec.operator, [Scene("cells", truth, frame)], (7,), "K=3", 0.0, "auto")
    summary = rows[0].summary()
    assert summary["knob"] == "K=3, 7 it, λ auto" and summary["settings"]["tv_weight"] == "auto"
    expected = psnr(truth, rec.reconstruct(frame).reconstruction.astype(np.float64), 1.0)
    assert summary["psnr"] == pytest.approx(expected, abs=1e-4)  # float32 output vs estimate


def test_bad_weights_are_refused(tiny_system, capsys):
    with pytest.raises(ValueError, match="a number >= 0 or 'auto'"):
        BaselineReconstructor("admm", tiny_system, tv_weight="strong")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["reconstruct", "in.tif", "--out", "o.tif",
                                   "--tv-weight", "strong"])  # fmt: skip
    assert "a number or 'auto', not 'strong'" in capsys.readouterr().err


def test_the_flag_parses_back():
    arguments = cli_arguments("admm", tv_weight="auto", iterations=20)
    args = build_parser().parse_args(["reconstruct", "in.tif", "--out", "o.tif", *arguments])
    assert (args.tv_weight, args.iterations) == ("auto", 20)
