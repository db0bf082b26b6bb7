"""Default tiling: the whole sub-view when it fits, else receptive-field overlap; seams."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from svcode_core import Reconstructor, SystemConfig
from svcode_core.methods.svcode import plan_tiles
from svcode_core.network import ModelConfig, SVCoDe
from svcode_core.phantoms import make_object
from svcode_core.physics.simulate import Simulator


@pytest.mark.parametrize("config", [ModelConfig.mini(), ModelConfig.reference(),
                                    ModelConfig.mini().replace(pixel_unshuffle=2, width=32)])
def test_plan_fits_the_budget_and_overlaps_by_the_receptive_radius(config):
    model = SVCoDe(config)
    per_pixel, step = model.working_bytes_per_pixel(), model.stride
    # generous budget: one tile, the whole sub-view, computed once
    assert plan_tiles(model, 384, 2**40) == (384, 384, 1)
    for budget in (2**26, 2**28, 2**30):
        tile, stride, batch = plan_tiles(model, 2400, budget)
        assert tile % step == 0 and batch * tile**2 * per_pixel <= budget
        assert (tile + step) ** 2 * per_pixel > budget  # the largest tile that fits
        overlap = tile - stride
        assert overlap == min(math.ceil(model.receptive_radius() / step) * step, tile // 2)


def test_reconstructor_uses_the_plan_and_keeps_explicit_settings():
    system = SystemConfig.preset("cm2-mini")
    model = SVCoDe(ModelConfig.mini())
    assert Reconstructor(model, system).grid.patch == system.sub_view_size
    rec = Reconstructor(model, system, tile_size=96, batch_size=3)
    assert (rec.grid.patch, rec.grid.stride, rec.batch_size) == (96, 48, 3)
    small = Reconstructor(model, system, tile_memory_bytes=2**26)
    assert small.grid.patch < system.sub_view_size


WHOLE_TILE_POOLING = pytest.mark.xfail(
    strict=True, reason="the bundled model's output depends on the tile's extent, not only "
    "at seams: its channel attention pools over the whole tile (trained on 96-px patches); "
    "192-px tiles agree with the whole sub-view to 32.5 dB; see its model card")


@pytest.mark.parametrize("pool_window", [pytest.param(None, marks=WHOLE_TILE_POOLING), 96])
def test_tiled_output_has_no_visible_seams(pool_window):
    """The bundled model on a simulated scene: 192-pixel tiles with the planned overlap
    agree with the whole-sub-view reconstruction to better than 40 dB (with its channel
    attention pooled over the training patch, ``pool_window=96``; not with the default)."""
    torch.set_num_threads(2)
    system = SystemConfig.preset("cm2-mini")
    scene = Simulator(system).simulate(make_object("cells", system.sub_view_size, 3), seed=4)
    whole = Reconstructor.pretrained(system, pool_window=pool_window)
    whole = whole.reconstruct(scene.measurement).reconstruction
    tiled = Reconstructor.pretrained(system, pool_window=pool_window, tile_size=192, stride=128)
    out = tiled.reconstruct(scene.measurement).reconstruction
    error = np.mean((out - whole) ** 2)
    assert 10 * np.log10(whole.max() ** 2 / error) > 40.0
