import argparse
import inspect
import pickle
import threading

import numpy as np
import pytest
import scipy.optimize
import torch
from skimage.restoration import richardson_lucy, wiener
from test_cm2 import gaussian_psfs

from svcode_core.cli.reconstruct import add_method_arguments, baseline_options
from svcode_core.config import OpticsConfig, system_from_scale
from svcode_core.evaluation.metrics import psnr
from svcode_core.methods.base import FrameProgress
from svcode_core.methods.baselines import BaselineReconstructor, reconstruct_with_baseline
from svcode_core.methods.baselines.admm import (
    LsvAdmm,
    _soft_threshold,
    gradient,
    operator_norm,
    total_variation,
)
from svcode_core.methods.baselines.deconv import (
    ShiftInvariantDeconvolution,
    centre_psfs,
    fuse_views,
    lens_transmission,
    richardson_lucy_deconvolve,
    wiener_deconvolve,
)
from svcode_core.methods.build import MethodSpec
from svcode_core.methods.tiling import Cancelled
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import extract_sub_views, pad_sensor_frame


def gaussian_kernel(size=9, sigma=1.3):
    axis = np.arange(size) - size // 2
    kernel = np.exp(-0.5 * (axis[:, None] ** 2 + axis[None, :] ** 2) / sigma**2)
    return kernel / kernel.sum()


@pytest.fixture
def micro_system():
    """16-pixel object, 5-pixel kernels: small enough for dense reference solvers."""
    optics = OpticsConfig(psf_grid=3, kernel_size=5, airy_radius=1.0, pupil_samples=16)
    return system_from_scale("micro", (20, 28), 16, 6, 8, optics, 1e-2).validate()


@pytest.fixture
def micro_op(micro_system):
    return CM2Operator.from_psfs(micro_system, gaussian_psfs(micro_system), dtype=torch.float64)


@pytest.fixture
def tiny_op(tiny_system):
    return CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), rank=3)


def disc_object(size, dtype=torch.float32):
    axis = torch.arange(size, dtype=dtype) - size / 2
    r = torch.sqrt(axis[:, None] ** 2 + axis[None, :] ** 2)
    obj = (r < size / 4).to(dtype) * 0.6
    obj[size // 3, size // 3] = 1.0
    return obj


# ------------------------------------------------------------------ pieces
def test_gradient_norm_bound():
    """‖∇‖² ≤ 8, the bound the ADMM weights rely on (adjointness: test_adjoints.py)."""
    x = torch.randn(3, 17, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert float(gradient(x).norm() ** 2) <= 8 * float(x.norm() ** 2)


def test_soft_threshold_is_the_prox_of_the_group_norm():
    gen = torch.Generator().manual_seed(1)
    v = torch.randn(2, 6, 6, generator=gen, dtype=torch.float64)
    t = 0.7
    z = _soft_threshold(v, t)
    # optimality of argmin_z t·Σ|z| + ½‖z − v‖²: objective is not improved by perturbations
    def objective(w):
        group = float(torch.sqrt(w[0] ** 2 + w[1] ** 2).sum())
        return t * group + 0.5 * float(((w - v) ** 2).sum())

    best = objective(z)
    for _ in range(20):
        assert objective(z + 1e-3 * torch.randn(v.shape, generator=gen, dtype=v.dtype)) >= best
    assert total_variation(torch.zeros(4, 4)) == 0


def test_operator_norm_matches_dense_svd(micro_system, micro_op):
    size = micro_system.sub_view_size
    basis = torch.eye(size * size, dtype=torch.float64).reshape(-1, size, size)
    dense = micro_op.forward(basis).reshape(size * size, -1).T.numpy()
    exact = np.linalg.norm(dense, 2)
    assert operator_norm(micro_op, iterations=30) == pytest.approx(exact, rel=1e-3)


# ------------------------------------------------------- shift-invariant filters
@pytest.mark.parametrize("balance", [1e-3, 0.1])
def test_wiener_matches_skimage(balance):
    rng = np.random.default_rng(0)
    image = rng.random((40, 36))
    psf = gaussian_kernel()
    ours = wiener_deconvolve(torch.from_numpy(image), torch.from_numpy(psf), balance).numpy()
    np.testing.assert_allclose(ours, wiener(image, psf, balance, clip=False), atol=1e-12)
    # reflect boundary = skimage on the mirrored image, cropped
    ours = wiener_deconvolve(torch.from_numpy(image), torch.from_numpy(psf), balance, "reflect")
    mirrored = np.pad(image, 9, mode="reflect")
    expected = wiener(mirrored, psf, balance, clip=False)[9:-9, 9:-9]
    np.testing.assert_allclose(ours.numpy(), expected, atol=1e-12)


def test_richardson_lucy_matches_skimage():
    rng = np.random.default_rng(1)
    image = rng.random((30, 34))
    psf = gaussian_kernel(7, 1.0)
    ours = richardson_lucy_deconvolve(torch.from_numpy(image), torch.from_numpy(psf), 15)
    expected = richardson_lucy(image, psf, num_iter=15, clip=False)
    np.testing.assert_allclose(ours.numpy(), expected, rtol=1e-9, atol=1e-12)


def shift_invariant_operator(system):
    """Only the central lens transmits, with one Gaussian PSF over the whole field."""
    k = system.optics.kernel_size
    psfs = np.zeros((9, system.optics.psf_grid**2, k, k))
    psfs[4] = gaussian_kernel(k, 1.2)
    return CM2Operator.from_psfs(system, psfs, dtype=torch.float64)


@pytest.mark.parametrize("method", ["wiener", "rl"])
def test_pipeline_agrees_with_skimage_on_a_shift_invariant_system(tiny_system, method):
    op = shift_invariant_operator(tiny_system)
    x = disc_object(tiny_system.sub_view_size, torch.float64)
    frame = op.forward(x) + 0.01  # an offset, so RL sees positive data everywhere
    frame = pad_sensor_frame(frame[tiny_system.sensor_window], tiny_system)
    view = extract_sub_views(frame, tiny_system)[4].numpy()
    psf = gaussian_kernel(tiny_system.optics.kernel_size, 1.2)
    if method == "wiener":
        deconv = ShiftInvariantDeconvolution(op, "wiener", balance=0.02, boundary="periodic")
        expected = wiener(view, psf, 0.02, clip=False)
    else:
        deconv = ShiftInvariantDeconvolution(op, "rl", iterations=20)
        expected = richardson_lucy(view, psf, num_iter=20, clip=False)
    # steps 1-3 (deconvolve, fuse) are scikit-image's; step 4 divides by the flat response
    fused = deconv(frame) * deconv.flat_response
    np.testing.assert_allclose(fused.numpy(), expected, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("method", ["wiener", "rl"])
def test_a_uniform_object_comes_back_as_itself(tiny_system, method):
    """Step 4 of the pipeline: in the object's units although every sub-view holds its
    neighbours' crosstalk (several times the object without it)."""
    op = CM2Operator.from_system(tiny_system, dtype=torch.float64)
    deconv = ShiftInvariantDeconvolution(op, method)
    size = tiny_system.sub_view_size
    frame = op.forward(0.3 * torch.ones(size, size, dtype=torch.float64))
    out = deconv(frame)
    seen = deconv.flat_response > 0
    assert seen.float().mean() > 0.9 and (out[~seen] == 0).all()
    assert deconv.flat_response[seen].mean() > 1.5  # the crosstalk step 4 removes
    # Wiener is linear in the frame and RL homogeneous (its first update already scales
    # with the data, whatever its constant start): exact up to float64 rounding
    torch.testing.assert_close(out[seen], torch.full_like(out[seen], 0.3), rtol=1e-9, atol=0)


def test_centre_psfs_and_transmission(tiny_system):
    psfs = gaussian_psfs(tiny_system)
    op = CM2Operator.from_psfs(tiny_system, psfs, rank=9, dtype=torch.float64)
    centre = centre_psfs(op).numpy()
    # grid node 4 is the object centre; pixel S//2 sits 1/(S-1) from it: close, not equal
    np.testing.assert_allclose(centre, psfs[:, 4], atol=0.02 * psfs.max())
    # gaussian_psfs' total energy is 1 − 0.15 (v² + u²), a quadratic the spline reproduces
    size = tiny_system.sub_view_size
    t = np.linspace(-1, 1, size)
    expected = 1 - 0.15 * (t[:, None] ** 2 + t[None, :] ** 2)
    transmission = lens_transmission(op).numpy()
    np.testing.assert_allclose(transmission, np.broadcast_to(expected, (9, size, size)), atol=1e-9)


def test_fusion_inverts_transmission_and_drops_unseen_pixels():
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(6, 6, generator=gen, dtype=torch.float64)
    transmission = 0.2 + torch.rand(9, 6, 6, generator=gen, dtype=torch.float64)
    coverage = torch.ones(9, 6, 6, dtype=torch.float64)
    coverage[:, 0, 0] = 0  # no lens sees this pixel
    coverage[:5, 1, 1] = 0  # only some lenses see this one
    fused = fuse_views(transmission * x, transmission, coverage)
    expected = x.clone()
    expected[0, 0] = 0
    torch.testing.assert_close(fused, expected)


# ------------------------------------------------------------------ LSV-ADMM
def dense_operator(op):
    size = op.system.sub_view_size
    basis = torch.eye(size * size, dtype=torch.float64).reshape(-1, size, size)
    return op.forward(basis).reshape(size * size, -1).T.numpy()


def micro_frame(op, seed=0):
    x = disc_object(op.system.sub_view_size, torch.float64)
    gen = torch.Generator().manual_seed(seed)
    frame = op.forward(x)
    return frame + 0.01 * torch.randn(frame.shape, generator=gen, dtype=frame.dtype) * (frame > 0)


def test_admm_without_tv_solves_nonnegative_least_squares(micro_op):
    frame = micro_frame(micro_op)
    dense = dense_operator(micro_op)
    reference = scipy.optimize.lsq_linear(dense, frame.numpy().ravel(), bounds=(0, np.inf),
                                          tol=1e-12, max_iter=5000)
    solver = LsvAdmm(micro_op, tv_weight=0.0, rho=0.1, cg_iterations=3)
    result = solver.solve(frame, iterations=1000, tolerance=1e-9)
    # lsq_linear's cost is ½‖Ax − y‖², the same objective
    assert abs(solver.objective(result.x, frame) - reference.cost) <= 1e-3 * reference.cost
    assert float(result.x.min()) >= 0


def smoothed_tv_reference(op, frame, tv_weight, epsilon=1e-5):
    """Independent solver: L-BFGS-B with bounds on a Huber-smoothed isotropic TV."""
    dense = dense_operator(op)
    y = frame.numpy().ravel()
    size = op.system.sub_view_size

    def fun(flat):
        x = torch.tensor(flat.reshape(size, size), requires_grad=True)
        g = gradient(x)
        tv = torch.sqrt(g[0] ** 2 + g[1] ** 2 + epsilon**2).sum()
        residual = torch.from_numpy(dense) @ x.reshape(-1) - torch.from_numpy(y)
        value = 0.5 * (residual**2).sum() + tv_weight * tv
        value.backward()
        return float(value.detach()), x.grad.numpy().ravel().copy()

    best = scipy.optimize.minimize(fun, np.zeros(size * size), jac=True, method="L-BFGS-B",
                                   bounds=[(0, None)] * size * size,
                                   options={"maxiter": 20000, "ftol": 1e-15, "gtol": 1e-12})
    return best.x.reshape(size, size)


def test_admm_with_tv_matches_an_independent_solver(micro_op):
    frame = micro_frame(micro_op)
    tv_weight = 3e-3
    reference = torch.from_numpy(smoothed_tv_reference(micro_op, frame, tv_weight))
    solver = LsvAdmm(micro_op, tv_weight=tv_weight, rho=0.1)
    result = solver.solve(frame, iterations=1500, tolerance=1e-8)
    ours, theirs = solver.objective(result.x, frame), solver.objective(reference, frame)
    assert ours <= theirs * (1 + 1e-3)
    assert float((result.x - reference).norm() / reference.norm()) < 2e-2


def test_admm_warm_start_continues_the_descent(tiny_op, tiny_system):
    frame = tiny_op.forward(disc_object(tiny_system.sub_view_size))
    solver = LsvAdmm(tiny_op, tv_weight=1e-3, rho=0.1)
    first = solver.solve(frame, iterations=30, tolerance=0)
    warm = solver.solve(frame, x0=first.x, iterations=30, tolerance=0)
    cold = solver.solve(frame, iterations=60, tolerance=0)
    assert solver.objective(warm.x, frame) < solver.objective(first.x, frame)
    assert solver.objective(warm.x, frame) <= 1.05 * solver.objective(cold.x, frame)
    assert len(cold.objective) == 60 and len(cold.primal_residual) == 6 == len(cold.rho)
    assert cold.objective[-1] < cold.objective[0]


def test_admm_stops_at_tolerance_and_reports_every_iteration(tiny_op, tiny_system):
    frame = tiny_op.forward(disc_object(tiny_system.sub_view_size))
    seen = []
    result = LsvAdmm(tiny_op, 1e-3).solve(
        frame, iterations=500, tolerance=5e-2, callback=lambda i, x: seen.append(i)
    )
    assert result.converged and result.iterations < 500
    assert seen == list(range(1, result.iterations + 1))
    assert result.primal_residual[-1] <= 5e-2 and result.dual_residual[-1] <= 5e-2


def test_admm_rejects_bad_input(tiny_op, tiny_system):
    solver = LsvAdmm(tiny_op, 1e-3)
    frame = torch.zeros(tiny_system.padded_shape)
    frame[30, 30] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        solver.solve(frame)
    with pytest.raises(ValueError, match="padded sensor frame"):
        solver.solve(torch.zeros(tiny_system.sensor_shape))
    with pytest.raises(ValueError, match="tv_weight"):
        LsvAdmm(tiny_op, -1.0)
    with pytest.raises(ValueError, match="rho"):
        LsvAdmm(tiny_op, 1e-3, rho=0.0)
    zero = CM2Operator.from_psfs(tiny_system, 0 * gaussian_psfs(tiny_system), rank=1)
    with pytest.raises(ValueError, match="zero"):
        LsvAdmm(zero, 1e-3)


# -------------------------------------------------------- reconstruction API
@pytest.mark.parametrize(
    "method, options, gain",
    [
        ("admm", {"iterations": 60}, 15.0),
        # the shift-invariant methods leave the crosstalk of the neighbouring lenses in
        ("wiener", {"balance": 1e-2}, 3.0),
        ("rl", {"iterations": 20}, 3.0),
    ],
)
def test_reconstruct_with_baseline(tiny_system, tiny_op, method, options, gain):
    x = disc_object(tiny_system.sub_view_size)
    raw = tiny_op.measure(x).numpy()
    recon = reconstruct_with_baseline(method, raw, tiny_system, operator=tiny_op, **options)
    assert recon.shape == x.shape and recon.dtype == np.float32
    assert np.isfinite(recon).all()
    # much better than the zero image, in the centre where all lenses see the object
    zone = slice(12, 36)
    assert psnr(x.numpy()[zone, zone], recon[zone, zone], 1.0) > psnr(
        x.numpy()[zone, zone], 0 * recon[zone, zone], 1.0
    ) + gain


def test_stack_views_and_spec(tiny_system, tiny_op):
    x = disc_object(tiny_system.sub_view_size)
    raw = tiny_op.measure(x).numpy()
    rec = BaselineReconstructor("admm", tiny_system, operator=tiny_op, iterations=20)
    result = rec.reconstruct(np.stack([raw, raw]), return_views=True)
    assert result.reconstruction.shape == (2, 48, 48)
    assert result.views.shape == (2, 9, 48, 48)
    spec = MethodSpec("rl", tiny_system, options={"iterations": 5})
    assert pickle.loads(pickle.dumps(spec)).describe() == {"method": "rl", "iterations": 5}
    with pytest.raises(ValueError, match="unknown option"):
        BaselineReconstructor("wiener", tiny_system, operator=tiny_op, iterations=5)
    with pytest.raises(ValueError, match="method"):
        BaselineReconstructor("svcode", tiny_system, operator=tiny_op)


ITERATIVE = {"admm": {"iterations": 6, "tolerance": 0.0}, "rl": {"iterations": 6}}


def _three_frames(system, op):
    """Two frames with signal around a blank one (which skips the solver)."""
    x = disc_object(system.sub_view_size)
    raw = op.measure(x).numpy()
    return np.stack([raw, np.zeros_like(raw), 0.5 * raw])


@pytest.mark.parametrize("method", ["admm", "rl", "wiener"])
def test_progress_per_iteration_and_the_same_result(tiny_system, tiny_op, method, drain):
    """LSV-ADMM and RL report before every frame and after every iteration (``tiles_done``
    the iterations done); Wiener once per frame; the result is that of reconstruct()."""
    rec = BaselineReconstructor(method, tiny_system, operator=tiny_op, **ITERATIVE.get(method, {}))
    stack = _three_frames(tiny_system, tiny_op)
    with pytest.warns(UserWarning, match="blank frames"):
        progress, result = drain(rec.iter_reconstruct(stack, return_views=True))
    total, done = (6, range(7)) if method in ITERATIVE else (1, [0])
    expected = [FrameProgress(0, 3, i, total) for i in done]
    expected += [FrameProgress(1, 3, 0, total)]  # blank: nothing to iterate
    expected += [FrameProgress(2, 3, i, total) for i in done]
    assert progress == expected
    with pytest.warns(UserWarning, match="blank frames"):
        whole = rec.reconstruct(stack, return_views=True)
    np.testing.assert_array_equal(result.reconstruction, whole.reconstruction)
    np.testing.assert_array_equal(result.views, whole.views)


@pytest.mark.parametrize("method", ["admm", "rl"])
@pytest.mark.parametrize("stop", ["close", "cancel"])
def test_a_stop_between_iterations_ends_the_frame(tiny_system, tiny_op, method, stop):
    """Closing the generator (or setting ``cancel``) at iteration 3 of the last frame runs
    no further iteration, closes the solver's loop and returns nothing; the reconstructor
    then runs as before."""
    rec = BaselineReconstructor(method, tiny_system, operator=tiny_op, **ITERATIVE[method])
    loops = []  # every frame's solver loop, to see it closed
    solve = rec.solver.iter_solve

    def watched(*args):
        loops.append(solve(*args))
        return loops[-1]

    rec.solver.iter_solve = watched
    stack = _three_frames(tiny_system, tiny_op)[[0, 2]]
    cancel = threading.Event()
    steps = rec.iter_reconstruct(stack, cancel=cancel)
    seen = []
    for progress in steps:
        seen.append(progress)
        if progress == FrameProgress(1, 2, 3, 6):
            break
    if stop == "close":
        steps.close()
    else:
        cancel.set()
        with pytest.raises(Cancelled):
            next(steps)
    assert seen[-1] == FrameProgress(1, 2, 3, 6) and len(seen) == 7 + 4
    assert len(loops) == 2 and all(inspect.getgeneratorstate(loop) == "GEN_CLOSED"
                                   for loop in loops)
    fresh = BaselineReconstructor(method, tiny_system, operator=tiny_op, **ITERATIVE[method])
    np.testing.assert_array_equal(rec.reconstruct(stack).reconstruction,
                                  fresh.reconstruct(stack).reconstruction)


def test_command_line_options():
    parser = argparse.ArgumentParser()
    parser.add_argument("--method")
    add_method_arguments(parser)
    args = parser.parse_args(["--method", "admm", "--iterations", "50", "--tv-weight", "1e-3"])
    assert baseline_options(args) == {"iterations": 50, "tv_weight": 1e-3}
    args = parser.parse_args(["--method", "wiener", "--wiener-balance", "0.1", "--rank", "2"])
    assert baseline_options(args) == {"balance": 0.1, "rank": 2}
    args = parser.parse_args(["--method", "wiener", "--rho", "1"])
    with pytest.raises(ValueError, match="--rho does not apply"):
        baseline_options(args)
    args = parser.parse_args(["--method", "rl", "--memory-budget", "0.5"])
    assert baseline_options(args) == {"memory_budget": 2**29}
    args = parser.parse_args(["--method", "admm", "--memory-budget", "0"])
    with pytest.raises(ValueError, match="--memory-budget must be positive"):
        baseline_options(args)


def test_the_solvers_the_command_line_and_the_registry_share_the_defaults(tiny_system,
                                                                        tiny_op, capsys):
    """One place (the registry) defines each model-based default; the solvers run with it
    and ``svcode reconstruct --help`` quotes it."""
    import inspect

    from svcode_core.cli import main
    from svcode_core.methods import registry
    from svcode_core.methods.baselines import default_rank, settings_for
    from svcode_core.methods.baselines.deconv import ShiftInvariantDeconvolution

    admm, wiener, rl = (registry.method(m).defaults for m in ("admm", "wiener", "rl"))
    assert (admm["rank"], admm["iterations"], admm["tv_weight"]) == (3, 50, "auto")
    assert (wiener["balance"], rl["iterations"]) == (0.1, 10)
    rec = BaselineReconstructor("admm", tiny_system, operator=tiny_op)
    assert (rec.iterations, rec.tolerance, rec.solver.tv_weight, rec.solver.rho,
            rec.solver.cg_iterations) == tuple(admm[k] for k in (
                "iterations", "tolerance", "tv_weight", "rho", "cg_iterations"))  # fmt: skip
    settings = settings_for(tiny_system)
    assert (settings.iterations, settings.tolerance) == (admm["iterations"], admm["tolerance"])
    solve = inspect.signature(LsvAdmm.solve).parameters
    assert solve["iterations"].default == admm["iterations"]
    deconv = BaselineReconstructor("wiener", tiny_system, operator=tiny_op).solver
    assert (deconv.balance, deconv.boundary) == (wiener["balance"], wiener["boundary"])
    assert BaselineReconstructor("rl", tiny_system, operator=tiny_op).solver.iterations == 10
    signature = inspect.signature(ShiftInvariantDeconvolution).parameters
    assert signature["balance"].default == wiener["balance"]
    assert signature["iterations"].default == rl["iterations"]
    # the rank: at most 3, the system's own when smaller
    assert default_rank(tiny_system) == 3
    assert BaselineReconstructor("wiener", tiny_system).operator.rank == 3
    assert default_rank(tiny_system.replace(rank=2)) is None
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for quoted in ("default 3, or the system's K when smaller", "default 50", "default auto",
                   "default 10", "default 0.1", f"default {admm['tolerance']:g}"):
        assert quoted in text, quoted


def test_memory_budget_chunks_the_operator_not_the_result(tiny_system):
    from svcode_core.phantoms import make_object
    from svcode_core.physics.simulate import Simulator

    frame = Simulator(tiny_system).simulate(make_object("cells", 48, 0), seed=1).measurement
    whole = BaselineReconstructor("admm", tiny_system, iterations=5, tolerance=0.0)
    chunked = BaselineReconstructor("admm", tiny_system, iterations=5, tolerance=0.0,
                                    memory_budget=1)  # one lens and component at a time
    assert chunked.operator.lenses.memory_budget == 1 != whole.operator.lenses.memory_budget
    np.testing.assert_allclose(chunked.reconstruct(frame).reconstruction,
                               whole.reconstruct(frame).reconstruction, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="not both"):
        BaselineReconstructor("admm", tiny_system, operator=whole.operator, memory_budget=1)


# ------------------------------------------------------------------ benchmark
def test_benchmark_rows_and_outputs(tiny_system, tiny_op, tmp_path):
    from svcode_bench.regimes import (
        QUICK,
        Scene,
        admm_rows,
        deconvolution_rows,
        pareto_front,
        plot_pareto,
        write_markdown,
    )

    truth = disc_object(tiny_system.sub_view_size).numpy()
    scenes = [Scene("disc", truth, tiny_op.measure(torch.from_numpy(truth)).numpy())]
    rows = admm_rows(tiny_op, scenes, (2, 10), "K=3", 0.0)
    rows += deconvolution_rows(tiny_op, scenes, QUICK)
    summaries = [row.summary() for row in rows]
    assert [s["method"] for s in summaries] == ["LSV-ADMM", "LSV-ADMM", "Wiener", "Richardson-Lucy"]
    assert summaries[0]["seconds"] < summaries[1]["seconds"]  # time grows with iterations
    assert summaries[0]["psnr"] < summaries[1]["psnr"]  # and so does the precision
    report = {"system": "tiny", "scenes": ["disc"], "simulator_rank": 3, "threads": 1,
              "zones": {"centre": "r < 0.5", "ring": "r > 0.8"}, "total_seconds": 1.0,
              "note": "no model", "rows": summaries}
    write_markdown(report, tmp_path / "wp.md")
    plot_pareto(report, tmp_path / "wp.png")
    assert (tmp_path / "wp.md").read_text().count("| LSV-ADMM |") == 2
    assert (tmp_path / "wp.png").stat().st_size > 0
    assert pareto_front([(1, 10), (2, 5), (3, 20), (0.5, 1)]) == [(0.5, 1), (1, 10), (3, 20)]


def test_benchmark_labels_and_scores_an_ablation_model(tiny_system, tiny_op, tiny_model_config,
                                                      tmp_path):
    from svcode_bench.regimes import Scene, model_label, run_benchmark, svcode_rows
    from svcode_core.methods.model_file import save_model
    from svcode_core.network import SVCoDe

    config = tiny_model_config.replace(coord_gate=False)
    path = save_model(tmp_path / "no-gate.safetensors", SVCoDe(config), tiny_system)
    assert model_label(path) == "SV-CoDe (no CoordGate)"
    wide = save_model(tmp_path / "wide.safetensors",
                      SVCoDe(config.replace(positional_encoding=False, lens_context=True)),
                      tiny_system)
    assert model_label(wide) == "SV-CoDe (no CoordGate, no PE, lens context)"
    mirrored = save_model(tmp_path / "mirrored.safetensors",
                          SVCoDe(tiny_model_config.replace(padding="reflect")), tiny_system)
    assert model_label(mirrored) == "SV-CoDe (mirrored padding)"
    truth = disc_object(tiny_system.sub_view_size).numpy()
    scenes = [Scene("disc", truth, tiny_op.measure(torch.from_numpy(truth)).numpy())]
    (row,) = svcode_rows(path, tiny_system, scenes, all_knobs=False)
    summary = row.summary()
    assert summary["method"] == "SV-CoDe (no CoordGate)" and np.isfinite(summary["psnr"])
    plain, refined = (r.summary() for r in svcode_rows(path, tiny_system, scenes, all_knobs=2))
    assert "refine" not in plain["knob"] and refined["knob"].endswith("refine 10")
    assert np.isfinite(refined["psnr"]) and refined["psnr"] != plain["psnr"]
    with pytest.raises(ValueError, match="unknown method families"):
        run_benchmark(tiny_system, methods=("fouriernet",))


def test_the_operator_norm_is_estimated_once_per_operator(tiny_system, monkeypatch):
    """A solver is built for every widget run on the operator the core keeps: the norm's
    power iteration (1.4 s on cm2-mini) runs once per operator and iteration count."""
    import svcode_core.methods.baselines.admm as admm

    calls = []
    estimate = admm._power_iteration
    monkeypatch.setattr(admm, "_power_iteration",
                        lambda op, n: calls.append(n) or estimate(op, n))
    operator = CM2Operator.from_system(tiny_system)
    first = operator_norm(operator)
    assert operator_norm(operator) == first and calls == [10]
    operator_norm(operator, 3)
    operator_norm(CM2Operator.from_system(tiny_system))
    assert calls == [10, 3, 10]
