"""Training data with per-frame departures (domain randomisation): draws, contents, resume."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from svcode_core.physics.departures import Departures
from svcode_core.physics.simulate import Simulator
from svcode_core.training import dataset as dataset_module
from svcode_core.training.dataset import (
    DataRecipe,
    TrainingData,
    frame_departures,
    generate_dataset,
)


def recipe(tiny_system) -> DataRecipe:
    ranges = Departures.named("realistic", tiny_system)  # lighter truth model: a fast test
    ranges = dataclasses.replace(ranges, truth_psf_grid=None, depth_spread_waves=0.1)
    return DataRecipe(frames=4, seed=2, val_fraction=0.25, object_kind="beads",
                      departures=ranges, instrument_frames=2)


def test_frames_draw_their_own_instrument(tiny_system):
    plan = recipe(tiny_system)
    draws = [frame_departures(plan, i) for i in range(4)]
    assert draws[1] == frame_departures(plan, 1)  # depends only on (seed, index)
    assert draws[0].optical_key() == draws[1].optical_key()  # one optical draw per block
    assert draws[1].optical_key() != draws[2].optical_key()
    assert draws[0].photons != draws[1].photons  # the camera is drawn per frame
    assert frame_departures(DataRecipe(frames=4), 0) is None
    assert DataRecipe.from_dict(plan.to_dict()) == plan
    assert "departures" not in DataRecipe(frames=4).to_dict()  # old manifests still match


def test_dataset_with_departures_resumes_to_the_same_data(tiny_system, tmp_path, monkeypatch):
    plan = recipe(tiny_system)
    whole = generate_dataset(tmp_path / "whole", tiny_system, plan, progress=False)
    # frame 3 is its own draw of the instrument: simulate it directly and compare
    departures = whole.frame_departures(3)
    scene = Simulator(tiny_system, departures=departures).simulate(
        np.array(whole.objects[3]), noise=False)
    np.testing.assert_allclose(whole.views[3], scene.views, atol=1e-6)
    np.testing.assert_allclose(whole.demixed[3], scene.demixed, atol=1e-6)
    nominal = Simulator(tiny_system).simulate(np.array(whole.objects[3]), noise=False)
    assert not np.allclose(whole.views[3], nominal.views, atol=1e-3)
    sensor = whole.frame_sensor(3)
    assert sensor.noise.photons == departures.photons and sensor.adc_bits == 12
    assert sensor.gain is None and sensor.offset is None  # already in the stored views
    patch = torch.as_tensor(np.array(whole.views[3, 4, :8, :8]))
    assert sensor.read(patch, torch.Generator().manual_seed(0)).shape == (8, 8)
    manifest = json.loads((whole.path / "manifest.json").read_text())
    assert manifest["recipe"]["departures"]["name"] == "realistic"

    original, calls = dataset_module.training_object, {"n": 0}

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(dataset_module, "training_object", failing)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(tmp_path / "resumed", tiny_system, plan, progress=False)
    monkeypatch.setattr(dataset_module, "training_object", original)
    resumed = generate_dataset(tmp_path / "resumed", tiny_system, plan, progress=False)
    for name in ("views", "demixed", "objects"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name))
    assert TrainingData(tmp_path / "resumed").frame_departures(2) == whole.frame_departures(2)


def test_several_processes_write_the_same_data(tiny_system, tmp_path):
    """workers=2: blocks of instrument draws in two processes, out of order, resumed from
    the middle of a block; every stored array equals one process's."""
    plan = dataclasses.replace(recipe(tiny_system), frames=5, view_margin=2)
    serial = generate_dataset(tmp_path / "serial", tiny_system, plan, progress=False)
    partial = tmp_path / "parallel"
    generate_dataset(partial, tiny_system, plan, progress=False)
    manifest = json.loads((partial / "manifest.json").read_text())
    manifest["count"] = 1  # as if interrupted after frame 0: frames 1-4 are written again
    (partial / "manifest.json").write_text(json.dumps(manifest))
    for name in ("views", "demixed", "objects"):
        stored = np.lib.format.open_memmap(partial / f"{name}.npy", mode="r+")
        stored[1:] = np.nan
        stored.flush()
    parallel = generate_dataset(partial, tiny_system, plan, progress=False, workers=2)
    assert json.loads((partial / "manifest.json").read_text())["count"] == 5
    for name in ("views", "demixed", "objects"):
        np.testing.assert_array_equal(getattr(parallel, name), getattr(serial, name))
    with pytest.raises(ValueError, match="workers"):
        generate_dataset(tmp_path / "x", tiny_system, plan, Simulator(tiny_system), workers=2)


def test_cli_dataset_departures(tiny_system, tmp_path, capsys):
    from svcode_core.cli import main

    system_json = tiny_system.save(tmp_path / "tiny.json")
    out = tmp_path / "data"
    assert main(["dataset", "--system", str(system_json), "--frames", "2", "--departures",
                 "calibration", "--out", str(out), "--no-progress"]) == 0
    assert "s per frame" in capsys.readouterr().out
    data = TrainingData(out)
    assert data.frame_departures(0).name == "calibration, frame 0"
    assert main(["dataset", "--system", str(system_json), "--frames", "2", "--departures",
                 "dawn", "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "neither a named set" in capsys.readouterr().err
