"""One exposure for the learned methods (svcode_core.methods.exposure), and blank frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.exposure import REFERENCE_LEVEL, exposure_gain, exposure_level
from svcode_core.methods.svcode import Reconstructor
from svcode_core.network import SVCoDe


def _scene(system, seed=0):
    rng = np.random.default_rng(seed)
    return (0.2 + rng.random(system.sensor_shape, dtype=np.float32)).astype(np.float32)


def test_the_level_scales_with_the_frame_and_ignores_hot_pixels():
    rng = np.random.default_rng(1)
    frame = rng.random((40, 50)).astype(np.float32)
    # powers of two scale every sum and maximum exactly
    assert exposure_level(frame / 16) == exposure_level(frame) / 16
    hot = frame.copy()
    hot[20, 25] = 1e3  # one pixel far above its neighbours
    assert exposure_level(hot) == pytest.approx(exposure_level(frame), rel=0.05)
    spot = np.zeros((40, 50), np.float32)
    spot[10:12, 10:12] = 3.0  # a 2 × 2 spot (a small bead) counts
    assert exposure_level(spot) == pytest.approx(4 * 3.0 / 9)
    assert exposure_gain(np.zeros((8, 8))) == 1.0
    assert exposure_gain(spot) == pytest.approx(REFERENCE_LEVEL / (4 * 3.0 / 9))


@pytest.mark.parametrize("shape", [(40, 50), (3, 17, 9), (1, 1), (2, 3)])
def test_the_level_is_scipys_filters(shape):
    """The same rule written with scipy.ndimage's filters (zeros outside the frame)."""
    from scipy import ndimage

    rng = np.random.default_rng(2)
    frame = (rng.random(shape) ** 4).astype(np.float32)
    frame.flat[rng.integers(frame.size)] = 30.0
    plane = (1,) * (frame.ndim - 2)
    neighbours = np.ones((3, 3), bool)
    neighbours[1, 1] = False
    despiked = np.minimum(frame, ndimage.maximum_filter(
        frame, footprint=neighbours.reshape(plane + (3, 3)), mode="constant"))
    expected = ndimage.uniform_filter(despiked, size=plane + (3, 3), mode="constant").max()
    # float32 sums of three then three values, in another order: a few units of rounding
    assert exposure_level(frame) == pytest.approx(float(expected), rel=4 * 2.0**-24, abs=0)


def test_svcode_is_exactly_scale_equivariant(tiny_system, tiny_model_config):
    """A power-of-two scale reaches the network as the same bits (the gain absorbs it
    exactly), so the output is the reconstruction of the frame, scaled: equal bit for bit."""
    torch.manual_seed(0)
    rec = Reconstructor(SVCoDe(tiny_model_config), tiny_system, skip_empty=False)
    frame = _scene(tiny_system)
    full = rec.reconstruct(frame, return_views=True)
    dim = rec.reconstruct(frame / 32, return_views=True)
    np.testing.assert_array_equal(dim.reconstruction * 32, full.reconstruction)
    np.testing.assert_array_equal(dim.views * 32, full.views)
    assert dim.exposure_gains[0] == 32 * full.exposure_gains[0]


def test_without_normalisation_the_network_sees_the_frame_as_it_is(tiny_system,
                                                                    tiny_model_config):
    torch.manual_seed(0)
    model = SVCoDe(tiny_model_config)
    plain = Reconstructor(model, tiny_system, skip_empty=False, normalise_exposure=False)
    frame = _scene(tiny_system)
    result = plain.reconstruct(frame)
    assert result.exposure_gains[0] == 1.0
    with torch.inference_mode():
        views = torch.from_numpy(plain.prepare(frame))[None]
        origin = torch.zeros(1, 2, dtype=torch.long)
        expected = model(views, origin, tiny_system.sub_view_size)[1][0, 0].numpy()
    np.testing.assert_allclose(result.reconstruction, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_the_bundled_model_gives_one_image_at_any_exposure(mini_system):
    """The same simulated frame read at 1, 0.05 and 0.02 of its gain: the reconstructions,
    scaled back, agree to float32 rounding (a gain that is not a power of two rounds the
    network's input by at most one unit in the last place: 2⁻²³ relative)."""
    from svcode_core.evaluation.metrics import psnr
    from svcode_core.phantoms import make_object
    from svcode_core.physics.simulate import Simulator

    truth = make_object("cells", mini_system.sub_view_size, 3)
    raw = Simulator(mini_system).simulate(truth, seed=3).measurement.astype(np.float32)
    rec = Reconstructor.pretrained("cm2-mini")
    reference = rec.reconstruct(raw).reconstruction
    for scale in (0.05, 0.02):
        scaled = rec.reconstruct(raw * np.float32(scale)).reconstruction / np.float32(scale)
        # 60 dB: ten thousand times the input rounding, amplified through the network
        assert psnr(reference, scaled, float(reference.max())) > 60


@pytest.mark.parametrize("method", ["svcode", "admm", "wiener", "rl"])
def test_a_blank_frame_is_zero_with_a_warning(tiny_system, tiny_weights, method):
    weights = tiny_weights if method == "svcode" else None
    options = {"iterations": 2} if method in ("admm", "rl") else {}
    rec = build_reconstructor(method, tiny_system, weights, **options)
    stack = np.stack([_scene(tiny_system), np.zeros(tiny_system.sensor_shape, np.float32)])
    with pytest.warns(UserWarning, match="blank frames"):
        result = rec.reconstruct(stack)
    assert not result.reconstruction[1].any()
    assert result.reconstruction[0].any()


# ------------------------------------------------------------------- training samples
@pytest.fixture(scope="module")
def departed_data(tmp_path_factory):
    """Four frames of the tiny system through drawn instruments (photon level recorded)."""
    import dataclasses

    from svcode_core.config import SystemConfig
    from svcode_core.physics.departures import Departures
    from svcode_core.training.dataset import DataRecipe, TrainingData, generate_dataset

    system = SystemConfig.tiny()
    ranges = dataclasses.replace(Departures.named("realistic", system), truth_psf_grid=None,
                                 depth_spread_waves=0.1)
    plan = DataRecipe(frames=4, seed=2, val_fraction=0.25, object_kind="cells",
                      departures=ranges, instrument_frames=2)
    folder = tmp_path_factory.mktemp("data") / "data"
    generate_dataset(folder, system, plan, progress=False)
    return TrainingData(folder)


def test_normalised_samples_scale_inputs_and_targets_alike(departed_data):
    from svcode_core.physics.geometry import assemble_frame, crop_to_sensor
    from svcode_core.training.sampler import PatchDataset

    frames = departed_data.train_frames
    plain = PatchDataset(departed_data, frames, fixed_noise=True, seed=1)
    normal = PatchDataset(departed_data, frames, fixed_noise=True, seed=1,
                          normalise_exposure=True)
    first, second = plain[0], normal[0]
    frame, _ = plain.locate(0)
    gain = normal.gain(frame)
    for key in ("views", "demixed", "object"):
        torch.testing.assert_close(second[key], first[key] * gain)
    # the level of a noisy reading, as a reconstructor measures it: near the noiseless
    # frame's for a scene well above the noise (the noise adds a few per cent to its peak)
    sensor = crop_to_sensor(assemble_frame(torch.from_numpy(np.array(
        departed_data.views[frame])), departed_data.system), departed_data.system)
    assert gain == pytest.approx(REFERENCE_LEVEL / exposure_level(sensor.numpy()), rel=0.1)


def test_an_empty_scene_gets_the_gain_inference_would_give(departed_data, tmp_path):
    """A scene at 1e-5 of full scale is read as noise: its training gain is the one a
    reconstructor computes from such readings, not the noiseless frame's (over 100× larger,
    as for the empty scene of the cm2-mini training data)."""
    import shutil

    from svcode_core.methods.exposure import exposure_gain
    from svcode_core.physics.geometry import assemble_frame, crop_to_sensor
    from svcode_core.training.dataset import TrainingData
    from svcode_core.training.sampler import PatchDataset

    folder = tmp_path / "data"
    shutil.copytree(departed_data.path, folder)
    frame = departed_data.train_frames[0]
    views = np.load(folder / "views.npy", mmap_mode="r+")
    views[frame] *= 1e-5
    views.flush()
    del views
    data = TrainingData(folder)
    sensor = crop_to_sensor(assemble_frame(data.read(data.views[frame]), data.system),
                            data.system)  # fmt: skip
    readings = [exposure_gain(data.frame_sensor(frame).read(
        sensor, torch.Generator().manual_seed(seed)).numpy()) for seed in range(8)]
    gain = PatchDataset(data, [frame], normalise_exposure=True).gain(frame)
    assert min(readings) / 1.5 <= gain <= 1.5 * max(readings)
    assert gain < 1e-2 * exposure_gain(sensor.numpy())  # the noiseless measurement


def test_a_photon_range_draws_dimmer_samples(departed_data):
    """Fewer photons at the same intensity: the same mean, more shot noise."""
    from svcode_core.training.sampler import PatchDataset

    frames = departed_data.train_frames
    clean = PatchDataset(departed_data, frames, noise=False)[0]["views"]
    noise = {}
    for photons in ((1.0, 1.0), (1 / 16, 1 / 16)):
        data = PatchDataset(departed_data, frames, seed=3, photon_range=photons)
        noise[photons] = torch.stack([data[(0, s)]["views"] - clean for s in range(8)]).std()
    # shot noise grows as 1/sqrt(photons): 4× at 1/16; read noise in electrons, too
    assert noise[(1 / 16, 1 / 16)] > 3 * noise[(1.0, 1.0)]
    with pytest.raises(ValueError, match="photon_range"):
        PatchDataset(departed_data, frames, photon_range=(1.0, 0.5))
