"""Tile grid, blending, batching, skipping, progress and cancellation."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from svcode_core.methods.tiling import (
    Cancelled,
    TileGrid,
    blend_window,
    box_mean_3x3,
    exhaust,
    iter_tiled,
    tile_starts,
    tiles_with_signal,
)

SIZE, PATCH = 40, 16


def identity(tiles, origins):
    return tiles.copy(), tiles.mean(axis=1, keepdims=True)


def coordinates(tiles, origins):
    """Output = global pixel index of each pixel: tests the origins of every tile."""
    p = tiles.shape[-1]
    rows = origins[:, 0, None, None] + np.arange(p)[None, :, None]
    cols = origins[:, 1, None, None] + np.arange(p)[None, None, :]
    recon = (rows * 1000 + cols).astype(np.float32)[:, None]
    return np.repeat(recon, 9, axis=1), recon


def tile_dependent(tiles, origins):
    """Non-linear and different for every tile, so blending weights matter."""
    scale = (
        1.0 + tiles.mean(axis=(1, 2, 3), keepdims=True) + 0.01 * origins.sum(1)[:, None, None, None]
    )
    views = np.tanh(tiles) * scale
    return views.astype(np.float32), views.mean(axis=1, keepdims=True).astype(np.float32)


@pytest.fixture
def views() -> np.ndarray:
    return np.random.default_rng(0).random((9, SIZE, SIZE), dtype=np.float32)


@pytest.mark.parametrize(
    "size,patch,stride", [(40, 16, 8), (40, 16, 16), (40, 16, 5), (16, 16, 8), (97, 32, 7)]
)
def test_tile_starts_cover_the_field_flush(size, patch, stride):
    starts = tile_starts(size, patch, stride)
    assert starts[0] == 0 and starts[-1] == size - patch
    assert np.all(np.diff(starts) <= stride) and np.all(np.diff(starts) > 0)
    covered = np.zeros(size, bool)
    for s in starts:
        covered[s : s + patch] = True
    assert covered.all()


@pytest.mark.parametrize(
    "args,match",
    [
        ((10, 12, 4), "exceeds the sub-view"),
        ((10, 4, 5), "exceeds the tile"),
        ((10, 0, 1), "positive"),
    ],
)
def test_tile_starts_rejects_bad_sizes(args, match):
    with pytest.raises(ValueError, match=match):
        tile_starts(*args)


def test_grid_origins_row_major():
    grid = TileGrid(SIZE, PATCH, 8)
    starts = tile_starts(SIZE, PATCH, 8)
    assert len(grid) == len(starts) ** 2 == len(grid.origins)
    assert grid.origins[: len(starts), 0].tolist() == [0] * len(starts)
    assert grid.origins[: len(starts), 1].tolist() == starts.tolist()


def test_blend_window_positive_symmetric():
    w = blend_window(PATCH)
    assert w.shape == (PATCH, PATCH) and w.min() > 0
    np.testing.assert_array_equal(w, w.T)
    np.testing.assert_array_equal(w, w[::-1, ::-1])
    assert w.argmax() == np.ravel_multi_index((PATCH // 2 - 1, PATCH // 2 - 1), w.shape)


@pytest.mark.parametrize("stride", [8, 5, 16])
def test_identity_model_reproduces_input(views, stride):
    out = exhaust(iter_tiled(identity, views, TileGrid(SIZE, PATCH, stride), 4, return_views=True))
    # float32 sums of at most 4 × 4 weighted terms and one division: ~20 roundings at most
    rtol = 20 * np.finfo(np.float32).eps
    np.testing.assert_allclose(out.views, views, rtol=rtol, atol=0)
    np.testing.assert_allclose(out.reconstruction, views.mean(0), rtol=rtol, atol=0)
    assert out.tiles_skipped == 0 and out.tiles_run == len(TileGrid(SIZE, PATCH, stride))


def test_origins_are_global_coordinates(views):
    out = exhaust(iter_tiled(coordinates, views, TileGrid(SIZE, PATCH, 6), 3))
    rows, cols = np.indices((SIZE, SIZE))
    np.testing.assert_allclose(out.reconstruction, rows * 1000 + cols, rtol=1e-6)


def test_batch_size_does_not_change_the_result(views):
    grid = TileGrid(SIZE, PATCH, 6)
    one = exhaust(iter_tiled(tile_dependent, views, grid, 1, return_views=True))
    many = exhaust(iter_tiled(tile_dependent, views, grid, 16, return_views=True))
    np.testing.assert_allclose(one.reconstruction, many.reconstruction, atol=1e-6, rtol=0)
    np.testing.assert_allclose(one.views, many.views, atol=1e-6, rtol=0)


def test_batches_never_exceed_batch_size(views):
    sizes = []

    def model(tiles, origins):
        sizes.append(len(tiles))
        return identity(tiles, origins)

    exhaust(iter_tiled(model, views, TileGrid(SIZE, PATCH, 8), 3))
    assert max(sizes) == 3 and sum(sizes) == len(TileGrid(SIZE, PATCH, 8))


def _sparse_scene(floor: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scene = (floor * rng.standard_normal((9, 96, 96))).astype(np.float32)
    scene[:, 10:13, 12:15] += 50 * floor  # one bead near the top-left corner
    return scene


def test_signal_detection_ignores_noise_keeps_beads():
    floor = 1e-3
    scene = _sparse_scene(floor)
    grid = TileGrid(96, 16, 8)
    signal = tiles_with_signal(scene, grid, 5 * floor)
    hit = [(r <= 12 and r + 16 > 10 and c <= 14 and c + 16 > 12) for r, c in grid.origins]
    np.testing.assert_array_equal(signal, hit)


def test_skipping_changes_only_signal_free_pixels():
    floor = 1e-3
    scene = _sparse_scene(floor)
    grid = TileGrid(96, 16, 8)
    active = tiles_with_signal(scene, grid, 5 * floor)
    dense = exhaust(iter_tiled(tile_dependent, scene, grid, 8))
    sparse = exhaust(iter_tiled(tile_dependent, scene, grid, 8, active=active))
    assert sparse.tiles_skipped == (~active).sum() > 0.8 * len(grid)
    changed = sparse.reconstruction != dense.reconstruction
    # every changed pixel lies in a skipped tile, and no input there is signal
    in_skipped = np.zeros((96, 96), bool)
    for r, c in grid.origins[~active]:
        in_skipped[r : r + 16, c : c + 16] = True
    assert not (changed & ~in_skipped).any()
    assert scene.max(0)[changed].max() < 5 * floor
    # the bead's reconstruction is untouched, uncovered pixels are background 0
    np.testing.assert_array_equal(
        sparse.reconstruction[8:16, 8:16], dense.reconstruction[8:16, 8:16]
    )
    assert sparse.reconstruction[60:, 60:].max() == 0


def test_identity_skip_result_equals_dense_where_any_tile_ran():
    floor = 1e-3
    scene = _sparse_scene(floor)
    grid = TileGrid(96, 16, 8)
    active = tiles_with_signal(scene, grid, 5 * floor)
    dense = exhaust(iter_tiled(identity, scene, grid, 8, return_views=True))
    sparse = exhaust(iter_tiled(identity, scene, grid, 8, active=active, return_views=True))
    ran = np.zeros((96, 96), bool)
    for r, c in grid.origins[active]:
        ran[r : r + 16, c : c + 16] = True
    np.testing.assert_allclose(sparse.views[:, ran], dense.views[:, ran], rtol=1e-6)
    assert np.all(sparse.views[:, ~ran] == 0)


def test_progress_after_every_batch(views):
    grid = TileGrid(SIZE, PATCH, 8)
    steps = list(iter_tiled(identity, views, grid, 4))
    assert [s.done for s in steps] == list(range(4, len(grid), 4)) + [len(grid)]
    assert all(s.total == len(grid) for s in steps)


def test_cancel_flag_and_close_stop_after_a_batch(views):
    calls = []

    def model(tiles, origins):
        calls.append(len(tiles))
        return identity(tiles, origins)

    cancel = threading.Event()
    gen = iter_tiled(model, views, TileGrid(SIZE, PATCH, 8), 2, cancel=cancel)
    next(gen)
    cancel.set()
    with pytest.raises(Cancelled):
        next(gen)
    assert len(calls) == 1  # no batch runs once the flag is seen
    gen = iter_tiled(model, views, TileGrid(SIZE, PATCH, 8), 2)
    next(gen)
    gen.close()
    assert len(calls) == 2


def test_bad_views_and_model_outputs_raise(views):
    grid = TileGrid(SIZE, PATCH, 8)
    with pytest.raises(ValueError, match="sub-views must"):
        exhaust(iter_tiled(identity, views[:8], grid))
    with pytest.raises(ValueError, match="reconstruction of shape"):
        exhaust(iter_tiled(lambda t, o: (t, t), views, grid))
    with pytest.raises(ValueError, match="NaN or Inf"):
        exhaust(iter_tiled(lambda t, o: (t, t[:, :1] * np.nan), views, grid))
    with pytest.raises(ValueError, match="batch_size"):
        exhaust(iter_tiled(identity, views, grid, 0))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_box_mean_matches_scipy(dtype):
    """Against scipy.ndimage.uniform_filter (mode "nearest"). SciPy keeps a running sum
    along each axis (one rounding of a value up to 3·max per step), so the two agree to
    about (steps along both axes + the few of the direct sum) rounding units of the max."""
    from scipy.ndimage import uniform_filter

    image = np.random.default_rng(0).random((37, 52)).astype(dtype) * 1e3
    expected = uniform_filter(image, size=3, mode="nearest")
    mine = box_mean_3x3(image)
    assert mine.dtype == dtype
    bound = (sum(image.shape) + 10) * np.finfo(dtype).eps * image.max()
    np.testing.assert_allclose(mine, expected, rtol=0, atol=bound)
