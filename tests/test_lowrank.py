"""Low-rank SV blur: adjointness, analytic cases, peer libraries, decomposition, basis."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import scipy.signal
import torch

from svcode_core.physics.lowrank import (
    InterpolatedMaps,
    LowRankSVOperator,
    coefficient_maps,
    decompose_psfs,
    interpolation_basis,
    plan_chunks,
)

TOLERANCE = {torch.float32: 1e-5, torch.float64: 1e-12}


def gaussian_psf_grid(n_grid: int = 5, size: int = 11) -> np.ndarray:
    """Unit-sum elongated Gaussians whose widths and tilt vary smoothly over the field."""
    half = size // 2
    rows, cols = np.mgrid[-half : half + 1, -half : half + 1]
    nodes = np.linspace(-1, 1, n_grid)
    psfs = []
    for v in nodes:
        for u in nodes:
            sigma_r, sigma_c = 1.0 + 0.5 * v**2 + 0.3 * u, 1.2 + 0.4 * u**2 - 0.2 * v
            psf = np.exp(
                -(rows**2) / (2 * sigma_r**2)
                - cols**2 / (2 * sigma_c**2)
                - 0.3 * u * v * rows * cols / (sigma_r * sigma_c)
            )
            psfs.append(psf / psf.sum())
    return np.array(psfs)


def random_operator(shape, kernel_shape, rank=3, lenses=None, dtype=torch.float64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    lead = (rank,) if lenses is None else (lenses, rank)
    kernels = torch.randn(*lead, *kernel_shape, generator=generator, dtype=torch.float64)
    weights = torch.rand(*lead, *shape, generator=generator, dtype=torch.float64)
    return LowRankSVOperator(kernels, weights, dtype=dtype)


def place(kernel: np.ndarray, shape: tuple[int, int], pixel: tuple[int, int]) -> np.ndarray:
    """``kernel`` with its centre at ``pixel`` in a zero image of ``shape`` (cropped)."""
    height, width = kernel.shape
    padded = np.zeros((shape[0] + height - 1, shape[1] + width - 1))
    padded[pixel[0] : pixel[0] + height, pixel[1] : pixel[1] + width] = kernel
    return padded[height // 2 : height // 2 + shape[0], width // 2 : width // 2 + shape[1]]


# --------------------------------------------------------------------------- operator


# Adjointness of the operator: test_adjoints.py.
# Chunks that split 5 lenses and 7 components unevenly (2+2+1 and 3+3+1, 4+1 and 2+2+2+1),
# one term at a time, and a single chunk; the budget keeps either no kernel spectrum or all.
UNEVEN_CHUNKS = [(2, 3), (4, 2), (1, 1), (5, 7)]


def factored_operator(dtype=torch.float64, budget=None, lenses=5, rank=7, seed=0):
    """Random kernels with coefficient maps kept as :class:`InterpolatedMaps`, 19 × 22."""
    generator = torch.Generator().manual_seed(seed)
    kernels = torch.randn(lenses, rank, 5, 7, generator=generator, dtype=torch.float64)
    grid = torch.rand(lenses, rank, 4, 3, generator=generator, dtype=torch.float64)
    maps = InterpolatedMaps(
        grid, interpolation_basis(4, 17, margin=1), interpolation_basis(3, 20, margin=1)
    )
    return LowRankSVOperator(kernels, maps, dtype=dtype, memory_budget=budget)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kept", [True, False])
@pytest.mark.parametrize("chunks", UNEVEN_CHUNKS)
def test_chunked_operator_matches_one_chunk_and_is_adjoint(monkeypatch, dtype, kept, chunks):
    whole = factored_operator(dtype)
    op = factored_operator(dtype, budget=None if kept else 1)
    assert op._spectra.shape[0] == (5 if kept else 0)
    monkeypatch.setattr(op, "chunking", lambda batch=1: chunks)
    generator = torch.Generator().manual_seed(1)
    x = torch.randn(2, *op.shape, generator=generator, dtype=dtype)
    y = torch.randn(2, 5, *op.shape, generator=generator, dtype=dtype)
    ax, aty = op.forward(x), op.adjoint(y)
    # the same terms summed in another order: a few roundings of each output value
    for result, expected in ((ax, whole.forward(x)), (aty, whole.adjoint(y))):
        error = (result.double() - expected.double()).norm() / expected.double().norm()
        assert error <= TOLERANCE[dtype]
    lhs, rhs = (ax.double() * y.double()).sum(), (x.double() * aty.double()).sum()
    assert abs(lhs - rhs) / (ax.double().norm() * y.double().norm()) <= TOLERANCE[dtype]


def test_factored_maps_equal_stored_maps():
    op = factored_operator()
    dense = LowRankSVOperator(op.kernels, op.weights, memory_budget=1)
    assert op.weights.shape == (5, 7, 19, 22)
    maps = coefficient_maps(op._maps.grid_weights[2].numpy(), (17, 20), margin=1)
    np.testing.assert_allclose(op.weights[2].numpy(), maps, rtol=0, atol=1e-14)
    x = torch.rand(19, 22, dtype=torch.float64)
    torch.testing.assert_close(op.forward(x), dense.forward(x), rtol=0, atol=1e-13)
    single = op.to(dtype=torch.float32)
    assert isinstance(single._maps, InterpolatedMaps) and single.memory_budget == op.memory_budget
    error = (single.forward(x.float()).double() - op.forward(x)).norm() / op.forward(x).norm()
    assert error <= TOLERANCE[torch.float32]
    mix = torch.rand(5, 7, dtype=torch.float64)
    window = (slice(3, 9), slice(2, 20))
    for operator in (op, dense):
        mixed = operator.weight_maps(*window, mix=mix)
        expected = torch.einsum("lkij,lk->lij", op.weights[..., window[0], window[1]], mix)
        torch.testing.assert_close(mixed, expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize("batch", [1, 3])
def test_budget_sets_the_chunks(batch):
    shape, kernel_shape, dtype = (19, 22), (5, 7), torch.float32
    per_lens, per_term = factored_operator(dtype)._costs(batch)
    smallest = per_lens + per_term  # one lens, one component
    seen = []
    for budget in np.geomspace(smallest, 200 * smallest, 40).astype(int):
        plan = plan_chunks(shape, kernel_shape, 5, 7, dtype, int(budget), batch)
        assert plan.bytes <= budget or (plan.lenses, plan.components) == (1, 1)
        assert plan.components == 7 or plan.lenses == 1
        op = factored_operator(dtype, budget=int(budget))
        assert op._spectra.shape[0] == plan.kept_lenses
        assert op.chunking(batch) == (plan.lenses, plan.components)
        factors = sum(t.nelement() * t.element_size() for t in (op.kernels, *op._maps.factors))
        assert op.memory_estimate(batch) == plan.bytes + factors
        seen.append((plan.lenses, plan.components))
    assert seen[-1] == (5, 7) and any(7 % k for _, k in seen) and any(5 % n for n, _ in seen)
    tiny = plan_chunks(shape, kernel_shape, 5, 7, dtype, 1, batch)  # below one term:
    assert (tiny.kept_lenses, tiny.lenses, tiny.components) == (0, 1, 1)  # one at a time
    with pytest.raises(ValueError, match="memory_budget"):
        factored_operator(budget=0)


def test_delta_gives_weighted_kernel_sum():
    shape, kernel_shape = (13, 16), (7, 5)
    op = random_operator(shape, kernel_shape, rank=4)
    kernels, weights = op.kernels[0].numpy(), op.weights[0].numpy()
    for pixel in [(6, 7), (1, 14), (12, 0)]:
        x = torch.zeros(shape, dtype=torch.float64)
        x[pixel] = 1.0
        expected = place(
            np.einsum("k,kij->ij", weights[:, pixel[0], pixel[1]], kernels), shape, pixel
        )
        np.testing.assert_allclose(op.forward(x).numpy(), expected, rtol=0, atol=1e-13)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("shape", "kernel_shape"), [((16, 21), (9, 7)), ((6, 5), (9, 11))])
def test_constant_weight_is_plain_convolution(dtype, shape, kernel_shape):
    rng = np.random.default_rng(2)
    x, kernel = rng.standard_normal(shape), rng.standard_normal(kernel_shape)
    op = LowRankSVOperator(kernel[None], np.ones((1, *shape)), dtype=dtype)
    if shape == (16, 21):
        # H + h//2 = 20 and W + w//2 = 24 are already fast: no slack hides a wrap-around
        assert op.fft_shape == (20, 24)
    result = op.forward(torch.as_tensor(x, dtype=dtype)).double().numpy()
    expected = scipy.signal.convolve2d(x, kernel, mode="same")
    np.testing.assert_allclose(
        expected, scipy.ndimage.convolve(x, kernel, mode="constant"), atol=1e-12
    )
    atol = 10 * TOLERANCE[dtype] * np.abs(expected).max()
    np.testing.assert_allclose(result, expected, rtol=0, atol=atol)
    adjoint = op.adjoint(torch.as_tensor(x, dtype=dtype)).double().numpy()
    np.testing.assert_allclose(
        adjoint, scipy.signal.correlate2d(x, kernel, mode="same"), rtol=0, atol=atol
    )


@pytest.mark.parametrize(("shape", "grid"), [((17, 20), (3, 4)), ((20, 17), (4, 3))])
def test_matches_pylops_nonstationary_convolution(shape, grid):
    pylops = pytest.importorskip("pylops")
    margin = 2
    size = (shape[0] - 2 * margin, shape[1] - 2 * margin)
    step = tuple((s - 1) // (g - 1) for s, g in zip(size, grid, strict=True))
    assert all((s - 1) % (g - 1) == 0 for s, g in zip(size, grid, strict=True))
    rng = np.random.default_rng(3)
    filters = rng.standard_normal((*grid, 5, 7))
    reference = pylops.signalprocessing.NonStationaryConvolve2D(
        dims=shape,
        hs=filters,
        ihx=tuple(margin + step[0] * np.arange(grid[0])),
        ihz=tuple(margin + step[1] * np.arange(grid[1])),
        engine="numpy",
    )
    n_filters = grid[0] * grid[1]
    weights = coefficient_maps(np.eye(n_filters).reshape(n_filters, *grid), size, margin, order=1)
    op = LowRankSVOperator(filters.reshape(n_filters, 5, 7), weights, dtype=torch.float64)
    x, y = rng.standard_normal(shape), rng.standard_normal(shape)
    expected = (reference @ x.ravel()).reshape(shape)
    result = op.forward(torch.as_tensor(x)).numpy()
    assert np.linalg.norm(result - expected) <= 1e-10 * np.linalg.norm(expected)
    expected = (reference.H @ y.ravel()).reshape(shape)
    result = op.adjoint(torch.as_tensor(y)).numpy()
    assert np.linalg.norm(result - expected) <= 1e-10 * np.linalg.norm(expected)


def test_lens_batch_equals_single_lens_operators():
    batched = random_operator((10, 12), (5, 3), rank=2, lenses=3)
    singles = [
        LowRankSVOperator(k, w) for k, w in zip(batched.kernels, batched.weights, strict=True)
    ]
    x = torch.randn(4, 10, 12, dtype=torch.float64)
    y = torch.randn(4, 3, 10, 12, dtype=torch.float64)
    images = batched.forward(x)
    for lens, single in enumerate(singles):
        torch.testing.assert_close(images[:, lens], single.forward(x), rtol=0, atol=1e-13)
    expected = sum(single.adjoint(y[:, lens]) for lens, single in enumerate(singles))
    torch.testing.assert_close(batched.adjoint(y), expected, rtol=0, atol=1e-13)
    assert (batched.n_lenses, batched.rank, batched.shape) == (3, 2, (10, 12))


def test_from_decomposition_pads_lower_ranks_with_zero_components():
    psfs = gaussian_psf_grid()
    low, high = decompose_psfs(psfs, rank=2), decompose_psfs(psfs[::-1], rank=4)
    op = LowRankSVOperator.from_decomposition([low, high], 20, margin=1, dtype=torch.float64)
    assert op.rank == 4 and op.shape == (22, 22) and op.n_lenses == 2
    x = torch.rand(22, 22, dtype=torch.float64)
    for lens, item in enumerate([low, high]):
        single = LowRankSVOperator.from_decomposition(item, 20, margin=1, dtype=torch.float64)
        assert not single.lens_batched
        torch.testing.assert_close(op.forward(x)[lens], single.forward(x), rtol=0, atol=1e-14)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_single_pixel_and_huge_objects(dtype):
    op = random_operator((15, 15), (5, 5), dtype=dtype)
    assert torch.count_nonzero(op.forward(torch.zeros(15, 15, dtype=dtype))) == 0
    x = torch.zeros(15, 15, dtype=torch.float64)
    x[3, 11] = 1.0
    exact = op.to(dtype=torch.float64).forward(x)
    for amplitude in (1.0, 1e6):
        result = op.forward((amplitude * x).to(dtype)).double() / amplitude
        assert (result - exact).norm() <= 10 * TOLERANCE[dtype] * exact.norm()


def test_to_changes_dtype_and_keeps_results():
    op32 = random_operator((9, 8), (3, 5), dtype=torch.float32)
    op64 = op32.to(dtype=torch.float64)
    assert op64.dtype == torch.float64 and op32.to(dtype=torch.float32) is op32
    x = torch.rand(9, 8, dtype=torch.float64)
    torch.testing.assert_close(
        op32.forward(x.float()).double(), op64.forward(x), atol=1e-5, rtol=1e-5
    )


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_input_raises(bad):
    op = random_operator((6, 7), (3, 3))
    x = torch.zeros(6, 7, dtype=torch.float64)
    x[2, 3] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        op.forward(x)
    with pytest.raises(ValueError, match="NaN or Inf"):
        op.adjoint(x)


def test_invalid_arguments_raise():
    op = random_operator((6, 7), (3, 3))
    with pytest.raises(ValueError, match="shape"):
        op.forward(torch.zeros(7, 6, dtype=torch.float64))
    with pytest.raises(ValueError, match="LowRankSVOperator.to"):
        op.forward(torch.zeros(6, 7, dtype=torch.float32))
    with pytest.raises(TypeError):
        op.forward(np.zeros((6, 7)))
    with pytest.raises(ValueError, match="odd"):
        LowRankSVOperator(np.ones((1, 4, 3)), np.ones((1, 6, 7)))
    with pytest.raises(ValueError, match="disagree"):
        LowRankSVOperator(np.ones((2, 3, 3)), np.ones((1, 6, 7)))
    with pytest.raises(ValueError, match="NaN or Inf"):
        LowRankSVOperator(np.full((1, 3, 3), np.nan), np.ones((1, 6, 7)))
    with pytest.raises(ValueError, match="dtype"):
        LowRankSVOperator(np.ones((1, 3, 3)), np.ones((1, 6, 7)), dtype=torch.float16)


# ----------------------------------------------------------------------- decomposition


def test_full_rank_decomposition_reconstructs_the_grid():
    psfs = gaussian_psf_grid()
    result = decompose_psfs(psfs, tolerance=0.0)
    assert result.rank == 25 and result.grid_weights.shape == (25, 5, 5)
    rebuilt = np.einsum("kab,kij->abij", result.grid_weights, result.kernels).reshape(psfs.shape)
    np.testing.assert_allclose(rebuilt, psfs, rtol=0, atol=1e-14)
    gram = np.einsum("kij,lij->kl", result.kernels, result.kernels)
    np.testing.assert_allclose(gram, np.eye(25), atol=1e-12)
    assert (result.kernels[0] >= 0).all()  # sign convention: the mean-like kernel is positive
    assert np.all(np.diff(result.captured_energy) >= 0)
    assert result.captured_energy[-1] == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("tolerance", [1e-1, 1e-2, 1e-3, 1e-5])
def test_tolerance_picks_the_smallest_sufficient_rank(tolerance):
    result = decompose_psfs(gaussian_psf_grid(), tolerance=tolerance)
    energy = result.singular_values**2 / np.sum(result.singular_values**2)
    assert energy[result.rank :].sum() <= tolerance < energy[result.rank - 1 :].sum()
    assert result.energy_fraction == pytest.approx(energy[: result.rank].sum())


def test_zero_psfs_do_not_produce_nan():
    psfs = gaussian_psf_grid()
    psfs[7] = 0.0
    result = decompose_psfs(psfs, rank=3)
    assert np.isfinite(result.kernels).all() and np.allclose(result.grid_weights[:, 1, 2], 0)
    empty = decompose_psfs(np.zeros((9, 5, 5)))
    assert empty.rank == 1 and not empty.kernels.any() and not empty.grid_weights.any()
    assert np.isfinite(empty.captured_energy).all()
    op = LowRankSVOperator.from_decomposition(empty, 8, dtype=torch.float64)
    assert not op.forward(torch.rand(8, 8, dtype=torch.float64)).any()


def test_decomposition_rejects_bad_input():
    psfs = gaussian_psf_grid(3, 5)
    with pytest.raises(ValueError, match="rank"):
        decompose_psfs(psfs, rank=10)
    with pytest.raises(ValueError, match="G\\*G"):
        decompose_psfs(psfs[:8])
    with pytest.raises(ValueError, match="odd"):
        decompose_psfs(np.ones((9, 4, 5)))
    with pytest.raises(ValueError, match="tolerance"):
        decompose_psfs(psfs, tolerance=1.0)
    psfs[4, 2, 2] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        decompose_psfs(psfs)


# --------------------------------------------------------------------- interpolation


@pytest.mark.parametrize("order", [1, 3])
def test_basis_interpolates_grid_values(order):
    basis = interpolation_basis(5, 41, margin=3, order=order)
    assert basis.shape == (5, 47)
    nodes = 3 + 10 * np.arange(5)
    np.testing.assert_allclose(basis[:, nodes], np.eye(5), atol=1e-12)
    np.testing.assert_allclose(basis.sum(axis=0), 1.0, atol=1e-12)
    # margin pixels take the edge value
    np.testing.assert_array_equal(basis[:, :3], np.repeat(basis[:, 3:4], 3, axis=1))
    np.testing.assert_array_equal(basis[:, -3:], np.repeat(basis[:, -4:-3], 3, axis=1))


@pytest.mark.parametrize(("order", "degree"), [(1, 1), (3, 1), (3, 3)])
def test_coefficient_maps_reproduce_polynomials(order, degree):
    nodes = np.linspace(-1, 1, 5)

    def field(v, u):
        return 0.3 + 0.7 * v - 0.4 * u + (0.5 * v**3 * u - 0.8 * u**3 + v**2 if degree == 3 else 0)

    grid = field(nodes[:, None], nodes[None, :])[None]
    maps = coefficient_maps(grid, (23, 30), order=order)
    v = np.linspace(-1, 1, 23)[:, None]
    u = np.linspace(-1, 1, 30)[None, :]
    np.testing.assert_allclose(maps[0], field(v, u), atol=1e-12)


def test_basis_edge_cases():
    np.testing.assert_array_equal(interpolation_basis(1, 6, margin=1), np.ones((1, 8)))
    with pytest.raises(ValueError, match="order"):
        interpolation_basis(4, 10, order=2)
    with pytest.raises(ValueError, match="margin"):
        interpolation_basis(4, 10, margin=-1)
