"""napari plugin widgets end to end, and the README screenshot (needs an X server: xvfb-run)."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

pytest.importorskip("napari")

import napari_svcode._errors as plugin_errors  # noqa: E402
from napari_svcode._layers import (  # noqa: E402
    LAYER_UNITS,
    SYSTEM_KEY,
    layer_metadata,
    object_translate,
)
from napari_svcode.widgets import (  # noqa: E402
    CalibrationWidget,
    MaskWidget,
    ReconstructWidget,
    SimulateWidget,
    reconstruct_frames,
)
from napari_svcode.widgets.reconstruct import STEPS  # noqa: E402
from svcode_core.config import SystemConfig  # noqa: E402
from svcode_core.methods.base import FrameProgress  # noqa: E402
from svcode_core.methods.model_file import save_model
from svcode_core.methods.svcode import Reconstructor  # noqa: E402
from svcode_core.network import SVCoDe  # noqa: E402

pytestmark = pytest.mark.gui

IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"
COMPARE_ADMM_ITERATIONS = 10
@pytest.fixture
def model_file(tiny_weights) -> Path:
    return tiny_weights


@pytest.fixture
def make_model_file(tiny_model_config):
    """Save the conftest's tiny SV-CoDe (seed 0) for a system: ``make(path, system)``."""
    def make(path: Path, system: SystemConfig) -> Path:
        torch.manual_seed(0)
        return save_model(path, SVCoDe(tiny_model_config), system)

    return make


@pytest.fixture
def errors(monkeypatch) -> list[str]:
    """Messages of the plugin's error notifications."""
    shown: list[str] = []
    monkeypatch.setattr(plugin_errors, "show_error", shown.append)
    return shown


@pytest.fixture
def warnings(monkeypatch) -> list[str]:
    """Messages of the plugin's warning notifications."""
    shown: list[str] = []
    monkeypatch.setattr(plugin_errors, "show_warning", shown.append)
    return shown


def _raw_stack(system: SystemConfig, frames: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.random((frames, *system.sensor_shape), dtype=np.float32)


def _dock(viewer, widget_class):
    widget = widget_class(viewer)
    viewer.window.add_dock_widget(widget, name=widget_class.__name__.removesuffix("Widget"))
    return widget


def _stack_in_widget(viewer, system: SystemConfig, model_file: Path, frames: int,
                     current: int = 0) -> tuple[np.ndarray, ReconstructWidget]:
    """A random raw stack as layer "raw" at frame ``current``, and a Reconstruct widget
    set to the model file."""
    stack = _raw_stack(system, frames)
    viewer.add_image(stack, name="raw", metadata=layer_metadata(system, "measurement"))
    viewer.dims.set_current_step(0, current)
    widget = _dock(viewer, ReconstructWidget)
    _use_model(widget, model_file)
    return stack, widget


class _SlowModel(torch.nn.Module):
    """A model that counts its calls and sleeps before each, so a cancel lands mid-run."""

    def __init__(self, inner: torch.nn.Module, seconds: float) -> None:
        super().__init__()
        self.inner, self.seconds, self.calls = inner, seconds, 0
        self.hook = None  # called with the call count after each call, in the worker

    def __getattr__(self, name: str):
        """Everything else (tile planning, mask cache) from the wrapped model, so the
        widget plans the same tiles as for the model itself."""
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.inner, name)

    def forward(self, *args):
        self.calls += 1
        time.sleep(self.seconds)
        out = self.inner(*args)
        if self.hook is not None:
            self.hook(self.calls)
        return out


def _slow_model(monkeypatch, model_file: Path, system: SystemConfig,
                seconds: float) -> _SlowModel:
    """Make the Reconstruct widget use a slow copy of the model in ``model_file``."""
    import napari_svcode.widgets.reconstruct as module
    from svcode_core.methods.model_file import load_model

    model = _SlowModel(load_model(model_file)[0], seconds)
    monkeypatch.setattr(module, "cached_model", lambda path, system_: (model, system))
    return model


def _use_model(widget, path: Path) -> None:
    """Choose the model file ``path`` in a widget's model chooser (Reconstruct: its method)."""
    chooser = widget._panel.model if isinstance(widget, ReconstructWidget) else widget._model
    chooser.source.value = chooser.FROM_FILE
    chooser.path.value = path


# ----------------------------------------------------------------- calibration
def _drag(layer, index: int, shift) -> None:
    """Drag point ``index`` of a Points layer by ``shift`` as the select mode does, in two
    moves between a press and a release seen by the widget's mouse drag callback (napari
    hands it one event object whose type changes)."""
    event = SimpleNamespace(type="mouse_press")
    callbacks = [callback(layer, event) for callback in layer.mouse_drag_callbacks
                 if getattr(callback, "__name__", "") == "_track_press"]
    for callback in callbacks:
        next(callback)
    start = np.asarray(layer.data[index], dtype=float)
    layer.selected_data = {index}
    event.type = "mouse_move"
    layer._move({index}, start)
    layer._move({index}, start + np.asarray(shift, dtype=float))
    layer._drag_start = None  # as napari's release does
    event.type = "mouse_release"
    for callback in callbacks:
        next(callback, None)


def test_calibration_rays_and_one_box_move_together_and_save(tmp_path, tiny_system,
                                                             make_napari_viewer, errors):
    viewer = make_napari_viewer()
    raw = viewer.add_image(_raw_stack(tiny_system, 1)[0], name="raw", translate=(5, 7))
    widget = _dock(viewer, CalibrationWidget)
    widget.show_sub_views()  # the layer has no system yet
    assert errors and "no system configuration" in errors[-1]

    system_file = tiny_system.save(tmp_path / "system.json")
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = system_file
    widget.show_sub_views()
    boxes, rays = viewer.layers["sub-views"], viewer.layers["chief rays"]
    assert len(boxes.data) == 1 and len(rays.data) == 9  # one box at a time
    assert list(rays.text.values) == [f"lens {lens}" for lens in range(9)]
    assert rays.text.translation[0] < 0  # each label just above its ray
    # the system's 10 µm pixels: the raw layer in µm, still 5, 7 pixels off; rays and box on it
    assert tuple(raw.scale) == tuple(boxes.scale) == tuple(rays.scale) == (10, 10)
    assert tuple(raw.translate) == tuple(boxes.translate) == tuple(rays.translate) == (50, 70)
    assert [str(unit) for unit in rays.units] == ["micrometer"] * 2
    assert viewer.canvas.overlays.scale_bar.visible
    size, pad = tiny_system.sub_view_size, np.asarray(tiny_system.padding)

    def check_box(lens: int, system: SystemConfig) -> None:
        chief = np.asarray(system.chief_rays[lens])
        np.testing.assert_allclose(boxes.data[0].min(0), chief - size // 2 - pad - 0.5)
        np.testing.assert_allclose(boxes.data[0].max(0), chief - size // 2 - pad + size - 0.5)

    check_box(4, tiny_system)
    for lens, ray in enumerate(rays.data):
        np.testing.assert_allclose(ray, np.asarray(tiny_system.chief_rays[lens]) - pad)
    widget._lens.value = 2
    check_box(2, tiny_system)
    assert raw.metadata[SYSTEM_KEY] == tiny_system

    _drag(rays, 6, (2.0, -3.0))  # dragging lens 6's ray selects it and moves its box
    expected = list(tiny_system.chief_rays)
    expected[6] = (expected[6][0] + 2, expected[6][1] - 3)
    assert widget._lens.value == 6 and widget.system.chief_rays == tuple(expected)
    check_box(6, widget.system)
    assert raw.metadata[SYSTEM_KEY] == widget.system

    boxes.data = [boxes.data[0] + np.array([1.0, 1.0])]  # dragging the box moves the ray
    expected[6] = (expected[6][0] + 1, expected[6][1] + 1)
    assert widget.system.chief_rays == tuple(expected)
    np.testing.assert_allclose(rays.data[6], np.asarray(expected[6]) - pad)

    widget._out.value = tmp_path / "edited" / "system.json"
    (tmp_path / "edited").mkdir()
    widget.save()
    saved = SystemConfig.load(tmp_path / "edited" / "system.json")
    assert saved == tiny_system.replace(chief_rays=tuple(expected))

    boxes.data = [boxes.data[0], boxes.data[0]]  # a second box is refused, the system kept
    assert "one box at a time" in errors[-1]
    assert widget.system == saved


def test_calibration_refuses_a_system_of_another_sensor(tiny_system, make_napari_viewer, errors):
    viewer = make_napari_viewer()
    viewer.add_image(_raw_stack(tiny_system, 1)[0], name="raw")
    widget = _dock(viewer, CalibrationWidget)
    widget._system_choice.source.value = "cm2-mini"
    widget.show_sub_views()
    assert "480×640 sensor" in errors[-1] and "sub-views" not in viewer.layers


# ------------------------------------------------------- calibration from a scan
#: the lens array of the scanned instrument is off by this much (pixels)
SCAN_SHIFT = (1.3, -0.7)


@pytest.fixture
def scan_files(tmp_path, tiny_system) -> dict:
    """A 5×5 bead scan of the tiny system whose lens array is shifted by SCAN_SHIFT:
    ``scan.tif`` (with the nominal system), ``pos.csv``, ``dark.tif``, and the arrays."""
    from svcode_core.io import write_tiff
    from svcode_core.physics.departures import Departures
    from svcode_core.physics.scan import scan_grid, simulate_scan, with_dark_offset, write_positions
    from svcode_core.physics.simulate import Simulator

    system = with_dark_offset(tiny_system, 2e-3)
    departed = Simulator(system, departures=Departures(name="shifted", mla_shift_px=SCAN_SHIFT))
    positions = scan_grid(system, 5)
    frames, dark = simulate_scan(departed, positions, seed=1)
    return {"system": system, "frames": frames, "dark": dark, "positions": positions,
            "scan": write_tiff(tmp_path / "scan.tif", frames, system, kind="scan"),
            "dark_file": write_tiff(tmp_path / "dark.tif", dark, system, kind="dark"),
            "csv": write_positions(tmp_path / "pos.csv", positions)}


def _set_scan(widget: CalibrationWidget, files: dict, layer: bool = False) -> None:
    """Choose the scan (its file unless ``layer``), positions and dark file of ``files``."""
    if not layer:
        widget._scan.layer.value = None
        widget._scan.path.value = files["scan"]
    widget._positions.value = files["csv"]
    widget._dark.path.value = files["dark_file"]


def test_calibrate_from_a_scan_file_draws_the_fitted_rays_and_saves(
        qtbot, monkeypatch, tmp_path, scan_files, make_napari_viewer, errors):
    import threading

    from svcode_core.physics.calibration import calibrate

    seen: list[tuple[float, bool]] = []
    original = CalibrationWidget._on_progress

    def on_progress(self, stage: str, fraction: float) -> None:
        seen.append((fraction, threading.current_thread() is threading.main_thread()))
        original(self, stage, fraction)

    monkeypatch.setattr(CalibrationWidget, "_on_progress", on_progress)
    system = scan_files["system"]
    viewer = make_napari_viewer()
    raw = viewer.add_image(scan_files["frames"][12], name="raw", translate=(5, 7),
                           metadata=layer_metadata(system, "measurement"))
    widget = _dock(viewer, CalibrationWidget)
    _set_scan(widget, scan_files)
    widget._tolerance.value = 1e-3
    worker = widget.start_calibration()
    assert worker is not None and not widget._calibrate.enabled
    qtbot.waitUntil(lambda: widget._calibrate.enabled, timeout=60_000)
    assert not errors
    expected = calibrate(scan_files["frames"], scan_files["positions"], system,
                         dark=scan_files["dark"], tolerance=1e-3)
    fitted = expected.system
    assert fitted.chief_rays != system.chief_rays  # the shifted array was found
    assert widget.calibration.system == fitted and raw.metadata[SYSTEM_KEY] == fitted
    # the fitted rays drawn over the raw frame, placed like it
    rays, spots = viewer.layers["chief rays"], viewer.layers["spots"]
    np.testing.assert_allclose(rays.data, np.asarray(fitted.chief_rays) - np.asarray(
        fitted.padding))
    assert tuple(rays.translate) == tuple(spots.translate) == (50, 70)  # 5, 7 pixels of 10 µm
    assert widget._spot_frame.value == 12 and widget._spot_frame.max == 24
    kinds = list(spots.features["kind"])
    assert kinds.count("measured") == kinds.count("predicted") == 9  # the centre frame
    np.testing.assert_allclose(spots.data[:9], expected.centroids[12], atol=1e-9)
    widget._spot_frame.value = 0  # a corner position: fewer spots
    assert 0 < list(viewer.layers["spots"].features["kind"]).count("measured") < 9
    # progress: in order, to the end, always shown in the main thread
    assert seen and all(main for _, main in seen)
    assert [f for f, _ in seen] == sorted(f for f, _ in seen) and seen[-1][0] == 1.0
    assert widget._progress.value == widget._progress.max
    assert widget._status.value.startswith("Calibrated: array shift")
    assert "lens array: shift" in widget._report.value and _shown(widget._report)
    assert "scan (scan)" not in viewer.layers  # the raw layer was used, no scan layer added

    widget._folder.value = tmp_path / "cal"
    files = widget.save_calibration()
    assert files is not None and not errors
    saved = SystemConfig.load(tmp_path / "cal" / "system.json")
    assert saved.psf_model == str((tmp_path / "cal" / "psfs.tif").resolve())
    assert saved.replace(psf_model=None) == fitted
    assert raw.metadata[SYSTEM_KEY] == saved == widget.system  # now with the measured PSFs
    assert (tmp_path / "cal" / "report.txt").read_text() == widget._report.value
    assert files["figure"] == tmp_path / "cal" / "report.png" and files["figure"].is_file()


def test_calibrate_a_scan_layer_without_a_raw_frame_and_cancel(qtbot, tmp_path, scan_files,
                                                               make_napari_viewer, errors):
    viewer = make_napari_viewer()
    [scan] = viewer.open(scan_files["scan"], plugin="napari-svcode")
    widget = _dock(viewer, CalibrationWidget)
    assert widget._scan.layer.value is scan and widget._dark.layer.value is None
    _set_scan(widget, scan_files, layer=True)
    assert widget.start_calibration() is not None
    widget.cancel()  # stops at the next progress report
    qtbot.waitUntil(lambda: widget._calibrate.enabled, timeout=60_000)
    assert widget._status.value == "Calibration cancelled." and widget.calibration is None
    assert scan.metadata[SYSTEM_KEY] == scan_files["system"] and not errors

    assert widget.start_calibration() is not None
    qtbot.waitUntil(lambda: widget._calibrate.enabled, timeout=60_000)
    assert not errors and widget.calibration is not None
    assert scan.metadata[SYSTEM_KEY] == widget.calibration.system  # the scan itself
    assert "chief rays" in viewer.layers and "spots" in viewer.layers
    assert viewer.dims.current_step[0] == 12  # the frame whose spots are shown
    psfs = widget.calibration.psfs  # (9, G·G, k, k): lens 4's centre field point
    grid, k = int(np.sqrt(psfs.shape[1])), psfs.shape[-1]
    layer = widget.show_psf_grid()
    assert layer.name == "calibrated PSFs" and layer.data.shape == (3 * grid * k,) * 2
    centre = layer.data[grid * k:2 * grid * k, grid * k:2 * grid * k]
    np.testing.assert_array_equal(centre[(grid // 2) * k:(grid // 2 + 1) * k,
                                         (grid // 2) * k:(grid // 2 + 1) * k],
                                  psfs[4, (grid // 2) * grid + grid // 2])
    # over it, the FWHM of each PSF in µm (10 µm pixels), one cell centred on its PSF
    from svcode_core.physics.calibration import psf_fwhm

    fwhm = viewer.layers["PSF FWHM"]
    assert fwhm.data.shape == (3 * grid,) * 2 and tuple(layer.scale) == (10, 10)
    assert tuple(fwhm.scale) == (10 * k, 10 * k) and tuple(fwhm.translate) == (5 * (k - 1),) * 2
    assert fwhm.data[grid + grid // 2, grid + grid // 2] == pytest.approx(
        10 * psf_fwhm(psfs[4, (grid // 2) * grid + grid // 2]))
    assert tuple(scan.scale) == (1, 10, 10)  # the reader placed the scan in µm

    calibrated = widget.calibration  # a cancelled second run keeps the first calibration
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = scan_files["system"].replace(name="other").save(
        tmp_path / "other.json")
    assert widget.start_calibration() is not None
    widget.cancel()
    qtbot.waitUntil(lambda: widget._calibrate.enabled, timeout=60_000)
    assert widget.calibration is calibrated
    widget._folder.value = tmp_path / "cal"
    assert widget.save_calibration() is not None and not errors
    assert "calibration of 'tiny'" in (tmp_path / "cal" / "report.txt").read_text()


def test_calibration_positions_in_micrometres_use_the_pixel_size(tmp_path, scan_files,
                                                                 make_napari_viewer, errors):
    viewer = make_napari_viewer()
    widget = _dock(viewer, CalibrationWidget)
    _set_scan(widget, scan_files)
    assert "x_um,y_um" in widget._positions.tooltip and "whole" not in widget._positions.tooltip
    system, positions = scan_files["system"], scan_files["positions"]
    y, x = ((positions - system.sub_view_size // 2) * 10.0).T  # the tiny system's 10 µm
    stage = tmp_path / "stage.csv"
    stage.write_text("x_um,y_um\n" + "".join(f"{a},{b}\n" for a, b in zip(x, y, strict=True)))
    widget._positions.value = stage
    np.testing.assert_allclose(widget._read_scan()["positions"], positions)  # the system's
    widget._pixel_size.value = 20.0  # given: half as many pixels from the centre
    centre = system.sub_view_size // 2
    np.testing.assert_allclose(widget._read_scan()["positions"],
                               centre + (positions - centre) / 2)
    assert not errors


def test_calibration_errors_are_one_notification_each(qtbot, tmp_path, scan_files,
                                                      make_napari_viewer, errors):
    viewer = make_napari_viewer()
    widget = _dock(viewer, CalibrationWidget)
    assert widget.start_calibration() is None and "No scan chosen" in errors[-1]
    _set_scan(widget, scan_files)
    bad = tmp_path / "bad.csv"
    bad.write_text("row,col\n0,1\n2.5,x\n")
    widget._positions.value = bad
    assert widget.start_calibration() is None
    assert len(errors) == 2 and errors[-1].count("\n") == 1
    assert "bad.csv line 3: 'x' is not a number" in errors[-1] and "x_um,y_um" in errors[-1]

    widget._positions.value = scan_files["csv"]
    widget._system_choice.source.value = "cm2-mini"  # another sensor
    assert widget.start_calibration() is None
    assert len(errors) == 3 and "480×640 sensor" in errors[-1]

    widget._system_choice.source.value = widget._system_choice.FROM_LAYER
    short = tmp_path / "short.csv"
    short.write_text("row,col\n" + "\n".join(f"{r},{c}" for r, c in
                                                scan_files["positions"][:-1]) + "\n")
    widget._positions.value = short  # the core's error, raised in the worker
    assert widget.start_calibration() is not None
    qtbot.waitUntil(lambda: widget._calibrate.enabled, timeout=60_000)
    assert len(errors) == 4 and "25 frames but the positions list 24" in errors[-1]
    assert "Traceback" not in errors[-1] and widget.calibration is None
    assert widget.save_calibration() is None and "No calibration" in errors[-1]


def test_self_registration_moves_the_rays_saves_and_refuses_what_no_drift_explains(
        qtbot, monkeypatch, tmp_path, tiny_system, make_napari_viewer, errors):
    import svcode_core.methods.baselines.self_registration as core
    from svcode_core.config import load_system
    from svcode_core.phantoms import make_object
    from svcode_core.physics.departures import Departures
    from svcode_core.physics.simulate import Simulator

    # the drift and frame of tests/test_registration.py: 0.24 px there
    drift = Departures(name="drift", mla_shift_px=(0.8, -0.5), mla_rotation_deg=1.0,
                       lens_jitter_px=0.4, seed=5)
    obj = make_object("cells", tiny_system.sub_view_size, 1)
    frame = Simulator(tiny_system, departures=drift).simulate(obj, seed=2).measurement
    viewer = make_napari_viewer()
    raw = viewer.add_image(np.stack([frame, frame]), name="raw",
                           metadata=layer_metadata(tiny_system, "measurement"))
    widget = _dock(viewer, CalibrationWidget)
    widget._register_folder.value = tmp_path / "reg"
    assert widget.start_registration() is not None and not widget._register.enabled
    widget.cancel()  # stops before the first round
    qtbot.waitUntil(lambda: widget._register.enabled, timeout=60_000)
    assert widget._status.value == "Self-registration cancelled." and not errors
    assert raw.metadata[SYSTEM_KEY] == tiny_system and not (tmp_path / "reg").exists()

    assert widget.start_registration() is not None
    qtbot.waitUntil(lambda: widget._register.enabled, timeout=120_000)
    assert not errors and widget._status.value.startswith("Registered: array shift")
    moved = load_system(tmp_path / "reg" / "system.json")
    assert raw.metadata[SYSTEM_KEY] == moved and moved.psf_model is not None
    relative = drift.lens_offsets(tiny_system) - drift.lens_offsets(tiny_system)[4]
    error = np.linalg.norm(widget.registration.offsets - relative, axis=1)
    assert error.max() < 0.3 < np.linalg.norm(relative, axis=1).max(), error
    np.testing.assert_allclose(viewer.layers["chief rays"].data,
                               np.asarray(moved.chief_rays) - np.asarray(moved.padding))
    assert (tmp_path / "reg" / "registration.json").is_file()

    def misled(*args, **kwargs):  # what a dense scene does: one lens far off the array
        raise core.RegistrationRejected("self-registration not applied: lens 2 would move "
                                        "3.7 px away from the rest of the array")

    monkeypatch.setattr("napari_svcode.widgets.calibration.register_recording", misled)
    assert widget.start_registration() is not None
    qtbot.waitUntil(lambda: widget._register.enabled, timeout=60_000)
    assert len(errors) == 1 and "lens 2 would move 3.7 px" in errors[-1]
    assert "bead scan" in errors[-1] and raw.metadata[SYSTEM_KEY] == moved


def test_a_moved_sub_view_box_keeps_the_bundled_model(qtbot, monkeypatch, tmp_path, tiny_system,
                                                      make_napari_viewer, errors,
                                                      make_model_file):
    """The model sees sub-views and coordinates relative to them: moving a box (a chief
    ray) only moves where its sub-view is cut, so the bundled model applies unchanged."""
    import napari_svcode.widgets._choosers as choosers
    from svcode_core.methods.model_file import load_model

    bundled = make_model_file(tmp_path / "tiny.safetensors", tiny_system)
    monkeypatch.setattr(choosers, "bundled_model",
                        lambda name=None: bundled if name in (None, "tiny") else None)
    viewer = make_napari_viewer()
    frame = _raw_stack(tiny_system, 1)[0]
    raw = viewer.add_image(frame, name="raw", metadata=layer_metadata(tiny_system, "measurement"))
    calibration = _dock(viewer, CalibrationWidget)
    calibration.show_sub_views()
    calibration._lens.value = 6
    boxes = viewer.layers["sub-views"]
    boxes.data = [boxes.data[0] + np.array([1.0, -2.0])]
    moved = calibration.system
    assert moved.chief_rays[6] != tiny_system.chief_rays[6] and raw.metadata[SYSTEM_KEY] == moved

    widget = _dock(viewer, ReconstructWidget)
    assert widget._panel.model.source.value == widget._panel.model.BUNDLED
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=30_000)
    assert not errors
    recon = viewer.layers["reconstruction"]
    assert recon.metadata[SYSTEM_KEY] == moved
    expected = Reconstructor(load_model(bundled)[0], moved, batch_size=8).reconstruct(frame)
    np.testing.assert_allclose(recon.data, expected.reconstruction, atol=1e-6)

    # any other difference is refused, the differing field named first, in a toast
    raw.metadata = {**raw.metadata, SYSTEM_KEY: moved.replace(patch_size=24, patch_stride=12)}
    assert widget.start() is None
    cause, fix = errors[-1].split("\n")[:2]
    assert cause == "tiny.safetensors was trained for system 'tiny', which differs in " \
                    "patch_size, patch_stride"
    assert fix == "→ choose a model trained for this system"


# ---------------------------------------------------------------- reconstruct
def test_reconstruct_frames_runs_the_current_frame_first(tiny_system, model_file):
    from svcode_core.methods.model_file import load_model

    model, _ = load_model(model_file)
    rec = Reconstructor(model, tiny_system, batch_size=8)
    stack = _raw_stack(tiny_system, 4)
    done = [item for item in reconstruct_frames(rec, stack, first=1, return_views=True)
            if not isinstance(item, FrameProgress)]
    assert [index for index, _ in done] == [1, 2, 3, 0]  # the done frames stay contiguous
    expected = rec.reconstruct(stack[3], return_views=True)
    np.testing.assert_allclose(done[2][1].reconstruction, expected.reconstruction)
    np.testing.assert_allclose(done[2][1].views, expected.views)


def test_reconstruct_widget_adds_layers(qtbot, tiny_system, model_file, make_napari_viewer):
    viewer = make_napari_viewer()
    stack, widget = _stack_in_widget(viewer, tiny_system, model_file, 3, current=1)
    widget._views.value = True
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=30_000)
    recon, views = viewer.layers["reconstruction"], viewer.layers["demixed views"]
    size = tiny_system.sub_view_size
    assert recon.data.shape == (3, size, size) and views.data.shape == (9, 3, size, size)
    assert tuple(recon.translate) == (0, *object_translate(tiny_system))
    assert tuple(views.translate) == (0, 0, *object_translate(tiny_system))
    expected = widget_reconstructor(model_file, tiny_system).reconstruct(stack, True)
    np.testing.assert_allclose(recon.data, expected.reconstruction, atol=1e-6)
    np.testing.assert_allclose(views.data, expected.views.transpose(1, 0, 2, 3), atol=1e-6)
    assert recon.metadata[SYSTEM_KEY] == tiny_system
    assert recon.metadata["svcode_model"]["path"] == str(model_file)
    assert widget.frames_done == 3 and widget._run.enabled


def widget_reconstructor(path: Path, system: SystemConfig) -> Reconstructor:
    return Reconstructor.from_weights(path, system, batch_size=8)


def test_reconstruct_cancel_stops_within_a_batch(qtbot, monkeypatch, tiny_system, model_file,
                                                 make_napari_viewer):
    import napari_svcode.widgets.reconstruct as module

    notices = []
    model = _slow_model(monkeypatch, model_file, tiny_system, 0.2)  # ≥ 1.2 s in all
    monkeypatch.setattr(module, "show_info", notices.append)
    viewer = make_napari_viewer()
    _, widget = _stack_in_widget(viewer, tiny_system, model_file, 6)
    widget._panel.batch.value, widget._panel.skip.value = 1, False  # a batch a frame
    assert widget.start() is not None
    qtbot.waitUntil(lambda: model.calls >= 3, timeout=30_000)
    widget.cancel()
    at_cancel = model.calls
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=30_000)
    assert model.calls <= at_cancel + 1  # at most the batch that was running
    assert widget.frames_done < 6 and not widget._cancel.enabled
    assert notices and "cancelled after" in notices[-1]


def test_a_paper_scale_frame_shows_its_tiles_and_cancels_within_one(
        qtbot, monkeypatch, tmp_path, tiny_model_config, make_napari_viewer):
    """A whole cm2-v2 frame (3000 × 4000 sensor, 2400² sub-views) in 25 tiles: the status
    line counts them as they run, and Cancel stops after the tile that is running."""
    system = SystemConfig.preset("cm2-v2")
    torch.manual_seed(0)  # masks on a lattice, as the bundled models have them
    model = SVCoDe(tiny_model_config.replace(mask_spacing=48))
    path = save_model(tmp_path / "v2.safetensors", model, system)
    model = _slow_model(monkeypatch, path, system, 0.2)
    # the network's own work is beside the point here (a 2-channel grouped convolution
    # over 800² takes a tenth of a second): each tile returns its views at once
    model.inner.forward = lambda views, origins, size: (views, views.mean(1, keepdim=True))
    statuses: list[str] = []
    viewer = make_napari_viewer()
    frame = np.full(system.sensor_shape, 0.2, np.float32)
    viewer.add_image(frame, name="raw", metadata=layer_metadata(system, "measurement"))
    widget = _dock(viewer, ReconstructWidget)
    _use_model(widget, path)
    widget._panel.tile.value, widget._panel.batch.value = 800, 1  # stride 400: 5 × 5 tiles
    widget._progress.changed.connect(lambda value: statuses.append(widget._status.value))
    worker = widget.start() or widget.start()  # the second press confirms a long run
    assert worker is not None
    qtbot.waitUntil(lambda: model.calls >= 3, timeout=60_000)
    widget.cancel()
    at_cancel = model.calls
    _wait_done(qtbot, widget)
    assert model.calls <= at_cancel + 1 < 25  # at most the tile that was running
    counted = [status for status in statuses if re.search(r", tiles [1-9]\d*/25\b", status)]
    assert counted, statuses  # (the line is updated at most every few tiles)
    assert "reconstruction" not in viewer.layers and widget.frames_done == 0


def test_reconstruct_errors_are_notices(make_model_file, qtbot, tmp_path, tiny_system,
                                       model_file, make_napari_viewer, errors):
    viewer = make_napari_viewer()
    widget = _dock(viewer, ReconstructWidget)
    _use_model(widget, model_file)
    meta = layer_metadata(tiny_system, "measurement")
    wrong = viewer.add_image(np.zeros((50, 50), np.float32), name="wrong", metadata=meta)
    widget._layer.value = wrong
    assert widget.start() is None and "expects raw sensor frames of 60×80" in errors[-1]

    frame = _raw_stack(tiny_system, 1)[0]
    frame[3, 4] = np.nan
    widget._layer.value = viewer.add_image(frame, name="nan", metadata=meta)
    assert widget.start() is None and "1 NaN or Inf" in errors[-1]

    other = make_model_file(tmp_path / "other.safetensors", tiny_system.replace(name="other"))
    _use_model(widget, other)
    assert widget.start() is None and "trained for system 'other'" in errors[-1]
    assert "choose a model trained for this system" in errors[-1]

    widget._panel.model.source.value = widget._panel.model.BUNDLED
    assert widget.start() is None and "bundled" in errors[-1]
    assert len(errors) == 4 and widget.worker is None

    _use_model(widget, model_file)  # the viewer stays usable
    widget._layer.value = viewer.add_image(_raw_stack(tiny_system, 1)[0], name="ok",
                                           metadata=meta)
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=30_000)
    assert viewer.layers["reconstruction"].data.shape == (tiny_system.sub_view_size,) * 2


def _shown(widget) -> bool:
    return not widget.native.isHidden()


def _wait_done(qtbot, widget, timeout: int = 120_000) -> None:
    qtbot.waitUntil(lambda: widget._run.enabled and not widget.worker.is_running,
                    timeout=timeout)


def test_pickers_fit_their_role_and_tiling_defaults_come_from_the_core(make_napari_viewer):
    from svcode_core.methods import reconstructor_defaults

    viewer = make_napari_viewer()
    viewer.open_sample("napari-svcode", "cells")  # ground truth first, then the raw frame
    widget = _dock(viewer, ReconstructWidget)
    assert widget._layer.value is viewer.layers["cells raw"]
    assert widget._truth.value is viewer.layers["cells ground truth"]
    defaults = reconstructor_defaults()
    assert widget._panel.batch.value == (defaults["batch_size"] or 0)
    assert widget._panel.options().get("batch_size") == defaults["batch_size"]
    assert widget._panel.tile.value == (defaults["tile_size"] or 0)
    assert widget._panel.skip.value == defaults["skip_empty"]
    assert widget._panel.refine.value == defaults["refine_periphery"] == 0
    assert "refine_periphery" not in widget._panel.options()
    widget._panel.refine.value = 10
    assert widget._panel.options()["refine_periphery"] == 10
    assert "admm" in widget._panel.method.choices
    # a picker docked before the layers exist moves to the raw frame when it appears
    viewer.layers.clear()
    late = _dock(viewer, ReconstructWidget)
    viewer.open_sample("napari-svcode", "beads")
    assert late._layer.value is viewer.layers["beads raw"]


def test_each_method_shows_only_its_options(make_napari_viewer):
    from svcode_core.methods import METHODS, registry

    viewer = make_napari_viewer()
    viewer.open_sample("napari-svcode", "cells")
    widget = _dock(viewer, ReconstructWidget)
    panel = widget._panel
    assert panel.method.choices == METHODS
    expected = {"svcode": {"model", "precision", "tile", "batch", "skip", "refine"},
                "admm": {"precision", "rank", "iterations", "tv_weight", "tv_auto"},
                "wiener": {"precision", "rank", "balance", "boundary"},
                "rl": {"precision", "rank", "iterations"},
                "multiwiener": {"weights", "precision"}, "fouriernet": {"weights", "precision"}}
    for method, names in expected.items():
        panel.method.value = method
        assert {name for name, w in panel._widgets.items() if _shown(w)} == names, method
    # each model-based method's widgets start at its defaults (svcode_core's registry)
    for method in registry.MODEL_BASED_METHODS:
        panel.method.value = method
        options = panel.options()
        assert options.pop("rank") is None  # the default rank
        options.pop("precision")
        shown = {k: v for k, v in registry.method(method).defaults.items()
                 if k in ("iterations", "tv_weight", "balance", "boundary")}
        assert options == shown, method
    panel.method.value = "admm"
    assert panel.precision.choices == ("fp32", "fp64")
    assert not _shown(widget._second)
    widget._compare.value = True
    assert _shown(widget._second) and widget._second.method.value == "admm"


def test_option_widgets_are_made_from_the_tables(qtbot):
    """Every option of every method's table that is not advanced has a widget, shown with
    its method, labelled, with the table's help and starting at the table's default, which
    is what the panel gives; the advanced ones have none (only their flag)."""
    from napari_svcode.widgets._methods import MethodPanel
    from svcode_core.methods import METHODS, registry

    panel = MethodPanel()
    for method in METHODS:
        panel.method.value = method
        expected = {"precision": registry.method(method).precisions[0]}
        for option in registry.method(method).options:
            name = option.widget or option.name
            if option.advanced:
                assert name not in panel._widgets, (method, name)
                continue
            widget = panel._widgets[name]
            assert _shown(widget) and widget.tooltip.startswith(option.describe())
            assert option.label in (widget.label, getattr(widget, "text", None))
            if option.auto:  # a tick box for "auto", the number beside it
                box = panel._widgets[f"{name.split('_')[0]}_auto"]
                assert box.value == (option.default == "auto")
            elif option.ceiling or option.default is None:
                assert widget.value == 0  # 0: the default
            else:
                assert widget.value == option.default, (method, name)
            if option.default != 0:  # an option that is 0 (none) by default is left out
                expected[option.name] = None if option.ceiling else option.default
        assert panel.options() == expected, method


def test_the_cost_estimate_tiles_as_the_core_does(qtbot):
    """The plugin's estimate counts the tiles and working memory the core plans for the
    run (the bundled model's whole sub-view by default), not a formula of its own."""
    from napari_svcode.widgets._methods import MethodPanel
    from svcode_core.methods.svcode import tile_plan

    system = SystemConfig.preset("cm2-mini")
    panel = MethodPanel()
    for tile in (0, 100, 7):
        panel.tile.value = tile
        options = {k: v for k, v in panel.options().items() if v is not None}
        run = Reconstructor.pretrained(system, **options)
        per_frame = len(run.grid)
        cost = panel.cost(system, 2, "cpu", False)
        assert cost.detail == f"{2 * per_frame:,} tiles: {per_frame:,} a frame × 2 frames"
        planned = tile_plan(run.model, system, tile_size=tile or None).working_bytes
        assert planned > 0 and cost.memory == 2 * 384**2 * 4 + 2**30 + planned
    assert per_frame == 138**2  # 7-px tiles at stride 3 over the sub-view and its 16-px margin


def test_cells_sample_reconstructs_with_lsv_admm(qtbot, make_napari_viewer):
    """After opening the cells sample the widget points at the raw frame, offers LSV-ADMM
    and adds a finite S×S layer with it."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-svcode", "cells")
    widget = _dock(viewer, ReconstructWidget)
    widget._panel.method.value = "admm"
    widget._panel.iterations.value = 2
    shown: list[tuple[int, bool, str]] = []  # the bar's maximum, the ticker, the status
    set_progress = widget._set_progress

    def spy(*args, **kwargs) -> None:
        set_progress(*args, **kwargs)
        shown.append((widget._progress.native.maximum(), widget._ticker.isActive(),
                       widget._status.value))

    widget._set_progress = spy
    assert widget.start() is not None
    _wait_done(qtbot, widget, 300_000)
    # determinate throughout (no busy animation); while ADMM prepares, the status line
    # counts the seconds
    assert all(top == STEPS for top, _, _ in shown)
    assert any(ticking and "preparing" in text for _, ticking, text in shown)
    assert not widget._ticker.isActive()
    assert widget._progress.value == widget._progress.max == STEPS
    recon = viewer.layers["reconstruction"]
    size = SystemConfig.preset("cm2-mini").sub_view_size
    assert recon.data.shape == (size, size) and np.isfinite(recon.data).all()
    assert recon.metadata["svcode_model"]["method"] == "admm"
    [entry] = widget.results  # the ground truth was picked: quality and seconds
    assert entry["seconds"] > 0 and np.isfinite(entry["psnr_ring"]) and 0 < entry["ssim"] <= 1
    assert "LSV-ADMM" in widget._results.value and "PSNR" in widget._results.value
    widget._state["busy"] = ("LSV-ADMM: preparing…", time.perf_counter() - 3.2)
    widget._tick()
    assert widget._status.value == "LSV-ADMM: preparing… 3 s"


def test_compare_two_methods_side_by_side(qtbot, tiny_system, model_file, make_napari_viewer):
    """Each panel is named by its method and knobs (and shows it in its grid cell), both
    share one contrast range, and both are scored against the frame's own truth."""
    viewer = make_napari_viewer()
    stack = _raw_stack(tiny_system, 2)
    viewer.add_image(stack, name="raw",
                     metadata=layer_metadata(tiny_system, "measurement", scene="s1"))
    size = tiny_system.sub_view_size
    viewer.add_image(np.random.default_rng(1).random((size, size)), name="truth",
                     translate=object_translate(tiny_system),
                     metadata=layer_metadata(tiny_system, "object", scene="s1"))
    viewer.dims.set_current_step(0, 1)
    widget = _dock(viewer, ReconstructWidget)
    assert widget._layer.value.name == "raw" and widget._truth.value.name == "truth"
    _use_model(widget, model_file)
    widget._compare.value = True
    widget._second.method.value = "wiener"
    widget._second.balance.value = 0.05
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    first = viewer.layers["A: SV-CoDe (network)"]
    second = viewer.layers["B: Wiener (per view, fused), balance 0.05, reflect boundary"]
    assert first.data.shape == second.data.shape == (size, size)  # the current frame only
    expected = widget_reconstructor(model_file, tiny_system).reconstruct(stack[1])
    np.testing.assert_allclose(first.data, expected.reconstruction, atol=1e-6)
    assert [entry["method"] for entry in widget.results] == ["svcode", "wiener"]
    assert all({"psnr", "ssim", "psnr_centre", "psnr_ring", "seconds"} <= set(entry)
               for entry in widget.results)
    assert second.metadata["svcode_quality"]["method"] == "wiener"
    assert "balance 0.05" in widget._results.value
    assert viewer.canvas.grid.enabled and not viewer.layers["raw"].visible
    assert first.name_overlay.visible and second.name_overlay.visible
    low = min(first.data.min(), second.data.min())
    high = max(first.data.max(), second.data.max())
    np.testing.assert_allclose(first.contrast_limits, (low, high), rtol=1e-5)
    np.testing.assert_allclose(second.contrast_limits, (low, high), rtol=1e-5)
    first.contrast_limits = (low, (low + high) / 2)  # changing one changes the other
    np.testing.assert_allclose(second.contrast_limits, (low, (low + high) / 2), rtol=1e-5)
    assert widget._status.value.startswith("Done")

    widget._second.balance.value = 0.1  # new knobs: the old panel B makes way
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert second.name not in viewer.layers
    assert sum(name.startswith("B: ") for name in map(str, viewer.layers)) == 1


def test_compare_scores_only_against_the_truth_of_its_own_scene(
        qtbot, tiny_system, model_file, make_napari_viewer):
    """An all-zero frame of no scene is not scored against another scene's truth: the
    chooser leaves the truth empty, and a truth forced onto it is refused in the status."""
    viewer = make_napari_viewer()
    size = tiny_system.sub_view_size
    viewer.add_image(np.random.default_rng(1).random((size, size)), name="cells truth",
                     translate=object_translate(tiny_system),
                     metadata=layer_metadata(tiny_system, "object", scene="cells"))
    viewer.add_image(_raw_stack(tiny_system, 1)[0], name="cells raw",
                     metadata=layer_metadata(tiny_system, "measurement", scene="cells"))
    widget = _dock(viewer, ReconstructWidget)
    _use_model(widget, model_file)
    assert widget._truth.value.name == "cells truth"
    zeros = viewer.add_image(np.zeros(tiny_system.sensor_shape, np.float32), name="zeros",
                             metadata=layer_metadata(tiny_system, "measurement"))
    widget._layer.value = zeros
    assert widget._truth.value is None  # another scene's truth does not stay selected
    widget._compare.value = True
    widget._second.method.value = "wiener"
    widget._truth.value = viewer.layers["cells truth"]  # forced: refused, not scored
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert len(widget.results) == 2 and not any("psnr" in entry for entry in widget.results)
    assert "PSNR" not in widget._results.value
    assert "Not scored" in widget._status.value and "another scene" in widget._status.value
    assert not viewer.layers["cells truth"].visible  # not shown as the truth either
    widget._layer.value = viewer.layers["cells raw"]  # back to the frame: its own truth
    assert widget._truth.value.name == "cells truth"


def test_costly_settings_ask_before_running(qtbot, make_napari_viewer, warnings, monkeypatch):
    import napari_svcode.widgets._methods as methods

    monkeypatch.setattr(methods, "LONG_RUN_SECONDS", 60.0)  # 7-px tiles: a few minutes
    viewer = make_napari_viewer()
    viewer.open_sample("napari-svcode", "cells")
    widget = _dock(viewer, ReconstructWidget)
    assert not _shown(widget._warning)
    widget._panel.tile.value = 7
    assert _shown(widget._warning) and "19,044 tiles" in widget._warning.value
    assert widget.start() is None and widget.worker is None
    cause, fix = warnings[-1].split("\n")[:2]
    assert "19,044 tiles" in cause and "Reconstruct anyway" in fix
    assert widget._run.text == "Reconstruct anyway"
    worker = widget.start()  # the way on: a second press runs it
    assert worker is not None
    widget.cancel()
    _wait_done(qtbot, widget)
    widget._panel.tile.value = 0  # back to the default: no warning
    assert not _shown(widget._warning) and widget._run.text == "Reconstruct"


def test_a_run_that_would_not_fit_in_memory_warns(monkeypatch):
    import napari_svcode.widgets._methods as methods

    class Memory:
        available = 4 << 30

    monkeypatch.setattr(methods.psutil, "virtual_memory", lambda: Memory)
    assert methods.Cost(10.0, 1 << 30, "300 frames").warning() is None
    warning = methods.Cost(10.0, 5 << 30, "300 frames").warning()
    assert warning == "needs about 5.0 GiB, 4.0 GiB free (300 frames)"
    assert "about 2.0 h" in methods.Cost(7200.0, 0, "16,129 tiles").warning()


def test_the_status_says_when_the_periphery_is_refined(qtbot, monkeypatch, tiny_system,
                                                       model_file, make_napari_viewer):
    viewer = make_napari_viewer()
    _, widget = _stack_in_widget(viewer, tiny_system, model_file, 1)
    widget._panel.refine.value = 2
    texts: list[str] = []
    show = ReconstructWidget._set_progress
    monkeypatch.setattr(ReconstructWidget, "_set_progress",
                        lambda self, *args, **kw: (texts.append(args[3]), show(self, *args, **kw)))
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert any(text.endswith("frame, refining the periphery…") for text in texts), texts
    assert widget._status.value.startswith("Done")


def test_cancelled_stack_adds_only_the_frames_done(qtbot, monkeypatch, tmp_path, tiny_system,
                                                   model_file, make_napari_viewer):
    model = _slow_model(monkeypatch, model_file, tiny_system, 0.0)  # a batch a frame
    viewer = make_napari_viewer()
    stack, widget = _stack_in_widget(viewer, tiny_system, model_file, 5, current=2)
    widget._panel.batch.value, widget._panel.skip.value = 1, False
    widget._views.value = True
    # cancelled from the worker while it runs frame 3, whatever the machine's load
    model.hook = lambda calls: widget.worker.quit() if calls == 3 else None
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    done = widget.frames_done
    assert 1 <= done < 5
    recon, views = viewer.layers["reconstruction"], viewer.layers["demixed views"]
    assert recon.data.shape[0] == views.data.shape[1] == done  # no zero frames
    assert tuple(recon.translate)[0] == 2 and tuple(views.translate)[1] == 2
    expected = Reconstructor.from_weights(model_file, tiny_system, batch_size=1,
                                          skip_empty=False).reconstruct(stack[2:2 + done])
    np.testing.assert_allclose(recon.data, expected.reconstruction, atol=1e-6)
    assert views.axis_labels[0] == "lens" and recon.axis_labels[0] == "frame"
    assert viewer.dims.axis_labels[0] == "lens"  # the slider is labelled, not "-3"
    # the bar and the status show what was kept; the layers and the file say which frames
    assert widget._progress.value == done * STEPS and widget._progress.max == 5 * STEPS
    assert widget._status.value.startswith("Cancelled") and f"{done} of 5" in widget._status.value
    frames = {"first": 2, "stop": 2 + done, "total": 5}
    assert recon.metadata["svcode_frames"] == views.metadata["svcode_frames"] == frames
    from svcode_core.io import read_tiff

    path = tmp_path / "partial.tif"
    recon.save(str(path), plugin="napari-svcode")
    assert read_tiff(path)[2]["frames"] == frames


def test_a_new_reconstruct_widget_starts_on_the_raw_frame(tiny_system, make_napari_viewer):
    """Docked after a plain image and a raw frame were opened, in that order, the widget
    chooses the raw frame (the better fit), not the first image of the list."""
    viewer = make_napari_viewer()
    viewer.add_image(np.zeros((64, 64), np.float32), name="edges")
    viewer.add_image(np.zeros(tiny_system.sensor_shape, np.float32), name="raw",
                     metadata=layer_metadata(tiny_system, "measurement"))
    viewer.layers.selection.active = viewer.layers["edges"]
    widget = _dock(viewer, ReconstructWidget)
    assert widget._layer.value.name == "raw"


def test_a_cancel_during_a_frames_last_step_keeps_the_frame():
    """run_jobs passes on every report of a frame but the one that all its tiles (or
    iterations) are done, which only cheap work follows: a cancel pressed during the last
    step takes effect after the frame's FrameDone (the worker stops before asking for the
    next item), not at that report, where the finished frame was thrown away. A periphery
    refinement's report stays (a cancel there stops before the refinement, as documented)."""
    from napari_svcode.widgets.reconstruct import Job, Started, run_jobs

    class Stepped:
        def iter_reconstruct(self, frame, return_views):
            for done in range(3):
                yield FrameProgress(0, 1, done, 2)
            yield FrameProgress(0, 1, 2, 2, refining=True)
            return "result"

    items = list(run_jobs([Job("svcode", Stepped)], np.zeros((2, 4, 4))))
    reports = [(item.tiles_done, item.refining) for item in items
               if isinstance(item, FrameProgress)]
    assert reports == [(0, False), (1, False), (2, True)] * 2
    assert isinstance(items[0], Started)
    assert [type(item).__name__ for item in items[-2:]] == ["FrameProgress", "FrameDone"]
    assert items[-1].result == "result"


def test_the_status_line_tells_how_the_last_run_ended(qtbot, monkeypatch, tiny_system,
                                                       model_file, make_napari_viewer, errors):
    model = _slow_model(monkeypatch, model_file, tiny_system, 0.0)
    viewer = make_napari_viewer()
    _, widget = _stack_in_widget(viewer, tiny_system, model_file, 1)
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert widget._status.value.startswith("Done in")

    def fail(calls: int) -> None:
        raise RuntimeError("CUDA out of memory (simulated)")

    model.hook = fail  # an error in the worker: not "Done" from the run before
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert widget._status.value.startswith("Failed after")
    assert "CUDA out of memory (simulated)" in widget._status.value
    assert widget._progress.value == 0

    model.hook = None
    meta = layer_metadata(tiny_system, "measurement")
    widget._layer.value = viewer.add_image(np.zeros((50, 50), np.float32), name="wrong",
                                           metadata=meta)
    assert widget.start() is None  # refused before running: said so, not the last run's
    assert widget._status.value.startswith("Not run:") and "60×80" in widget._status.value


def test_progress_shows_in_the_widget_within_a_second_without_event_processing(
        qtbot, monkeypatch, tiny_system, model_file, make_napari_viewer):
    from qtpy.QtCore import QCoreApplication

    inside, reentered = [], []
    original_yielded = ReconstructWidget._on_yielded

    def on_yielded(self, item):
        inside.append(item)
        try:
            original_yielded(self, item)
        finally:
            inside.pop()

    original_process = QCoreApplication.processEvents

    def process_events(*args):
        if inside:
            reentered.append(args)
        return original_process(*args)

    monkeypatch.setattr(ReconstructWidget, "_on_yielded", on_yielded)
    monkeypatch.setattr(QCoreApplication, "processEvents", staticmethod(process_events))
    viewer = make_napari_viewer()
    _, widget = _stack_in_widget(viewer, tiny_system, model_file, 3)
    seen: list[tuple[float, int, str]] = []
    widget._progress.changed.connect(
        lambda value: seen.append((time.perf_counter(), value, widget._status.value)))
    pressed = time.perf_counter()
    widget._run.changed.emit(True)  # as the button does
    assert widget._status.value.startswith("Starting")  # at once, before the worker runs
    qtbot.waitUntil(lambda: "preparing" in widget._status.value or bool(seen), timeout=1_000)
    assert time.perf_counter() - pressed < 1.0
    _wait_done(qtbot, widget)
    assert seen and seen[-1][1] == widget._progress.max == 3 * STEPS
    assert [value for _, value, _ in seen] == sorted(value for _, value, _ in seen)
    assert widget._status.value.startswith("Done")
    assert viewer.layers["reconstruction"].data.shape[0] == 3 and not reentered


def test_errors_toast_cause_and_fix_and_log_the_full_text(make_model_file, tmp_path, tiny_system,
                                                          model_file, make_napari_viewer, errors,
                                                          caplog):
    viewer = make_napari_viewer()
    widget = _dock(viewer, ReconstructWidget)
    (tmp_path / "deep").mkdir()
    other = make_model_file(tmp_path / "deep" / "other.safetensors",
                        tiny_system.replace(name="other"))
    _use_model(widget, other)
    viewer.add_image(_raw_stack(tiny_system, 1)[0], name="raw",
                     metadata=layer_metadata(tiny_system, "measurement"))
    with caplog.at_level("ERROR", logger="napari_svcode"):
        assert widget.start() is None
    cause, fix = errors[-1].split("\n")[:2]
    assert len(cause) <= 90 and str(tmp_path) not in cause and "other.safetensors" in cause
    assert fix == "→ choose a model trained for this system"
    assert str(other) in caplog.text and "differs" in caplog.text  # the full text is logged
    whole = errors[-1].split("\n\n", 1)[1]  # and shown on the toast's expand arrow
    assert str(other) in whole and "1 field(s): name" in whole

    widget._panel.method.value = "fouriernet"  # a learned baseline without a model file
    assert widget.start() is None
    cause, fix, _, whole = errors[-1].split("\n")
    assert "needs a trained model file" in cause and "svcode train --method fouriernet" in whole


def test_cli_command_for_a_folder(tiny_system, make_napari_viewer):
    import shlex

    from svcode_core.cli import build_parser

    viewer = make_napari_viewer()
    viewer.open_sample("napari-svcode", "cells")
    widget = _dock(viewer, ReconstructWidget)
    widget._panel.method.value = "admm"
    widget._panel.iterations.value = 40
    text = widget.copy_command()
    assert text == widget._command_text.value and _shown(widget._command_text)
    assert text.startswith("for f in FOLDER/*.tif; do svcode reconstruct")
    command = text.split("; do ", 1)[1].removesuffix("; done")
    command = command.replace('"$f"', "in.tif").replace('"${f%.tif}.recon.tif"', "out.tif")
    args = build_parser().parse_args(shlex.split(command)[1:])
    assert (args.method, args.iterations, args.system) == ("admm", 40, "cm2-mini")
    assert args.tv_weight == "auto"  # the default: λ from each frame's noise
    assert widget._panel.options()["tv_weight"] == "auto"
    assert not widget._panel.tv_weight.enabled
    widget._panel.tv_auto.value = False  # a fixed λ
    assert widget._panel.tv_weight.enabled
    command = widget.copy_command().split("; do ", 1)[1].removesuffix("; done")
    command = command.replace('"$f"', "in.tif").replace('"${f%.tif}.recon.tif"', "out.tif")
    fixed = build_parser().parse_args(shlex.split(command)[1:]).tv_weight
    assert float(fixed) == widget._panel.tv_weight.value
    # the command shown follows the settings changed after the copy
    widget._panel.method.value = "wiener"
    assert "--method wiener" in widget._command_text.value == widget.command()
    # and the method's caveat is said where it is chosen (Wiener's scale), for it only
    assert "crosstalk" in widget._panel.caveat.value and _shown(widget._panel.caveat)
    widget._panel.method.value = "admm"
    assert not widget._panel.caveat.value and not _shown(widget._panel.caveat)


# ---------------------------------------------------------------------- masks
def test_mask_widget_shows_a_cached_mask(qtbot, tiny_system, model_file, make_napari_viewer):
    viewer = make_napari_viewer()
    widget = _dock(viewer, MaskWidget)
    _use_model(widget, model_file)
    widget.load_model()
    assert widget._stage.choices == ("demix", "recon")
    widget._stage.value, widget._block.value, widget._gate.value = "recon", "view", "conv2"
    widget._lens.value, widget._channel.value = 5, 1
    assert widget.show_mask() is not None
    qtbot.waitUntil(lambda: len(widget.cache) == 1, timeout=20_000)
    [layer] = [layer for layer in viewer.layers if layer.name.startswith("mask")]
    assert layer.name == "mask recon/view/conv2 lens 5 ch 1"
    model = widget._loaded[1]
    expected = model.coordinate_mask("recon", "view", "conv2", tiny_system.sub_view_size, lens=5)
    np.testing.assert_allclose(layer.data, expected[1].numpy(), atol=1e-6)
    # in µm, over the raw frame's object grid, like every layer the plugin adds
    pixel = tiny_system.object_pixel_um
    assert tuple(layer.translate) == tuple(pixel * t for t in object_translate(tiny_system))
    assert tuple(layer.scale) == (pixel, pixel)
    np.testing.assert_allclose(layer.contrast_limits, (layer.data.min(), layer.data.max()))
    assert "reconstruction network" in widget._stage.tooltip
    assert widget._block.tooltip.startswith("view: ") and "lens-specific" in widget._block.tooltip
    assert "3×3 depth-wise" in widget._gate.tooltip

    viewer.layers.remove(layer)
    assert widget.show_mask() is None  # served from the cache, no worker
    assert len(widget.cache) == 1 and layer.name in viewer.layers
    widget._stage.value, widget._block.value = "demix", "enc0.0"
    assert widget._block.tooltip == "enc0.0: encoder level 0 (features at 1/1 of the tile " \
                                    "size), block 0"


def test_a_failure_inside_a_worker_is_one_notice(qtbot, monkeypatch, tmp_path, tiny_system,
                                                model_file, make_napari_viewer, errors):
    """The work raises in the worker thread: one notice of ours, none from napari's
    task-status handler, and the widget stays usable."""
    from napari.utils.notifications import notification_manager

    from napari_svcode.widgets import simulate as simulate_module

    raised = []
    notification_manager.notification_ready.connect(raised.append)
    viewer = make_napari_viewer()

    model = _slow_model(monkeypatch, model_file, tiny_system, 0.0)

    def fail(calls: int) -> None:
        raise RuntimeError("CUDA out of memory (simulated)")

    model.hook = fail
    _, widget = _stack_in_widget(viewer, tiny_system, model_file, 2)
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    assert len(errors) == 1 and "CUDA out of memory (simulated)" in errors[0]
    assert widget._run.enabled and widget.frames_done == 0

    class Broken:
        def simulate(self, *args, **kwargs):
            raise MemoryError("cannot allocate 6.00 GiB (simulated)")

    monkeypatch.setattr(simulate_module, "simulator", lambda system, departures: Broken())
    simulate = _dock(viewer, SimulateWidget)
    viewer.add_image(np.ones((70, 90)), name="cells")
    simulate._layer.value = viewer.layers["cells"]
    simulate._system_choice.source.value = simulate._system_choice.FROM_FILE
    simulate._system_choice.path.value = tiny_system.save(tmp_path / "system.json")
    assert simulate.start() is not None
    qtbot.waitUntil(lambda: simulate._run.enabled, timeout=20_000)
    assert len(errors) == 2 and "6.00 GiB" in errors[1]
    qtbot.wait(200)
    assert not [n for n in raised if "Traceback" in str(n.message) or
                getattr(n, "exception", None) is not None], raised
    notification_manager.notification_ready.disconnect(raised.append)


# ------------------------------------------------------------------- simulate
def test_reconstruction_lands_on_its_raw_frame_in_micrometres(qtbot, tiny_system, model_file,
                                                             make_napari_viewer):
    """Over a raw stack in µm (the system's 10 µm pixels, moved 3 frames and 5, 7 pixels),
    the reconstruction and the demixed views take its scale, units and origin."""
    from napari_svcode._layers import placement

    viewer = make_napari_viewer()
    stack = _raw_stack(tiny_system, 2)
    viewer.add_image(stack, name="raw", metadata=layer_metadata(tiny_system, "measurement"),
                     **placement(tiny_system, 3, origin=(5, 7), lead=(3,)))
    widget = _dock(viewer, ReconstructWidget)
    _use_model(widget, model_file)
    widget._views.value = True
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=30_000)
    recon, views = viewer.layers["reconstruction"], viewer.layers["demixed views"]
    origin = 10 * (np.asarray(object_translate(tiny_system)) + (5, 7))
    assert tuple(recon.scale) == (1, 10, 10) and tuple(views.scale) == (1, 1, 10, 10)
    assert tuple(recon.translate) == (3, *origin) and tuple(views.translate) == (0, 3, *origin)
    assert [str(unit) for unit in recon.units] == ["pixel", "micrometer", "micrometer"]
    assert viewer.canvas.overlays.scale_bar.visible


def test_simulate_widget_makes_a_raw_frame(qtbot, tmp_path, tiny_system, make_napari_viewer):
    viewer = make_napari_viewer()
    viewer.add_image(np.random.default_rng(2).random((70, 90)), name="cells")
    widget = _dock(viewer, SimulateWidget)
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = tiny_system.save(tmp_path / "system.json")
    assert widget.start() is not None
    qtbot.waitUntil(lambda: "cells (simulated raw)" in viewer.layers, timeout=20_000)
    layer = viewer.layers["cells (simulated raw)"]
    assert layer.data.shape == tiny_system.sensor_shape and layer.data.max() > 0
    assert layer.metadata[SYSTEM_KEY] == tiny_system
    assert tuple(layer.scale) == (10, 10) and str(layer.units[-1]) == "micrometer"


def test_simulate_through_a_departed_instrument(qtbot, tmp_path, tiny_system,
                                                make_napari_viewer):
    """The instrument choice simulates through a named set of departures, as svcode
    simulate --departures: another frame of the same object, recorded with the nominal
    system, equal to the core's."""
    from svcode_core.phantoms import from_image
    from svcode_core.physics.simulate import Simulator

    viewer = make_napari_viewer()
    image = np.random.default_rng(3).random((64, 64))
    viewer.add_image(image, name="photo")
    widget = _dock(viewer, SimulateWidget)
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = tiny_system.save(tmp_path / "system.json")
    widget._noise.value, widget._peak.value = False, 0.5
    frames = {}
    for name in ("none", "calibration"):
        widget._departures.value = name
        assert widget.start() is not None
        qtbot.waitUntil(lambda: widget._run.enabled and viewer.layers[-1].name.startswith(
            "photo (simulated raw)") and len(viewer.layers) == 1 + 2 * (len(frames) + 1),
            timeout=20_000)
        frames[name] = viewer.layers[-1]
    assert all(layer.metadata[SYSTEM_KEY] == tiny_system for layer in frames.values())
    obj = from_image(image, tiny_system.sub_view_size) * np.float32(0.5)
    expected = Simulator(tiny_system, departures="calibration").simulate(obj, noise=False)
    np.testing.assert_allclose(frames["calibration"].data, expected.measurement, atol=1e-6)
    assert np.abs(frames["calibration"].data - frames["none"].data).max() > 1e-3


def test_simulate_brightness_saturation_truth_and_the_reconstruct_choosers(
        qtbot, tmp_path, tiny_system, make_napari_viewer, warnings):
    """A bright object warns that the frame saturates, a lower peak does not; the truth
    comes as a layer of the raw frame's scene, and the Reconstruct widget moves from a
    plain 512×512 image to the raw frame that fits its system and scores against it."""
    viewer = make_napari_viewer()
    viewer.add_image(np.random.default_rng(2).random((512, 512)), name="photo")
    reconstruct = _dock(viewer, ReconstructWidget)
    assert reconstruct._layer.value.name == "photo" and reconstruct._truth.value is None
    widget = _dock(viewer, SimulateWidget)
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = tiny_system.save(tmp_path / "system.json")
    assert widget._peak.value == 1.0
    assert widget.start() is not None
    qtbot.waitUntil(lambda: "photo (simulated raw)" in viewer.layers, timeout=20_000)
    raw, truth = viewer.layers["photo (simulated raw)"], viewer.layers["photo (simulated truth)"]
    assert len(warnings) == 1 and "% of the simulated frame's pixels are saturated" in warnings[0]
    assert "lower the object peak" in warnings[0]
    size = tiny_system.sub_view_size
    assert truth.data.shape == (size, size) and not truth.visible
    assert np.isclose(truth.data.max(), 1.0)
    assert tuple(truth.translate) == tuple(10 * t for t in object_translate(tiny_system))
    assert truth.metadata["svcode_scene"] == raw.metadata["svcode_scene"]
    assert truth.metadata["svcode_kind"] == "object"
    assert reconstruct._layer.value is raw and reconstruct._truth.value is truth
    # the photo, in pixels, now covers the truth's field in the same units
    photo = viewer.layers["photo"]
    np.testing.assert_allclose(photo.scale, np.asarray(truth.scale) * size / 512)
    for layer, count in ((photo, 512), (truth, size)):  # the outer pixel edges
        low = np.asarray(layer.translate) - np.asarray(layer.scale) / 2
        np.testing.assert_allclose(low + count * np.asarray(layer.scale),
                                   np.asarray(truth.translate) + (size - 0.5) * truth.scale)
        np.testing.assert_allclose(low, np.asarray(truth.translate) - np.asarray(truth.scale) / 2)
    if LAYER_UNITS:
        assert tuple(photo.units) == tuple(truth.units)

    widget._peak.value = 0.3  # dimmer: no saturation, a truth of that peak, another scene
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled and len(viewer.layers) == 5, timeout=20_000)
    assert len(warnings) == 1
    dim = viewer.layers[-2]
    assert np.isclose(dim.data.max(), 0.3)
    assert dim.metadata["svcode_scene"] != truth.metadata["svcode_scene"]

    reconstruct._panel.method.value = "wiener"  # scored against the frame's own truth
    assert reconstruct.start() is not None
    _wait_done(qtbot, reconstruct)
    [entry] = reconstruct.results
    assert "psnr" in entry and "PSNR" in reconstruct._results.value


def test_simulate_widget_announces_or_refuses_a_large_simulation(
    qtbot, tmp_path, tiny_system, make_napari_viewer, monkeypatch
):
    from napari_svcode.widgets import simulate as module

    viewer = make_napari_viewer()
    viewer.add_image(np.random.default_rng(2).random((70, 90)), name="cells")
    widget = _dock(viewer, SimulateWidget)
    widget._system_choice.source.value = widget._system_choice.FROM_FILE
    widget._system_choice.path.value = tiny_system.save(tmp_path / "system.json")
    warnings, errors = [], []
    monkeypatch.setattr(module, "show_warning", warnings.append)
    monkeypatch.setattr(module, "notify_error", lambda *args: errors.append(args))
    monkeypatch.setattr(module, "_available_memory", lambda: 1)  # 1 byte: refused
    assert widget.start() is None and "GiB" in errors[0][0] and not warnings
    monkeypatch.setattr(module, "_available_memory", lambda: None)
    monkeypatch.setattr(module, "LARGE_MEMORY", 0)  # everything is large: announced, run
    worker = widget.start()
    assert worker is not None and "GiB of memory" in warnings[0] and "K = " in warnings[0]
    qtbot.waitUntil(lambda: "cells (simulated raw)" in viewer.layers, timeout=20_000)


# ----------------------------------------------------------------- screenshot
def test_screenshot_raw_frame_boxes_and_reconstruction(make_model_file, qtbot, tmp_path,
                                                       make_napari_viewer):
    """The README picture: cm2-mini vessels sample, its sub-views and a reconstruction
    (written to docs/images/napari.png with ``SVCODE_UPDATE_SCREENSHOT=1``)."""
    from napari_svcode._resources import bundled_model

    system = SystemConfig.preset("cm2-mini")
    viewer = make_napari_viewer(show=True)
    viewer.window.resize(1200, 800)
    viewer.open_sample("napari-svcode", "vessels")
    _, calibration = viewer.window.add_plugin_dock_widget("napari-svcode", "Calibration")
    assert isinstance(calibration, CalibrationWidget)  # the manifest's widget, given the viewer
    calibration._layer.value = viewer.layers["vessels raw"]
    calibration.show_sub_views()
    _, widget = viewer.window.add_plugin_dock_widget("napari-svcode", "Reconstruct")
    weights = bundled_model(system.name)
    if weights is None:  # until a trained model ships: a random one, one tile a frame
        weights = make_model_file(tmp_path / "mini.safetensors", system)
        widget._panel.tile.value = system.sub_view_size
    _use_model(widget, weights)
    widget._layer.value = viewer.layers["vessels raw"]
    assert widget.start() is not None
    qtbot.waitUntil(lambda: widget._run.enabled, timeout=120_000)
    recon = viewer.layers["reconstruction"]
    recon.blending, recon.opacity = "additive", 0.8
    viewer.layers.selection.active = viewer.layers["sub-views"]
    _screenshot(qtbot, viewer, "napari.png", tmp_path)


def _screenshot(qtbot, viewer, name: str, tmp_path: Path) -> np.ndarray:
    """Screenshot of the window; written to docs/images/``name`` only with
    ``SVCODE_UPDATE_SCREENSHOT=1``, so a test run leaves the tree clean."""
    from skimage.io import imsave

    viewer.reset_view()
    qtbot.wait(300)
    image = viewer.screenshot(canvas_only=False, flash=False)
    assert image.ndim == 3 and image.shape[0] > 400
    assert image[..., :3].std() > 20, "screenshot looks blank"
    target = IMAGES / name if os.environ.get("SVCODE_UPDATE_SCREENSHOT") else tmp_path / name
    imsave(target, image[..., :3], check_contrast=False)
    return image


def test_screenshot_compare_view(qtbot, tmp_path, make_napari_viewer):
    """The README's compare picture: SV-CoDe and LSV-ADMM on the vessels sample, side by
    side with the ground truth, quality and seconds in the widget."""
    viewer = make_napari_viewer(show=True)
    viewer.window.resize(1400, 820)
    viewer.open_sample("napari-svcode", "vessels")
    _, widget = viewer.window.add_plugin_dock_widget("napari-svcode", "Reconstruct")
    widget._compare.value = True
    widget._second.method.value = "admm"
    widget._second.iterations.value = COMPARE_ADMM_ITERATIONS
    assert widget.start() is not None
    _wait_done(qtbot, widget, 600_000)
    assert len(widget.results) == 2 and all("psnr" in entry for entry in widget.results)
    grid = [layer.name for layer in viewer.layers if layer.visible]
    assert grid[0] == "vessels ground truth" and grid[1].startswith("A: SV-CoDe")
    assert grid[2].startswith(f"B: LSV-ADMM (TV), {COMPARE_ADMM_ITERATIONS} iterations")
    _screenshot(qtbot, viewer, "napari-compare.png", tmp_path)


def test_screenshot_calibration_overlay(qtbot, tmp_path, make_napari_viewer):
    """The README's calibration picture: labelled chief rays and the box of one lens."""
    viewer = make_napari_viewer(show=True)
    viewer.window.resize(1200, 800)
    viewer.open_sample("napari-svcode", "vessels")
    _, widget = viewer.window.add_plugin_dock_widget("napari-svcode", "Calibration")
    assert widget._layer.value is viewer.layers["vessels raw"]
    widget.show_sub_views()
    widget._lens.value = 1
    assert len(viewer.layers["sub-views"].data) == 1
    _screenshot(qtbot, viewer, "napari-calibration.png", tmp_path)


def test_frames_the_core_would_warn_about_are_named_before_the_run(
        qtbot, monkeypatch, tiny_system, make_napari_viewer, make_model_file, tmp_path,
        warnings):
    """12-bit counts in 16-bit words and a blank frame: the same words as the command
    line, each a notice of two lines (problem, what to do) and the whole message on expand;
    the first press is held (the output would be 16x too dim), a second runs anyway, and
    the 12-bit notice's button sets the full scale to 4095."""
    toasts = []
    monkeypatch.setattr(plugin_errors, "dispatch", toasts.append)
    viewer = make_napari_viewer()
    stack = (_raw_stack(tiny_system, 2) * 4000).astype(np.uint16)
    stack[1] = 0
    viewer.add_image(stack, name="raw", metadata=layer_metadata(tiny_system, "measurement"))
    widget = _dock(viewer, ReconstructWidget)
    path = make_model_file(tmp_path / "tiny.safetensors", tiny_system)
    _use_model(widget, path)
    assert widget.start() is None and widget._run.text == "Reconstruct anyway"
    assert "full scale" in widget._status.value
    worker = widget.start()
    assert worker is not None
    _wait_done(qtbot, widget)
    del toasts[: len(toasts) // 2]  # the first press's notices: the second gives them again
    messages = warnings + [toast.message for toast in toasts]
    causes = [message.split("\n")[0] for message in messages]
    assert any("at most 12 bits" in cause for cause in causes), causes
    assert any("blank frames" in cause for cause in causes), causes
    assert all(message.split("\n")[1].startswith("→ ") for message in messages)

    (bits,) = toasts
    ((label, press),) = bits.actions
    assert "at most 12 bits" in bits.message and label == "Use 4095"
    press(None)
    assert widget._full_scale.value == 4095.0
    assert "--input-scale 4095" in widget.command()
    worker = widget.start()
    assert worker is not None
    _wait_done(qtbot, widget)
    assert len(toasts) == 1  # no 12-bit notice with the full scale set
    rec = Reconstructor.from_weights(path, tiny_system)
    expected = rec(stack[0].astype(np.float32) / 4095.0).reconstruction
    np.testing.assert_allclose(viewer.layers["reconstruction"].data[0], expected, atol=1e-5)


def test_lsv_admm_shows_its_iterations_and_a_cancel_keeps_the_frames_done(
        qtbot, monkeypatch, tiny_system, make_napari_viewer):
    """LSV-ADMM fills the bar iteration by iteration (determinate, with the time left at the
    pace so far); a cancel at iteration 5 of frame 2 runs no further iteration and keeps
    frame 1 only."""
    import napari_svcode.widgets.reconstruct as module
    from svcode_core.methods.baselines.admm import LsvAdmm

    viewer = make_napari_viewer()
    stack = _raw_stack(tiny_system, 3)
    viewer.add_image(stack, name="raw", metadata=layer_metadata(tiny_system, "measurement"))
    viewer.dims.set_current_step(0, 0)
    widget = _dock(viewer, ReconstructWidget)
    widget._panel.method.value = "admm"
    widget._panel.iterations.value = 40
    starts: list[int] = []
    ran: list[tuple[int, int]] = []  # (frame, iteration), recorded in the worker
    solve = LsvAdmm.iter_solve

    def watched(self, *args):
        frame = len(starts)
        starts.append(frame)

        def hook(iteration, estimate):
            ran.append((frame, iteration))
            if (frame, iteration) == (1, 5):
                widget.worker.quit()  # as Cancel does, from the worker: mid-frame for sure

        return solve(self, *args, callback=hook)

    monkeypatch.setattr(LsvAdmm, "iter_solve", watched)
    shown: list[tuple[str, int, int]] = []  # status, bar maximum, bar value
    set_progress = widget._set_progress

    def spy(*args, **kwargs) -> None:
        set_progress(*args, **kwargs)
        shown.append((args[3], widget._progress.native.maximum(), widget._progress.value))

    widget._set_progress = spy
    assert widget.start() is not None
    _wait_done(qtbot, widget)
    within = [(top, value) for text, top, value in shown if "frame 1 of 3, iteration" in text]
    assert within and all(top == 3 * STEPS for top, _ in within)  # determinate
    assert any(0 < value < STEPS for _, value in within)  # part of a frame
    assert any("frame 2 of 3, iteration 5/40" in text for text, _, _ in shown)
    assert starts == [0, 1] and max(i for f, i in ran if f == 1) == 5
    assert widget.frames_done == 1 and widget._progress.value == STEPS
    assert widget._status.value.startswith("Cancelled") and "1 of 3" in widget._status.value
    recon = viewer.layers["reconstruction"]
    expected = widget._state["jobs"][0].build().reconstruct(stack[0]).reconstruction
    np.testing.assert_array_equal(recon.data, expected[None])
    # the time left: the frames still to do at the pace since the job's first report
    times = [10.0, 12.0]
    with monkeypatch.context() as patch:
        patch.setattr(module.time, "perf_counter", lambda: times.pop(0) if times else 12.0)
        widget._state.update(count=4)
        widget._state.pop("pace", None)
        assert widget._time_left(1.0) == ""
        assert widget._time_left(2.0) == ", about 4 s left"


def test_calibration_undo_reset_and_the_offsets_of_moved_rays(tiny_system, make_napari_viewer,
                                                              errors):
    viewer = make_napari_viewer()
    viewer.add_image(_raw_stack(tiny_system, 1)[0], name="raw",
                     metadata={SYSTEM_KEY: tiny_system})
    widget = _dock(viewer, CalibrationWidget)
    widget.show_sub_views()
    rays, pad = viewer.layers["chief rays"], np.asarray(tiny_system.padding)
    assert widget._offsets.value == "no ray moved"
    assert not widget._undo.enabled and not widget._reset.enabled

    _drag(rays, 3, (1.0, -2.0))  # one drag, two moves: one step to undo
    pixel = tiny_system.object_pixel_um
    assert widget._offsets.value == (f"lens 3: (+1.0, \u22122.0) px, "
                                     f"(+{pixel:.1f}, \u2212{2 * pixel:.1f}) µm")
    assert widget._undo.enabled and widget._reset.enabled
    widget._undo.clicked.emit()
    assert widget.system.chief_rays == tiny_system.chief_rays
    np.testing.assert_allclose(rays.data, np.asarray(tiny_system.chief_rays) - pad)
    assert widget._offsets.value == "no ray moved" and not widget._undo.enabled

    _drag(rays, 0, (2.0, 1.0))
    _drag(rays, 8, (-1.0, 3.0))
    assert widget._offsets.value.splitlines()[0].startswith("lens 0: (+2.0, +1.0) px")
    assert widget._offsets.value.splitlines()[1].startswith("lens 8: (\u22121.0, +3.0) px")
    widget.undo()  # one level: lens 8 back, lens 0 still moved
    assert widget._offsets.value.startswith("lens 0:") and "lens 8" not in widget._offsets.value
    _drag(rays, 8, (-1.0, 3.0))
    widget._reset.clicked.emit()
    assert widget.system.chief_rays == tiny_system.chief_rays
    np.testing.assert_allclose(rays.data, np.asarray(tiny_system.chief_rays) - pad)
    assert widget._offsets.value == "no ray moved" and not widget._reset.enabled
    assert viewer.layers["raw"].metadata[SYSTEM_KEY] == tiny_system and not errors
