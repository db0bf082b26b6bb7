"""The contract of every registered method (methods.base): one test list over the registry.

For each name of :data:`svcode_core.methods.registry.METHODS`: a frame in gives an ``S × S``
finite float32 image out, a stack a stack; bad frames are refused with a
:class:`ValueError` before any result; the result records its time and tile counters; views
come with the methods that demix and are refused by those that do not; the picklable recipe
builds the same method.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from svcode_core.methods import registry
from svcode_core.methods.base import BaseReconstructor, FrameProgress
from svcode_core.methods.build import MethodSpec, build_reconstructor
from svcode_core.methods.learned import LEARNED_MODELS
from svcode_core.methods.model_file import save_model
from svcode_core.physics.cm2 import CM2Operator

#: small settings that keep every method fast on the tiny system
FAST = {"admm": {"iterations": 3, "rank": 1}, "wiener": {"rank": 1},
        "rl": {"iterations": 2, "rank": 1}}  # fmt: skip


@pytest.fixture(scope="module")
def weights(tiny_system, tiny_model_config, tmp_path_factory):
    """A model file of every trained method for the tiny system (random weights)."""
    from svcode_core.network import SVCoDe

    folder = tmp_path_factory.mktemp("contract")
    torch.manual_seed(0)
    files = {"svcode": save_model(folder / "svcode.safetensors", SVCoDe(tiny_model_config),
                                  tiny_system)}  # fmt: skip
    operator = CM2Operator.from_system(tiny_system)
    for name in registry.LEARNED_METHODS:
        cls = LEARNED_MODELS[registry.method(name).architecture]
        config = cls.config_class(width=4, enc_blocks=(1,), dec_blocks=(1,)).validate()
        model = cls.from_operator(operator, config)
        files[name] = save_model(folder / f"{name}.safetensors", model, tiny_system)
    return files


def _spec(name: str, system, weights) -> MethodSpec:
    path = str(weights[name]) if name in weights else None
    return MethodSpec(name, system, path, FAST.get(name, {}))


def _frames(system, count: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.uniform(0.0, 0.5, (count, *system.sensor_shape)).astype(np.float32)


@pytest.mark.parametrize("name", registry.METHODS)
def test_frames_in_a_result_out(name, tiny_system, weights, drain):
    spec = _spec(name, tiny_system, weights)
    reconstructor = pickle.loads(pickle.dumps(spec))()
    assert isinstance(reconstructor, BaseReconstructor) and reconstructor.method == name
    assert reconstructor.system == tiny_system
    default = registry.method(name).precisions[0]  # SV-CoDe's "auto" resolves to one
    assert reconstructor.precision == ("fp32" if default == "auto" else default)
    size = tiny_system.sub_view_size
    stack = _frames(tiny_system, 2)

    single = reconstructor.reconstruct(stack[0])
    assert single.reconstruction.shape == (size, size)
    assert single.reconstruction.dtype == np.float32
    assert np.isfinite(single.reconstruction).all() and single.views is None
    assert single.timings["total"] > 0
    assert single.tiles_total == single.tiles_run + single.tiles_skipped

    progress, result = drain(reconstructor.iter_reconstruct(stack))
    assert result.reconstruction.shape == (2, size, size)
    assert all(isinstance(p, FrameProgress) and p.frames == 2 for p in progress)
    assert {p.frame for p in progress} == {0, 1}
    np.testing.assert_allclose(result.reconstruction[0], single.reconstruction, atol=1e-5)
    assert spec.describe()["method"] == name


@pytest.mark.parametrize("name", registry.METHODS)
def test_views_where_the_method_demixes(name, tiny_system, weights):
    reconstructor = _spec(name, tiny_system, weights)()
    frame = _frames(tiny_system, 1)[0]
    size = tiny_system.sub_view_size
    if name in registry.LEARNED_METHODS:
        with pytest.raises(ValueError, match="no demixed views"):
            reconstructor.reconstruct(frame, return_views=True)
        return
    views = reconstructor.reconstruct(frame, return_views=True).views
    assert views.shape == (9, size, size) and np.isfinite(views).all()


@pytest.mark.parametrize("name", registry.METHODS)
def test_bad_frames_are_refused(name, tiny_system, weights):
    reconstructor = _spec(name, tiny_system, weights)()
    frame = _frames(tiny_system, 1)[0]
    nan = frame.copy()
    nan[2, 3] = np.nan
    bad = {
        "wrong size": frame[:-1],
        "padded size": np.zeros(tiny_system.padded_shape, np.float32),
        "NaN": nan,
        "empty stack": np.zeros((0, *frame.shape), np.float32),
        "4-D": frame[None, None],
        "booleans": frame > 0.2,
        "raw counts": frame * 4095,
    }
    for label, value in bad.items():
        with pytest.raises(ValueError):
            reconstructor.reconstruct(value)
            pytest.fail(f"{name}: {label} was accepted")


@pytest.mark.parametrize("name", registry.METHODS)
def test_precisions_are_those_of_the_registry(name, tiny_system, weights):
    refused = sorted({"fp32", "fp64", "bf16", "fp16"} - set(registry.method(name).precisions))
    for precision in refused:
        with pytest.raises(ValueError, match="precision"):
            build_reconstructor(name, tiny_system, weights.get(name),
                                precision=precision, **FAST.get(name, {}))  # fmt: skip
