"""svcode_core.methods: one entry point for every reconstruction method."""

from __future__ import annotations

import inspect
import shlex

import numpy as np
import pytest

from svcode_core.cli import build_parser
from svcode_core.cli.reconstruct import METHODS as CLI_METHODS
from svcode_core.methods import (
    METHODS,
    build_reconstructor,
    cli_arguments,
    iter_method,
    reconstruct_with_method,
    reconstructor_defaults,
)
from svcode_core.methods.base import FrameProgress
from svcode_core.methods.baselines import BaselineReconstructor, reconstruct_with_baseline
from svcode_core.methods.svcode import Reconstructor
from svcode_core.methods.tiling import exhaust
from svcode_core.network import SVCoDe


def _frames(system, count: int) -> np.ndarray:
    return np.random.default_rng(0).random((count, *system.sensor_shape), dtype=np.float32)


def test_the_methods_are_those_of_the_cli():
    assert METHODS == CLI_METHODS


def test_defaults_are_read_from_the_reconstructor():
    parameters = inspect.signature(Reconstructor.__init__).parameters
    defaults = reconstructor_defaults()
    for name in ("tile_size", "stride", "batch_size", "skip_empty", "mask_cache_bytes"):
        assert defaults[name] == parameters[name].default


def test_a_named_baseline_matches_its_reconstructor(tiny_system):
    frame = _frames(tiny_system, 1)[0]
    result = reconstruct_with_method("wiener", frame, tiny_system, balance=0.05)
    expected = reconstruct_with_baseline("wiener", frame, tiny_system, balance=0.05)
    np.testing.assert_array_equal(result.reconstruction, expected)
    assert isinstance(build_reconstructor("rl", tiny_system, iterations=3),
                      BaselineReconstructor)


def test_iter_method_yields_progress_for_any_method(tiny_system, tiny_model_config, drain):
    stack = _frames(tiny_system, 2)
    rl = build_reconstructor("rl", tiny_system, iterations=2)
    progress, result = drain(iter_method(rl, stack, return_views=True))
    # RL reports before each frame and after each of its iterations
    assert progress == [FrameProgress(f, 2, i, 2) for f in (0, 1) for i in (0, 1, 2)]
    expected = rl.reconstruct(stack, return_views=True)
    np.testing.assert_allclose(result.reconstruction, expected.reconstruction, atol=1e-6)
    assert result.views.shape == expected.views.shape

    model = SVCoDe(tiny_model_config)
    svcode = build_reconstructor("svcode", tiny_system, model=model, batch_size=4)
    single = exhaust(iter_method(svcode, stack[0]))
    np.testing.assert_allclose(single.reconstruction, svcode.reconstruct(stack[0]).reconstruction)


def test_unknown_methods_and_missing_weights_are_refused(tiny_system):
    with pytest.raises(ValueError, match="not one of"):
        build_reconstructor("deconvolve", tiny_system)
    with pytest.raises(ValueError, match="needs a trained model file"):
        build_reconstructor("fouriernet", tiny_system)
    with pytest.raises(ValueError, match="no `svcode reconstruct` flag"):
        cli_arguments("svcode", skip_factor=2.0)


@pytest.mark.parametrize(("method", "options", "expected"), [
    ("svcode", {"tile_size": 64, "batch_size": 4, "skip_empty": False, "refine_periphery": 10},
     {"tile": 64, "batch_size": 4, "no_skip": True, "refine_periphery": 10}),
    ("admm", {"iterations": 50, "tv_weight": 1e-3, "rank": 3},
     {"iterations": 50, "tv_weight": 1e-3, "rank": 3}),
    ("wiener", {"balance": 0.02, "boundary": "periodic", "precision": "fp64"},
     {"wiener_balance": 0.02, "wiener_boundary": "periodic", "precision": "fp64"}),
    ("fouriernet", {"precision": "bf16"}, {"weights": "model.safetensors", "precision": "bf16"}),
])
def test_cli_arguments_parse_back(method, options, expected):
    weights = "model.safetensors" if method == "fouriernet" else None
    arguments = cli_arguments(method, weights, **options)
    args = build_parser().parse_args(["reconstruct", "in.tif", "--out", "out.tif", *arguments])
    assert args.method == method
    for name, value in expected.items():
        assert str(getattr(args, name)) == str(value), shlex.join(arguments)
