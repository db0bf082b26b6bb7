"""napari plugin: manifest, reader, writer and sample data (needs an X server: xvfb-run)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import tifffile

pytest.importorskip("napari")

from napari.layers import Layer  # noqa: E402

from napari_svcode._layers import KIND_KEY, MODEL_KEY, SYSTEM_KEY, object_translate  # noqa: E402
from napari_svcode._reader import get_reader  # noqa: E402
from napari_svcode._sample_data import sample_layers  # noqa: E402
from svcode_core.io import read_tiff, write_tiff  # noqa: E402

pytestmark = pytest.mark.gui

PLUGIN = "napari-svcode"


def test_manifest_of_installed_package_validates():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution(PLUGIN)
    contributions = manifest.contributions
    assert [w.display_name for w in contributions.widgets] == [
        "Calibration", "Reconstruct", "Coordinate masks", "Simulate"]
    assert {s.key for s in contributions.sample_data} == {"beads", "cells", "vessels"}
    for command in contributions.commands:  # every python_name imports
        module, _, attr = command.python_name.partition(":")
        assert hasattr(__import__(module, fromlist=[attr]), attr), command.python_name
    run = subprocess.run([sys.executable, "-m", "npe2", "validate", PLUGIN],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "valid" in run.stdout


def test_reader_gets_system_from_metadata_or_system_json(tmp_path, tiny_system, make_napari_viewer):
    stack = np.random.default_rng(0).random((3, *tiny_system.sensor_shape), dtype=np.float32)
    tagged = write_tiff(tmp_path / "tagged" / "raw.tif", stack, tiny_system, kind="measurement")
    plain = tmp_path / "plain" / "raw.ome.tif"
    plain.parent.mkdir()
    tifffile.imwrite(plain, stack[0], ome=True)
    tiny_system.save(plain.with_name("system.json"))

    assert get_reader(str(tmp_path / "x.png")) is None
    for path, shape in ((tagged, stack.shape), (plain, stack.shape[1:])):
        [(data, kwargs, kind)] = get_reader(str(path))(str(path))
        assert kind == "image" and data.shape == shape
        assert kwargs["metadata"][SYSTEM_KEY] == tiny_system

    viewer = make_napari_viewer()
    [layer] = viewer.open(str(tagged), plugin=PLUGIN)
    np.testing.assert_array_equal(layer.data, stack)
    assert layer.metadata[SYSTEM_KEY] == tiny_system
    assert layer.metadata[KIND_KEY] == "measurement"


def test_writer_round_trip_records_system_and_model(tmp_path, tiny_system, make_napari_viewer):
    viewer = make_napari_viewer()
    recon = np.random.default_rng(1).random((tiny_system.sub_view_size,) * 2, dtype=np.float32)
    model = {"path": "model.safetensors", "architecture": "SVCoDe"}
    layer = viewer.add_image(recon, name="reconstruction", translate=object_translate(tiny_system),
                             metadata={SYSTEM_KEY: tiny_system, KIND_KEY: "reconstruction",
                                       MODEL_KEY: model})
    path = tmp_path / "recon.tif"
    written = layer.save(str(path), plugin=PLUGIN)
    assert written == [str(path)]
    array, system, meta = read_tiff(path)
    np.testing.assert_array_equal(array, recon)
    assert system == tiny_system
    assert meta["kind"] == "reconstruction" and meta["model"] == model

    [reopened] = viewer.open(str(path), plugin=PLUGIN)  # back on the object grid
    assert tuple(reopened.translate) == object_translate(tiny_system)
    assert reopened.metadata[MODEL_KEY] == model


def test_sample_layers_load_with_ground_truth(tiny_system, make_napari_viewer):
    viewer = make_napari_viewer()
    layers = sample_layers("cells", tiny_system)
    assert sample_layers("cells", tiny_system)[0][0] is layers[0][0]  # cached in memory
    for data, kwargs, kind in layers:
        viewer.add_layer(Layer.create(data, kwargs, kind))
    truth, raw = viewer.layers["cells ground truth"], viewer.layers["cells raw"]
    assert raw.data.shape == tiny_system.sensor_shape and raw.data.max() > 0
    assert truth.data.shape == (tiny_system.sub_view_size,) * 2
    assert truth.metadata[SYSTEM_KEY] == raw.metadata[SYSTEM_KEY] == tiny_system
    assert tuple(truth.translate) == object_translate(tiny_system)
    with pytest.raises(ValueError, match="unknown sample"):
        sample_layers("galaxies", tiny_system)
