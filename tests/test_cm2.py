import numpy as np
import pytest
import torch

from svcode_core.physics.cm2 import CM2Operator, simulation_cost
from svcode_core.physics.geometry import (
    crop_to_sensor,
    extract_sub_views,
    place_sub_views,
    sub_view_origins,
)


def gaussian_psfs(system, widths=(0.8, 2.0)) -> np.ndarray:
    """Smoothly field-dependent, elongated Gaussian PSFs on the system's grid, per lens."""
    k = system.optics.kernel_size
    grid = system.optics.psf_grid
    axis = np.arange(k) - k // 2
    yy, xx = np.meshgrid(axis, axis, indexing="ij")
    coords = np.linspace(-1, 1, grid)
    psfs = np.zeros((9, grid * grid, k, k))
    for lens in range(9):
        for g, (v, u) in enumerate((v, u) for v in coords for u in coords):
            sy = widths[0] + (widths[1] - widths[0]) * abs(v) * (1 + lens / 9)
            sx = widths[0] + (widths[1] - widths[0]) * abs(u)
            psf = np.exp(-0.5 * ((yy / sy) ** 2 + (xx / sx) ** 2))
            psfs[lens, g] = psf / psf.sum() * (1 - 0.3 * (v * v + u * u) / 2)
    return psfs


def delta_psfs(system) -> np.ndarray:
    k = system.optics.kernel_size
    psfs = np.zeros((9, system.optics.psf_grid**2, k, k))
    psfs[..., k // 2, k // 2] = 1.0
    return psfs


def test_point_source_gives_nine_spots_at_chief_rays(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, delta_psfs(tiny_system), dtype=torch.float64)
    size = tiny_system.sub_view_size
    r = (5, -7)  # offset from the object centre, pixels
    x = torch.zeros(size, size, dtype=torch.float64)
    x[size // 2 + r[0], size // 2 + r[1]] = 1.0
    frame = op.forward(x)
    spots = {tuple(p) for p in torch.nonzero(frame > 1e-9).tolist()}  # FFT round-off aside
    window_rows, window_cols = tiny_system.sensor_window
    expected = set()
    for c in tiny_system.chief_rays:
        p = (c[0] + r[0], c[1] + r[1])
        on_sensor = window_rows.start <= p[0] < window_rows.stop
        on_sensor &= window_cols.start <= p[1] < window_cols.stop
        if on_sensor:
            expected.add(p)
    assert spots == expected
    assert len(expected) == 9  # a central point is seen by every lens


def test_edge_point_seen_by_fewer_lenses(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, delta_psfs(tiny_system), dtype=torch.float64)
    x = torch.zeros(tiny_system.sub_view_size, tiny_system.sub_view_size, dtype=torch.float64)
    x[0, 0] = 1.0  # the object corner: the outer lenses image it off the sensor
    assert 0 < int((op.forward(x) > 1e-9).sum()) < 9


def test_lens_images_are_the_own_view_parts(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float64)
    x = torch.rand(tiny_system.sub_view_size, tiny_system.sub_view_size, dtype=torch.float64)
    targets = op.lens_images(x)
    views = extract_sub_views(op.forward(x), tiny_system)
    # each view holds its own lens image plus non-negative crosstalk from the others
    assert torch.all(views - targets >= -1e-12)
    assert torch.all(targets >= -1e-12)
    # the central lens's sub-view is fully inside the sensor
    origin = sub_view_origins(tiny_system)[4]
    assert origin.min() >= 0


def test_blur_past_object_edge_is_kept(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float64)
    x = torch.ones(tiny_system.sub_view_size, tiny_system.sub_view_size, dtype=torch.float64)
    blur = op.lens_blur(x)
    assert blur[4, :, : op.margin].sum() > 0  # light outside the object grid


def test_extreme_objects(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float32)
    size = tiny_system.sub_view_size
    assert op.forward(torch.zeros(size, size)).abs().max() == 0
    x = torch.rand(size, size, generator=torch.Generator().manual_seed(3))
    big = op.forward(1e6 * x)
    assert torch.isfinite(big).all()
    torch.testing.assert_close(big / 1e6, op.forward(x), rtol=1e-5, atol=1e-6)
    bad = x.clone()
    bad[3, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        op.forward(bad)
    with pytest.raises(ValueError, match="object must have shape"):
        op.forward(torch.zeros(size + 1, size))


def test_zero_energy_psf_is_harmless(tiny_system):
    psfs = gaussian_psfs(tiny_system)
    psfs[3] = 0.0  # a lens whose PSFs are truncated away completely
    op = CM2Operator.from_psfs(tiny_system, psfs, dtype=torch.float64)
    x = torch.rand(tiny_system.sub_view_size, tiny_system.sub_view_size, dtype=torch.float64)
    assert torch.isfinite(op.forward(x)).all()
    assert op.lens_images(x)[3].abs().max() == 0
    assert torch.isfinite(op.adjoint(op.forward(x))).all()


def test_measure_with_targets_matches_separate_calls(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float64)
    x = torch.rand(tiny_system.sub_view_size, tiny_system.sub_view_size, dtype=torch.float64)
    frame, targets = op.measure_with_targets(x)
    torch.testing.assert_close(frame, op.measure(x), rtol=0, atol=0)
    torch.testing.assert_close(targets, op.lens_images(x), rtol=0, atol=0)


@pytest.mark.parametrize("dtype, tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_memory_budget_chunks_lenses_and_components_unevenly(tiny_system, dtype, tol):
    psfs = gaussian_psfs(tiny_system)
    whole = CM2Operator.from_psfs(tiny_system, psfs, rank=5, dtype=dtype)
    per_lens, per_term = whole.lenses._costs(2)
    spectra = 9 * 5 * whole.lenses._spectrum_bytes
    budgets = {  # budget → (chunks of 9 lenses × 5 components, lenses with kept spectra)
        spectra + per_lens + 2 * per_term: ((1, 2), 7),  # 1 × (2 + 2 + 1)
        spectra + 2 * (per_lens + 5 * per_term): ((2, 5), 9),  # (2 + 2 + 2 + 2 + 1) × 5
    }
    gen = torch.Generator().manual_seed(0)
    size = tiny_system.sub_view_size
    x = torch.rand(2, size, size, generator=gen, dtype=dtype)
    y = torch.randn(2, *tiny_system.padded_shape, generator=gen, dtype=dtype)
    for budget, (chunks, kept) in budgets.items():
        op = CM2Operator.from_psfs(tiny_system, psfs, rank=5, dtype=dtype, memory_budget=budget)
        assert op.lenses.chunking(2) == chunks and op.lenses._spectra.shape[0] == kept
        ax, aty = op.forward(x), op.adjoint(y)
        for result, expected in ((ax, whole.forward(x)), (aty, whole.adjoint(y))):
            assert (result - expected).norm() <= tol * expected.norm()
        assert abs((ax * y).sum() - (x * aty).sum()) <= tol * abs((ax * y).sum())


def test_simulation_cost_names_the_rank_and_grows_with_the_field(tiny_system):
    small = simulation_cost(tiny_system)
    assert small.rank == CM2Operator.from_system(tiny_system).decompositions[0].rank
    assert simulation_cost(tiny_system.replace(rank=3)).rank == 3
    assert small.memory > 0 and small.seconds > 0
    double = tiny_system.replace(sub_view_size=2 * tiny_system.sub_view_size)
    assert simulation_cost(double).memory > small.memory


def test_lens_images_past_the_window(tiny_system):
    """Run on past the window by the whole margin, the nine lens images placed back give
    the measurement exactly (nothing of a lens's light on the sensor is left out); their
    middle is the ordinary targets; past the window they hold the border's light."""
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float64)
    size, m = tiny_system.sub_view_size, op.margin
    x = torch.rand(size, size, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    frame, wide = op.measure_with_targets(x, past=m)
    assert wide.shape == (9, size + 2 * m, size + 2 * m)
    placed = crop_to_sensor(place_sub_views(wide, tiny_system, m), tiny_system)
    torch.testing.assert_close(placed, frame, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(wide[:, m:-m, m:-m], op.lens_images(x), rtol=0, atol=0)
    assert wide[4, :, :m].sum() > 0  # the centre lens's spill past its left edge
    cut = m - m // 2
    torch.testing.assert_close(op.lens_images(x, past=m // 2), wide[:, cut:-cut, cut:-cut],
                               rtol=0, atol=0)  # fmt: skip
    for bad in (-1, m + 1, 1.5, True):
        with pytest.raises(ValueError, match="past must be an integer"):
            op.lens_images(x, past=bad)
