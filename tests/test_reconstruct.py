"""Reconstructor: raw frame → sub-views → tiled model, validation, devices, precision."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from svcode_core.methods.base import FrameProgress
from svcode_core.methods.svcode import Reconstructor
from svcode_core.methods.tiling import Cancelled
from svcode_core.physics.geometry import extract_sub_views, pad_sensor_frame


class IdentityModel(torch.nn.Module):
    """Demixed = input, reconstruction = mean of the nine views."""

    def forward(self, views, origins, sub_view_size):
        return views.clone(), views.mean(1, keepdim=True)


class CoordinateModel(torch.nn.Module):
    """Reconstruction = global normalised row + 10 × column coordinate of every pixel."""

    def forward(self, views, origins, sub_view_size):
        assert origins.dtype == torch.long and origins.shape == (views.shape[0], 2)
        p = views.shape[-1]
        ramp = torch.arange(p, device=views.device)
        rows = (origins[:, 0, None, None] + ramp[None, :, None]) / (sub_view_size - 1)
        cols = (origins[:, 1, None, None] + ramp[None, None, :]) / (sub_view_size - 1)
        recon = (rows + 10 * cols).float()[:, None]
        return views.clone(), recon


class ConvModel(torch.nn.Module):
    """A small random non-linear convolutional stand-in with the SV-CoDe signature."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.demix = torch.nn.Conv2d(9, 9, 3, padding=1)
        self.recon = torch.nn.Conv2d(9, 1, 3, padding=1)

    def forward(self, views, origins, sub_view_size):
        demixed = torch.sigmoid(self.demix(views))
        return demixed, torch.sigmoid(self.recon(demixed))


def _frame(system, seed=0, shape=None):
    rng = np.random.default_rng(seed)
    return rng.random(shape or system.sensor_shape, dtype=np.float32)


def _sub_views(frame, system):
    return extract_sub_views(pad_sensor_frame(torch.from_numpy(frame), system), system).numpy()


def test_identity_model_returns_the_sub_views(tiny_system):
    frame = _frame(tiny_system)
    result = Reconstructor(IdentityModel(), tiny_system, skip_empty=False)(frame, return_views=True)
    size = tiny_system.sub_view_size
    assert result.reconstruction.shape == (size, size) and result.reconstruction.dtype == np.float32
    expected = _sub_views(frame, tiny_system)
    rtol = 20 * np.finfo(np.float32).eps
    np.testing.assert_allclose(result.views, expected, rtol=rtol, atol=1e-7)
    np.testing.assert_allclose(result.reconstruction, expected.mean(0), rtol=rtol, atol=1e-7)
    assert result.tiles_run == result.tiles_total and result.tiles_skipped == 0
    assert set(result.timings) == {"prepare", "model", "blend", "refine", "total"}


def test_origins_reach_the_model_as_global_coordinates(tiny_system):
    result = Reconstructor(
        CoordinateModel(), tiny_system, tile_size=16, stride=6, skip_empty=False,
        normalise_exposure=False,  # the stand-in's output does not scale with its input
    )(_frame(tiny_system))
    rows, cols = np.indices(result.reconstruction.shape) / (tiny_system.sub_view_size - 1)
    np.testing.assert_allclose(result.reconstruction, rows + 10 * cols, rtol=1e-6)


def test_batch_size_one_and_sixteen_agree(tiny_system):
    frame = _frame(tiny_system)
    model = ConvModel()
    one = Reconstructor(model, tiny_system, batch_size=1, skip_empty=False)(frame, True)
    many = Reconstructor(model, tiny_system, batch_size=16, skip_empty=False)(frame, True)
    np.testing.assert_allclose(one.reconstruction, many.reconstruction, atol=1e-6, rtol=0)
    np.testing.assert_allclose(one.views, many.views, atol=1e-6, rtol=0)


def test_stack_matches_frame_by_frame(tiny_system):
    stack = np.stack([_frame(tiny_system, seed) for seed in range(3)])
    rec = Reconstructor(ConvModel(), tiny_system, skip_empty=False)
    result = rec(stack, return_views=True)
    size = tiny_system.sub_view_size
    assert result.reconstruction.shape == (3, size, size)
    assert result.views.shape == (3, 9, size, size)
    for index, frame in enumerate(stack):
        single = rec(frame, return_views=True)
        np.testing.assert_array_equal(result.reconstruction[index], single.reconstruction)
        np.testing.assert_array_equal(result.views[index], single.views)
    assert result.tiles_total == 3 * len(rec.grid)


def test_dark_frame_skips_every_tile_and_gives_background(tiny_system):
    rec = Reconstructor(ConvModel(), tiny_system)
    result = rec(np.zeros(tiny_system.sensor_shape, np.float32))
    assert result.tiles_skipped == len(rec.grid) and result.tiles_run == 0
    assert np.all(result.reconstruction == 0)


def test_a_frame_too_dim_for_every_tile_is_zero_with_a_warning(tiny_system):
    rec = Reconstructor(ConvModel(), tiny_system)
    dim = _frame(tiny_system) * (0.5 * rec.skip_threshold / _frame(tiny_system).max())
    with pytest.warns(UserWarning, match="below the skipping threshold in every tile") as seen:
        result = rec(dim)
    assert result.tiles_run == 0 and np.all(result.reconstruction == 0)
    assert "--input-scale" in str(seen[0].message) and "--no-skip" in str(seen[0].message)
    with pytest.warns(UserWarning, match="blank frames"):  # not "too dim"
        assert rec(dim * 0).tiles_run == 0
    assert Reconstructor(ConvModel(), tiny_system, skip_empty=False)(dim).reconstruction.any()


def test_negative_values_are_clipped_to_zero(tiny_system):
    frame = _frame(tiny_system) - 0.3
    rec = Reconstructor(ConvModel(), tiny_system, skip_empty=False)
    np.testing.assert_array_equal(
        rec(frame).reconstruction, rec(np.maximum(frame, 0)).reconstruction
    )


def test_bf16_close_to_fp32(tiny_system):
    frame = _frame(tiny_system)
    fp32 = Reconstructor(ConvModel(), tiny_system, skip_empty=False)(frame).reconstruction
    bf16 = Reconstructor(ConvModel(), tiny_system, precision="bf16", skip_empty=False)(frame)
    assert bf16.reconstruction.dtype == np.float32
    np.testing.assert_allclose(bf16.reconstruction, fp32, atol=2e-2)  # bf16 has 8 mantissa bits


def test_progress_and_cancel(tiny_system):
    stack = np.stack([_frame(tiny_system, seed) for seed in range(2)])
    rec = Reconstructor(IdentityModel(), tiny_system, batch_size=4, skip_empty=False)
    steps = list(rec.iter_reconstruct(stack))
    assert all(isinstance(step, FrameProgress) for step in steps)
    assert [s.frame for s in steps].count(1) == -(-len(rec.grid) // 4)
    assert steps[-1] == FrameProgress(1, 2, len(rec.grid), len(rec.grid))
    cancel = threading.Event()
    gen = rec.iter_reconstruct(stack, cancel=cancel)
    next(gen)
    cancel.set()
    with pytest.raises(Cancelled):
        next(gen)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda s: np.full(s.sensor_shape, np.nan, np.float32), "NaN or Inf"),
        (lambda s: np.where(np.eye(*s.sensor_shape) > 0, np.inf, 0.0), "NaN or Inf"),
        (lambda s: np.zeros((50, 50)), r"50×50 pixels but system 'tiny' expects .* 60×80"),
        (lambda s: np.zeros(s.padded_shape), "padded size"),
        (lambda s: np.ones((*s.sensor_shape, 3), np.uint8), "a colour image"),
        (lambda s: np.zeros((0, *s.sensor_shape)), "empty"),
        (lambda s: np.zeros(s.sensor_shape[0]), "shape"),
        (lambda s: np.zeros((1, 1, *s.sensor_shape)), "shape"),
        (lambda s: np.full(s.sensor_shape, "a"), "real numbers"),
    ],
)
def test_bad_inputs_raise_clear_errors(tiny_system, make, match):
    rec = Reconstructor(IdentityModel(), tiny_system)
    with pytest.raises(ValueError, match=match):
        rec(make(tiny_system))


def test_nan_in_a_later_frame_names_it(tiny_system):
    stack = np.stack([_frame(tiny_system, seed) for seed in range(3)])
    stack[2, 5, 5] = np.nan
    with pytest.raises(ValueError, match="frame 2 holds 1 NaN"):
        Reconstructor(IdentityModel(), tiny_system)(stack)


@pytest.mark.parametrize(
    "options,match",
    [
        ({"precision": "fp16"}, "fp16 is not supported on the CPU"),
        ({"precision": "fp64"}, "precision"),
        ({"device": "quantum"}, "device"),
        ({"tile_size": 64}, "exceeds the sub-view size"),
        ({"tile_size": 16, "stride": 20}, "exceeds the tile size"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_bad_options_raise(tiny_system, options, match):
    with pytest.raises(ValueError, match=match):
        Reconstructor(IdentityModel(), tiny_system, **options)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA present")
def test_unavailable_cuda_is_a_clear_error(tiny_system):
    with pytest.raises(ValueError, match="CUDA is not available"):
        Reconstructor(IdentityModel(), tiny_system, device="cuda")


@pytest.mark.skipif(torch.backends.mps.is_available(), reason="MPS present")
def test_unavailable_mps_is_a_clear_error(tiny_system):
    with pytest.raises(ValueError, match="MPS"):
        Reconstructor(IdentityModel(), tiny_system, device="mps")


def test_moved_chief_rays_cut_the_same_sub_views_for_the_same_model(tiny_system, tiny_weights):
    """An SV-CoDe model sees sub-views and coordinates relative to them: a system whose
    chief rays moved, given the frame moved with them, gives the same reconstruction."""
    from svcode_core.methods.model_file import load_model

    model, _ = load_model(tiny_weights)
    shift = np.array([2, -3])
    moved = tiny_system.replace(chief_rays=tuple(
        (int(r), int(c)) for r, c in np.asarray(tiny_system.chief_rays) + shift))
    frame = np.zeros(tiny_system.sensor_shape, np.float32)
    frame[4:-4, 4:-4] = np.random.default_rng(3).random((52, 72), dtype=np.float32)
    shifted = np.roll(frame, tuple(shift), axis=(0, 1))  # the border is zero: nothing wraps
    nominal = Reconstructor(model, tiny_system, skip_empty=False)
    at_moved = Reconstructor(model, moved, skip_empty=False)
    np.testing.assert_array_equal(at_moved.prepare(shifted), nominal.prepare(frame))
    expected = nominal.reconstruct(frame, return_views=True)
    result = at_moved.reconstruct(shifted, return_views=True)
    np.testing.assert_allclose(result.reconstruction, expected.reconstruction, atol=1e-6)
    np.testing.assert_allclose(result.views, expected.views, atol=1e-6)
    # the same frame cut at other rays is another input: the result changes
    assert not np.allclose(at_moved.reconstruct(frame).reconstruction, expected.reconstruction)


@pytest.mark.parametrize("unshuffle", [1, 2])
def test_a_lens_context_model_gets_the_crops_a_pitch_away(tiny_system, unshuffle):
    from svcode_core.network import ModelConfig, SVCoDe, with_lens_context
    from svcode_core.physics.geometry import context_views

    torch.manual_seed(0)
    plain = SVCoDe(ModelConfig.mini().replace(pixel_unshuffle=unshuffle))
    frame = np.random.default_rng(0).random(tiny_system.sensor_shape, dtype=np.float32)
    wide = Reconstructor(with_lens_context(plain), tiny_system)
    crops = wide.prepare(frame)
    padded = pad_sensor_frame(torch.from_numpy(frame), tiny_system)
    np.testing.assert_array_equal(crops, context_views(padded, tiny_system).numpy())
    # the new inputs start with zero weights: the same reconstruction as the plain model
    expected = Reconstructor(plain, tiny_system)(frame).reconstruction
    np.testing.assert_allclose(wide(frame).reconstruction, expected, rtol=1e-5, atol=1e-6)


def test_a_longer_lens_context_reach_starts_where_the_shorter_one_was(tiny_system):
    """Widened from reach 1 to 2, a model takes the 99 crops of reach 2 and, its new inputs
    at zero weight, reconstructs as before; a reach it already has is refused."""
    from svcode_core.network import ModelConfig, SVCoDe, with_lens_context
    from svcode_core.physics.geometry import context_views

    torch.manual_seed(0)
    near = with_lens_context(SVCoDe(ModelConfig.mini()))
    torch.nn.init.normal_(near.demix.intro.weight, std=0.1)  # every reach-1 crop weighs
    far = with_lens_context(near, reach=2)
    assert far.model_config.context_reach == 2 and far.demix.views_per_lens == 11
    frame = np.random.default_rng(1).random(tiny_system.sensor_shape, dtype=np.float32)
    padded = pad_sensor_frame(torch.from_numpy(frame), tiny_system)
    wide = Reconstructor(far, tiny_system)
    np.testing.assert_array_equal(wide.prepare(frame),
                                  context_views(padded, tiny_system, reach=2).numpy())
    expected = Reconstructor(near, tiny_system)(frame).reconstruction
    np.testing.assert_allclose(wide(frame).reconstruction, expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="already has lens context of reach 2"):
        with_lens_context(far, reach=2)
