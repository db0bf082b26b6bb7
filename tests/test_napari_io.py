"""napari plugin: manifest, reader, writer and sample data (needs an X server: xvfb-run)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import tifffile

pytest.importorskip("napari")

from napari.layers import Layer  # noqa: E402

from napari_svcode._layers import (  # noqa: E402
    AXIS_LABELS,
    KIND_KEY,
    MODEL_KEY,
    SYSTEM_KEY,
    object_translate,
)
from napari_svcode._reader import get_reader, read_cm2_tiff  # noqa: E402
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
    assert {s.key for s in contributions.sample_data} == {"beads", "cells", "vessels",
                                                          "paper-cells"}
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

    assert meta["pixel_size_um"] == tiny_system.object_pixel_um  # the resolution tags

    [reopened] = viewer.open(str(path), plugin=PLUGIN)  # back on the object grid, in µm
    assert tuple(reopened.scale) == (10, 10)
    assert tuple(reopened.translate) == tuple(10 * t for t in object_translate(tiny_system))
    assert reopened.metadata[MODEL_KEY] == model


def test_the_paper_scale_sample_is_a_cm2_v2_frame_and_says_its_cost(monkeypatch):
    import napari_svcode._sample_data as samples

    asked = []
    monkeypatch.setattr(samples, "sample_layers", lambda kind, system: asked.append(
        (kind, system.name, system.sensor_shape)))  # a real one takes a minute
    samples.make_paper_cells_sample()
    assert asked == [("cells", "cm2-v2", (3000, 4000))]
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution(PLUGIN)
    [sample] = [s for s in manifest.contributions.sample_data if s.key == "paper-cells"]
    assert "cm2-v2" in sample.display_name and "minute" in sample.display_name


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
    # both in object-space µm: the truth sits over the raw frame where lens 4 images it
    assert tuple(truth.scale) == tuple(raw.scale) == (10, 10)
    assert tuple(truth.translate) == tuple(10 * t for t in object_translate(tiny_system))
    assert [str(unit) for unit in truth.units] == ["micrometer"] * 2
    with pytest.raises(ValueError, match="unknown sample"):
        sample_layers("galaxies", tiny_system)


def test_reader_places_layers_in_micrometres_with_a_scale_bar(tmp_path, tiny_system,
                                                              make_napari_viewer):
    """A raw stack and its reconstruction overlay in object-space µm (the system's 10 µm
    pixels); a foreign TIFF gets its own resolution; without any size, pixels."""
    size = tiny_system.sub_view_size
    write_tiff(tmp_path / "raw.tif", np.zeros((2, *tiny_system.sensor_shape)), tiny_system,
               kind="measurement")
    write_tiff(tmp_path / "rec.tif", np.zeros((size, size)), tiny_system, kind="reconstruction")
    tifffile.imwrite(tmp_path / "fiji.tif", np.zeros((4, 4), np.uint16), imagej=True,
                     resolution=(1 / 0.5, 1 / 0.5), metadata={"unit": "um"})
    tifffile.imwrite(tmp_path / "bare.tif", np.zeros((4, 4), np.uint16))
    viewer = make_napari_viewer()
    [raw] = viewer.open(str(tmp_path / "raw.tif"), plugin=PLUGIN)
    assert viewer.canvas.overlays.scale_bar.visible
    [rec] = viewer.open(str(tmp_path / "rec.tif"), plugin=PLUGIN)
    assert tuple(raw.scale) == (1, 10, 10) and tuple(raw.translate) == (0, 0, 0)
    assert [str(unit) for unit in raw.units] == ["pixel", "micrometer", "micrometer"]
    origin = np.asarray(object_translate(tiny_system))
    # object pixel (i, j) lies on sensor pixel origin + (i, j), in µm in the viewer
    np.testing.assert_allclose(rec.data_to_world((3, 4)), 10 * (origin + (3, 4)))
    np.testing.assert_allclose(raw.world_to_data((0, *rec.data_to_world((3, 4))))[1:],
                               origin + (3, 4))
    [fiji] = viewer.open(str(tmp_path / "fiji.tif"), plugin=PLUGIN)
    assert tuple(fiji.scale) == (0.5, 0.5) and str(fiji.units[-1]) == "micrometer"
    [(_, kwargs, _)] = get_reader(str(tmp_path / "bare.tif"))(str(tmp_path / "bare.tif"))
    assert kwargs["scale"] == (1.0, 1.0) and "units" not in kwargs


def test_placement_without_layer_units(monkeypatch, tiny_system):
    """napari before 0.6 has no layer units: scale and translation only."""
    import napari_svcode._layers as layers

    monkeypatch.setattr(layers, "LAYER_UNITS", False)
    place = layers.placement(tiny_system, 3)
    assert place == {"scale": (1.0, 10.0, 10.0), "translate": (0.0, 0.0, 0.0)}
    assert layers.in_micrometres(place)


def test_writer_takes_the_pixel_size_from_a_layer_in_micrometres(tmp_path, make_napari_viewer):
    viewer = make_napari_viewer()
    layer = viewer.add_image(np.zeros((5, 6), np.float32), name="plain", scale=(2.5, 2.5),
                             units="µm")
    layer.save(str(tmp_path / "plain.tif"), plugin=PLUGIN)
    _, system, meta = read_tiff(tmp_path / "plain.tif")
    assert system is None and meta["pixel_size_um"] == 2.5


def test_sample_truth_and_frame_share_a_scene_and_the_writer_keeps_the_frames(
        tmp_path, tiny_system, make_napari_viewer):
    (truth, truth_kwargs, _), (_, raw_kwargs, _) = sample_layers("beads", tiny_system)
    scene = raw_kwargs["metadata"]["svcode_scene"]
    assert scene and truth_kwargs["metadata"]["svcode_scene"] == scene
    assert sample_layers("cells", tiny_system)[1][1]["metadata"]["svcode_scene"] != scene

    viewer = make_napari_viewer()
    size = tiny_system.sub_view_size
    frames = {"first": 3, "stop": 5, "total": 8}  # a cancelled run kept frames 3 and 4
    layer = viewer.add_image(np.zeros((2, size, size), np.float32), name="reconstruction",
                             metadata={SYSTEM_KEY: tiny_system, KIND_KEY: "reconstruction",
                                       "svcode_frames": frames})
    path = tmp_path / "partial.tif"
    layer.save(str(path), plugin=PLUGIN)
    assert read_tiff(path)[2]["frames"] == frames
    [(_, reopened, _)] = read_cm2_tiff(str(path))  # and back into the layer on reopening
    assert reopened["metadata"]["svcode_frames"] == frames
    # at the raw frames it holds, on an axis named frame
    assert reopened["translate"][0] == 3
    if AXIS_LABELS:
        assert tuple(reopened["axis_labels"]) == ("frame", "y", "x")
        for shape, lead in (((9, size, size), ("lens",)), ((9, 2, size, size), ("lens", "frame")),
                            ((size, size), ())):
            views = tmp_path / f"views{len(shape)}.tif"
            write_tiff(views, np.zeros(shape, np.float32), tiny_system, kind="demixed")
            [(_, kwargs, _)] = read_cm2_tiff(str(views))
            assert tuple(kwargs["axis_labels"]) == (*lead, "y", "x")
