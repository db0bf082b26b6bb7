"""Default tiling: the whole sub-view when it fits, else receptive-field overlap; seams."""

from __future__ import annotations

import math
from pathlib import Path

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
    # a given tile without a batch: as many as fit the budget, at most 8, at least one
    assert Reconstructor(model, system, tile_size=96).batch_size == 8
    per_tile = 96**2 * model.working_bytes_per_pixel()
    assert Reconstructor(model, system, tile_size=96,
                         tile_memory_bytes=3 * per_tile).batch_size == 3  # fmt: skip
    assert Reconstructor(model, system, tile_size=192, tile_memory_bytes=2**20).batch_size == 1


def test_a_measured_overlap_replaces_the_receptive_radius(tiny_system, tiny_model_config,
                                                         tmp_path):
    """The overlap ``bench/tile_overlap.py --record`` writes into a model file is the one
    its planned tiles use; a file without one overlaps by the receptive radius."""
    import sys

    from svcode_core.methods.model_file import load_model, record_extra, save_model

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from tile_overlap import overlap_check

    path = save_model(tmp_path / "m.safetensors", SVCoDe(tiny_model_config), tiny_system)
    model, _ = load_model(path)
    assert model.overlap_check == {}
    tile, stride, _ = plan_tiles(model, 240, model.working_bytes_per_pixel() * 64**2)
    assert tile - stride == min(math.ceil(model.receptive_radius() / model.stride)
                                * model.stride, tile // 2)  # fmt: skip
    rows = [{"regime": r, "overlap": o, "psnr": p, "per_scene": {"a": {}}}
            for r, o, p in [("m", 30, 20.0), ("m", 16, 19.96), ("m", 8, 19.9),
                            ("x", 30, 10.0), ("x", 16, 10.1), ("x", 8, 10.2)]]  # fmt: skip
    check = overlap_check(rows, radius=30, tile=64)
    assert check["overlap"] == 16  # 8 loses 0.1 dB in regime m
    record_extra(path, overlap_check=check)
    model, _ = load_model(path)
    measured = plan_tiles(model, 240, model.working_bytes_per_pixel() * 64**2)
    assert measured[0] == tile and measured[0] - measured[1] == 16
    rec = Reconstructor.from_weights(path, tiny_system, tile_memory_bytes=
                                     model.working_bytes_per_pixel() * 32**2)  # fmt: skip
    assert rec.grid.patch - rec.grid.stride == min(16, rec.grid.patch // 2)


WHOLE_TILE_POOLING = pytest.mark.xfail(
    strict=True, reason="the bundled model's output depends on the tile's extent, not only "
    "at seams: its channel attention pools over the whole tile (trained on 96-px patches); "
    "192-px tiles agree with the whole sub-view to 33.4 dB; see its model card")


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
