import numpy as np
import pytest
import torch
from test_cm2 import gaussian_psfs

from svcode_core.io import read_tiff
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.simulate import Simulator


@pytest.fixture
def simulator(tiny_system):
    op = CM2Operator.from_psfs(tiny_system, gaussian_psfs(tiny_system), dtype=torch.float32)
    return Simulator(tiny_system, operator=op)


def test_shapes_and_consistency(simulator, tiny_system):
    size = tiny_system.sub_view_size
    obj = np.random.default_rng(0).random((size, size)).astype(np.float32) * 0.5
    scene = simulator.simulate(obj, seed=1, noise=False)
    assert scene.measurement.shape == tiny_system.sensor_shape
    assert scene.views.shape == scene.demixed.shape == (9, size, size)
    np.testing.assert_array_equal(scene.object, obj)
    # without noise each sub-view is its own lens image plus crosstalk
    assert np.all(scene.views - scene.demixed >= -1e-6)


def test_noise_is_seeded_and_frames_differ(simulator, tiny_system):
    size = tiny_system.sub_view_size
    obj = np.full((size, size), 0.3, np.float32)
    a = simulator.simulate(obj, seed=5, frames=3)
    b = simulator.simulate(obj, seed=5, frames=3)
    c = simulator.simulate(obj, seed=6, frames=3)
    assert a.measurement.shape == (3, *tiny_system.sensor_shape)
    np.testing.assert_array_equal(a.measurement, b.measurement)
    assert not np.array_equal(a.measurement, c.measurement)
    assert not np.array_equal(a.measurement[0], a.measurement[1])
    assert np.isfinite(a.measurement).all() and a.measurement.max() <= 1.0


def test_save_writes_five_files_with_system(simulator, tiny_system, tmp_path):
    size = tiny_system.sub_view_size
    scene = simulator.simulate(np.zeros((size, size), np.float32), seed=0)
    scene.save(tmp_path, tiny_system, extra={"seed": 0})
    for name in ("measurement", "views", "demixed", "object"):
        array, system, meta = read_tiff(tmp_path / f"{name}.tif")
        assert system == tiny_system and meta["kind"] == name and meta["seed"] == 0
    assert (tmp_path / "system.json").is_file()


def test_bad_input(simulator):
    with pytest.raises(ValueError, match="object must have shape"):
        simulator.simulate(np.zeros((5, 5)))
    with pytest.raises(ValueError, match="frames"):
        simulator.simulate(np.zeros((48, 48)), frames=0)
    bad = np.zeros((48, 48))
    bad[0, 0] = np.inf
    with pytest.raises(ValueError, match="NaN or Inf"):
        simulator.simulate(bad)
