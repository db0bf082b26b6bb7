"""The exact SV convolution and the low-rank error table."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_lowrank import gaussian_psf_grid, place

from svcode_core.physics.lowrank import LowRankSVOperator, decompose_psfs, interpolation_basis
from svcode_core.physics.reference import lowrank_error, sv_convolve_reference


def sparse_object(shape, seed=0, fill=0.3):
    rng = np.random.default_rng(seed)
    x = rng.random(shape)
    return np.where(rng.random(shape) < fill, x, 0.0)


def test_single_pixel_gives_its_interpolated_psf():
    psfs = gaussian_psf_grid()
    rows, cols = interpolation_basis(5, 19, margin=2), interpolation_basis(5, 24, margin=2)
    for pixel in [(0, 0), (7, 13), (22, 27), (11, 1)]:
        x = np.zeros((23, 28))
        x[pixel] = 2.5
        phi = np.outer(rows[:, pixel[0]], cols[:, pixel[1]]).ravel()
        expected = place(2.5 * np.einsum("g,gij->ij", phi, psfs), x.shape, pixel)
        result = sv_convolve_reference(x, psfs, rows, cols, chunk_elements=50)
        np.testing.assert_allclose(result, expected, rtol=0, atol=1e-15)


def test_reference_matches_pylops_with_bilinear_basis():
    pylops = pytest.importorskip("pylops")
    shape, margin, grid = (21, 17), 2, (3, 4)
    filters = np.random.default_rng(4).standard_normal((*grid, 7, 5))
    op = pylops.signalprocessing.NonStationaryConvolve2D(
        dims=shape, hs=filters, ihx=(2, 10, 18), ihz=(2, 6, 10, 14), engine="numpy"
    )
    rows = interpolation_basis(3, shape[0] - 2 * margin, margin, order=1)
    cols = interpolation_basis(4, shape[1] - 2 * margin, margin, order=1)
    x = sparse_object(shape, seed=5)
    expected = (op @ x.ravel()).reshape(shape)
    result = sv_convolve_reference(x, filters.reshape(12, 7, 5), rows, cols, chunk_elements=200)
    assert np.linalg.norm(result - expected) <= 1e-12 * np.linalg.norm(expected)


@pytest.mark.parametrize("order", [1, 3])
def test_lowrank_error_falls_with_rank_to_float_precision(order):
    ranks = [1, 2, 4, 8, 25]
    table = lowrank_error(
        sparse_object((30, 34)), gaussian_psf_grid(), ranks, margin=2, order=order
    )
    assert [row.rank for row in table] == ranks
    errors = np.array([row.relative_error for row in table])
    energies = np.array([row.captured_energy for row in table])
    assert np.all(np.diff(errors) < 0) and np.all(np.diff(energies) > 0)
    assert errors[0] > 1e-2 and errors[-1] < 1e-12
    assert energies[-1] == pytest.approx(1.0, abs=1e-14)
    assert all(row.lowrank_seconds > 0 and row.reference_seconds > 0 for row in table)


@pytest.mark.parametrize("chunked", [False, True])
def test_full_rank_operator_matches_reference_with_huge_amplitude(chunked):
    psfs = gaussian_psf_grid()
    x = 1e6 * sparse_object((26, 26), seed=6)
    rows = interpolation_basis(5, 22, margin=2)
    reference = sv_convolve_reference(x, psfs, rows, rows)
    decomposition = decompose_psfs(psfs, tolerance=0.0)
    op = LowRankSVOperator.from_decomposition(decomposition, 22, margin=2, dtype=torch.float32)
    if chunked:  # the 25 components in chunks of 4 (6 × 4 + 1), their spectra kept
        per_lens, per_term = op._costs(1)
        budget = 25 * op._spectrum_bytes + per_lens + 4 * per_term
        op = LowRankSVOperator.from_decomposition(
            decomposition, 22, margin=2, dtype=torch.float32, memory_budget=budget
        )
        assert op.chunking(1) == (1, 4) and op._spectra.shape[0] == 1
    result = op.forward(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
    assert np.linalg.norm(result - reference) <= 1e-5 * np.linalg.norm(reference)


def test_reference_edge_cases():
    psfs = gaussian_psf_grid(3, 5)
    rows = interpolation_basis(3, 8)
    assert not sv_convolve_reference(np.zeros((8, 8)), psfs, rows, rows).any()
    x = np.ones((8, 8))
    x[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        sv_convolve_reference(x, psfs, rows, rows)
    with pytest.raises(ValueError, match="basis_rows"):
        sv_convolve_reference(np.ones((8, 9)), psfs, rows, rows)
    with pytest.raises(ValueError, match="zero"):
        lowrank_error(np.zeros((8, 8)), psfs, [1])
