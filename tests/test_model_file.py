"""Safe model files: round trip, refusal of pickles, truncation, shapes and other systems."""

from __future__ import annotations

import json
import pickle

import pytest
import torch
from safetensors.torch import save_file

from svcode_core.config import ConfigError, SystemConfig
from svcode_core.methods.model_file import (
    load_model,
    read_model_metadata,
    record_pool_window,
    save_model,
)
from svcode_core.network import ModelConfig, ReconNet, SVCoDe

TINY = ModelConfig(
    width=4,
    view_width=2,
    demix_enc_blocks=(1,),
    demix_dec_blocks=(1,),
    recon_enc_blocks=(1,),
    recon_dec_blocks=(1,),
    mlp_hidden=8,
)


@pytest.fixture
def saved(tmp_path, tiny_system):
    torch.manual_seed(0)
    model = SVCoDe(TINY)
    path = save_model(tmp_path / "model.safetensors", model, tiny_system, extra={"epochs": 3})
    return path, model, tiny_system


def test_round_trip_is_bit_for_bit(saved):
    path, model, system = saved
    loaded, stored = load_model(path, system)
    assert stored == system and not loaded.training
    assert loaded.model_config == TINY
    reference = model.state_dict()
    for key, value in loaded.state_dict().items():
        assert torch.equal(value, reference[key]), key
    views = torch.rand(1, 9, 8, 8)
    with torch.no_grad():
        assert torch.equal(loaded(views, [[0, 0]], 48)[1], model.eval()(views, [[0, 0]], 48)[1])
    assert read_model_metadata(path)["extra"] == {"epochs": 3}


def test_stage_models_round_trip(tmp_path, tiny_system):
    model = ReconNet(TINY)
    loaded, _ = load_model(save_model(tmp_path / "recon.safetensors", model, tiny_system))
    assert isinstance(loaded, ReconNet)


def test_a_recorded_pool_window_is_loaded_and_the_weights_kept(saved):
    path, model, system = saved
    record_pool_window(path, 32)
    loaded, _ = load_model(path, system)
    assert loaded.model_config == TINY.replace(pool_window=32)
    assert all(stage.config.pool_window == 32 for stage in (loaded.demix, loaded.recon))
    reference = model.state_dict()
    assert all(torch.equal(v, reference[k]) for k, v in loaded.state_dict().items())
    assert read_model_metadata(path)["extra"] == {"epochs": 3}
    with pytest.raises(ConfigError, match="pool_window"):
        record_pool_window(path, -1)
    assert read_model_metadata(path)["model_config"].pool_window == 32


def test_pickles_are_refused(tmp_path, saved):
    _, model, _ = saved
    zipped = tmp_path / "model.pt"
    torch.save(model.state_dict(), zipped)
    with pytest.raises(ValueError, match="zip archive"):
        load_model(zipped)
    raw = tmp_path / "model.pkl"
    raw.write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    with pytest.raises(ValueError, match="pickle"):
        load_model(raw)


def test_truncated_file_is_refused(tmp_path, saved):
    path = saved[0]
    data = path.read_bytes()
    for cut, message in ((len(data) - 10, "truncated"), (100, "truncated"), (5, "truncated")):
        short = tmp_path / f"short{cut}.safetensors"
        short.write_bytes(data[:cut])
        with pytest.raises(ValueError, match=message):
            load_model(short)


def test_other_system_is_refused(saved):
    path, _, system = saved
    other = system.replace(name="other", patch_size=24, patch_stride=12)
    with pytest.raises(ValueError, match="patch_size.*patch_stride|patch_stride.*patch_size"):
        load_model(path, other)
    with pytest.raises(ValueError, match="optics.kernel_size"):
        load_model(path, SystemConfig.preset("cm2-mini"))


def test_a_calibrated_system_keeps_the_model(saved, tmp_path):
    """Moved chief rays and a measured forward model (PSF stack, rank) are not inputs of
    the network: the model loads for such a system."""
    path, _, system = saved
    rays = tuple((r + 1, c - 1) for r, c in system.chief_rays)
    calibrated = system.replace(chief_rays=rays, psf_model=str(tmp_path / "psfs.tif"),
                                rank=None, rank_tolerance=0.01)
    _, stored = load_model(path, calibrated)
    assert stored == system


def test_shape_mismatch_is_refused(tmp_path, saved):
    path, model, system = saved
    wider = TINY.replace(width=6)
    metadata = {
        "format": "svcode-model-1",
        "architecture": "SVCoDe",
        "model_config": wider.to_json(),
        "system_config": system.to_json(),
        "extra": json.dumps({}),
    }
    forged = tmp_path / "forged.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(forged), metadata)
    with pytest.raises(ValueError, match="do not fit.*file"):
        load_model(forged)


def test_plain_safetensors_is_not_a_model(tmp_path):
    path = tmp_path / "plain.safetensors"
    save_file({"x": torch.zeros(3)}, str(path))
    with pytest.raises(ValueError, match="not an SV-CoDe model"):
        load_model(path)
