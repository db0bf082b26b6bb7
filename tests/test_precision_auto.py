"""``precision="auto"``: bf16 only where the hardware has it and the model file's own check
allows it; the check is written into a model file without touching its weights."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
import torch
from safetensors.torch import load_file

from svcode_core.io import read_tiff
from svcode_core.methods import svcode as svcode_module
from svcode_core.methods.model_file import load_model, read_model_metadata, record_extra, save_model
from svcode_core.methods.svcode import AUTO_TOLERANCE_DB, Reconstructor, auto_precision
from svcode_core.network import SVCoDe
from svcode_core.pretrained import require_bundled_weights

WITHIN = {"bf16": {"loss_db": AUTO_TOLERANCE_DB}}
BEYOND = {"bf16": {"loss_db": AUTO_TOLERANCE_DB + 0.01}}


@pytest.fixture
def bf16_units(monkeypatch):
    """Pretend the device has (True) or lacks (False) bf16 units."""

    def pretend(native: bool) -> None:
        monkeypatch.setattr(svcode_module, "native_bf16", lambda device: native)

    return pretend


@pytest.mark.parametrize(("checks", "native", "chosen"), [
    ({}, True, "fp32"),  # nothing recorded: never bf16
    (BEYOND, True, "fp32"),  # recorded, but bf16 costs more than the tolerance
    (WITHIN, False, "fp32"),  # allowed, but bf16 would be emulated (slower)
    (WITHIN, True, "bf16"),
])  # fmt: skip
def test_auto_chooses_bf16_only_when_checked_and_native(bf16_units, checks, native, chosen):
    bf16_units(native)
    assert auto_precision(checks, "cpu") == chosen


def test_record_extra_keeps_the_weights_and_load_model_reads_the_check(
    tmp_path, tiny_system, tiny_model_config
):
    path = save_model(tmp_path / "m.safetensors", SVCoDe(tiny_model_config), tiny_system,
                      extra={"epochs": 3})
    before = load_file(str(path))
    record_extra(path, precision_check=WITHIN)
    after = load_file(str(path))
    assert before.keys() == after.keys()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert read_model_metadata(path)["extra"] == {"epochs": 3, "precision_check": WITHIN}
    assert load_model(path)[0].precision_check == WITHIN
    assert not list(tmp_path.glob("*.partial"))


def test_reconstructor_and_tile_plan_resolve_auto(bf16_units, tmp_path, tiny_system,
                                                  tiny_model_config):
    path = save_model(tmp_path / "m.safetensors", SVCoDe(tiny_model_config), tiny_system)
    record_extra(path, precision_check=WITHIN)
    bf16_units(True)
    assert Reconstructor.from_weights(path).precision == "bf16"
    assert Reconstructor.from_weights(path, precision="fp32").precision == "fp32"
    bf16_units(False)
    assert Reconstructor.from_weights(path).precision == "fp32"
    assert Reconstructor(SVCoDe(tiny_model_config), tiny_system).precision == "fp32"


def test_the_command_records_the_precision_it_chose(bf16_units, tmp_path, tiny_system,
                                                    tiny_model_config, capsys):
    from svcode_core.cli import main

    path = save_model(tmp_path / "m.safetensors", SVCoDe(tiny_model_config), tiny_system)
    record_extra(path, precision_check=WITHIN)
    frame, system = tmp_path / "frame.tif", tmp_path / "system.json"
    tifffile.imwrite(frame, np.full(tiny_system.sensor_shape, 0.2, np.float32))
    system.write_text(tiny_system.to_json())
    common = ["reconstruct", str(frame), "--weights", str(path), "--system", str(system),
              "--no-progress"]
    bf16_units(True)
    assert main([*common, "--out", str(tmp_path / "rec.tif")]) == 0
    assert "(bf16)" in capsys.readouterr().out
    assert read_tiff(tmp_path / "rec.tif")[2]["precision"] == "bf16"  # what ran, not "auto"
    assert main([*common, "--out", str(tmp_path / "rec32.tif"), "--precision", "fp32"]) == 0
    assert "(fp32)" in capsys.readouterr().out


@pytest.mark.parametrize("system", ["cm2-mini", "cm2-v2"])
def test_the_bundled_models_record_bf16_within_the_tolerance(system):
    check = read_model_metadata(require_bundled_weights(system))["extra"]["precision_check"]
    assert check["bf16"]["loss_db"] <= AUTO_TOLERANCE_DB
    assert set(check["bf16"]["regimes"]) >= {"matched", "realistic"}


def test_bf16_on_the_cpu_computes_the_features_in_bf16_and_leaves_the_model(
    tiny_system, tiny_model_config
):
    """A bf16 reconstructor runs a bf16 copy of the network (coordinate MLPs in float32):
    the given model keeps its float32 weights, and the output is float32's to bf16's
    rounding (8 significant bits: 2⁻⁸ of the output's scale for its last rounding, a few
    of them through this one-level network)."""
    torch.manual_seed(0)
    model = SVCoDe(tiny_model_config.replace(mask_spacing=8))
    with torch.no_grad():
        for name, param in model.named_parameters():
            if name.endswith(("beta", "gamma")):
                param.uniform_(-0.5, 0.5)  # blocks that are not the identity
    frame = np.random.default_rng(0).uniform(0, 0.5, tiny_system.sensor_shape).astype(np.float32)
    fp32 = Reconstructor(model, tiny_system, precision="fp32", skip_empty=False)(frame)
    rec = Reconstructor(model, tiny_system, precision="bf16", skip_empty=False)
    assert {p.dtype for p in model.parameters()} == {torch.float32}
    assert rec.model is not model
    gates = {id(p) for _, g in rec.model._gates.values() for p in g.mlp.parameters()}
    assert all((p.dtype == torch.float32) == (id(p) in gates) for p in rec.model.parameters())
    bf16 = rec(frame).reconstruction
    assert bf16.dtype == np.float32
    scale = float(np.abs(fp32.reconstruction).max())
    np.testing.assert_allclose(bf16, fp32.reconstruction, atol=4 * 2.0**-8 * scale)
