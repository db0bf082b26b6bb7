"""Calibration dock widget: chief rays over the raw frame and one sub-view box, editable;
a calibration from a point-source scan and a self-registration from the raw frame, each
run in a worker thread."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import napari
import numpy as np
from magicgui.widgets import (
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    ProgressBar,
    PushButton,
    SpinBox,
    TextEdit,
)
from napari.qt.threading import FunctionWorker, thread_worker
from napari.utils.notifications import show_info
from qtpy.QtCore import QObject, Qt, Signal
from qtpy.QtGui import QFontDatabase

from svcode_core.config import ConfigError, SystemConfig
from svcode_core.evaluation.figures import calibration_figure, psf_montage
from svcode_core.methods.baselines.self_registration import (
    REGISTRATION_FRAMES,
    RegistrationRejected,
    register_recording,
)
from svcode_core.physics.calibration import (
    Calibration,
    CalibrationError,
    calibrate,
    psf_fwhm,
    read_positions,
    report_text,
    save_calibration,
)
from svcode_core.physics.registration import Registration

from .._errors import notify_warning
from .._layers import (
    SYSTEM_KEY,
    chief_rays_from_boxes,
    in_micrometres,
    layer_metadata,
    notify_error,
    place_layer,
    placement,
    placement_over,
    show_scale_bar,
    sub_view_boxes,
)
from .._workers import Failed, returning_failure
from ._choosers import LayerOrFile, SystemChooser, image_layer_box, raw_frame_fit, scan_fit

__all__ = ["CalibrationWidget"]

BOXES = "sub-views"
RAYS = "chief rays"
SPOTS = "spots"
PSF_GRID = "calibrated PSFs"
FWHM_MAP = "PSF FWHM"
#: the spots layer: measured centroids and those the fitted chief rays predict
SPOT_STYLE = {"measured": ("disc", "#00e5ff"), "predicted": ("cross", "#ff4fd8")}
#: progress-bar steps of a calibration
STEPS = 100
LENS_COLOURS = ["#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231",
                "#911eb4", "#42d4f4", "#f032e6", "#bfef45"]


class _ProgressRelay(QObject):
    """Carries the calibration's progress from its thread to the widget (queued signal)."""

    progress = Signal(str, float)


class _Cancelled(Exception):
    """Raised in the worker thread, at its next progress report, after *Cancel*."""


class CalibrationWidget(Container):
    """Check and nudge the nine chief rays of a raw CM² frame, or calibrate them (and the
    PSFs) from a point-source scan, then save the system.

    *Show sub-views* applies the chosen system to the raw layer and draws a Points layer
    ``"chief rays"`` (one point per lens, labelled ``lens ℓ`` beside it) and a Shapes layer
    ``"sub-views"`` with the ``S × S`` box of one lens at a time (the *lens* box, or the
    ray last clicked or moved), both placed like the raw layer. Applying a system with a
    pixel size puts the raw layer in object-space µm (scale, units, scale bar). Dragging a
    ray moves its box, dragging the box moves its ray; either updates the system, and
    *Save* writes it to a ``system.json``. *Undo* takes back the last move (one drag at a
    time, several levels), *Reset* restores the chief rays of the system as drawn, and a
    line below them gives each moved ray's offset from there (pixels, and µm when the
    system has a pixel size).

    *Calibrate from a scan*: a scan (a layer or a TIFF file of ``N × H × W`` raw frames),
    its positions CSV (:func:`~svcode_core.physics.calibration.read_positions`: object
    pixels ``row,col``, or stage micrometres ``x_um,y_um`` scaled by the *pixel size*,
    default the system's), an optional dark frame or stack and the low-rank tolerance.
    *Calibrate* runs
    :func:`~svcode_core.physics.calibration.calibrate` in a worker thread with the chosen system
    as the nominal one (progress below the button; *Cancel* stops at the next frame or
    lens). The calibrated system is applied to the raw layer (the scan itself when no
    raw frame of that sensor is open; a scan read from a file is added as a layer), its
    chief rays are drawn, a ``"spots"`` layer shows the measured spot centroids and those
    the fit predicts for one frame, and the report is shown (with the PSF FWHM per field
    point in pixels and µm). *Show PSF grid* adds the fitted PSFs and, over them, a map of
    their FWHM (one cell per PSF, in µm when the pixel size is known). *Save calibration* writes
    the folder of :func:`~svcode_core.physics.calibration.save_calibration` (``system.json`` with
    its PSF stack) and gives the raw layer that saved system.

    *Self-register*: estimates a small drift of the lens array from the raw layer itself
    (the mean of its first frames;
    :func:`~svcode_core.methods.baselines.self_registration.register_recording`) in a
    worker, with the same progress and *Cancel*; writes the moved system (its PSFs beside
    it) and ``registration.json`` into the chosen folder, applies it to the raw layer and
    redraws the chief rays. A registration no rigid lens array explains (the scene misled
    it) is refused with a notice and changes nothing.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "raw layer", fit=raw_frame_fit)
        self._system_choice = SystemChooser()
        self._show = PushButton(text="Show sub-views")
        self._lens = SpinBox(label="lens", min=0, max=8, value=4,
                             tooltip="the lens whose sub-view box is drawn (0–8, row by row); "
                                     "clicking a chief ray chooses it too")
        self._undo = PushButton(text="Undo", enabled=False,
                                tooltip="put the chief rays back as they were before the last move")
        self._reset = PushButton(text="Reset", enabled=False,
                                 tooltip="put every chief ray back where the system drawn has it")
        self._offsets = Label(value="no ray moved")
        self._out = FileEdit(label="save to", mode="w", filter="*.json", value="system.json")
        self._save = PushButton(text="Save system.json")
        self._scan_title = Label(value="<b>Calibrate from a scan</b>")
        self._scan = LayerOrFile(napari_viewer, "scan", fit=scan_fit,
                                 tooltip="raw frames N×H×W, one per point-source position")
        self._positions = FileEdit(label="positions", mode="r", filter="*.csv",
                                   tooltip="CSV: a header line, then the source position of "
                                           "each frame: row,col in pixels of the S×S object "
                                           "grid (fractions allowed), or x_um,y_um in "
                                           "micrometres from the field's centre (scaled by "
                                           "the pixel size below)")
        self._pixel_size = FloatSpinBox(
            label="pixel size (µm)", min=0.0, max=1e4, step=0.01, value=0.0,
            tooltip="object-space pixel size in micrometres (sensor pixel over "
                    "magnification), for positions in x_um,y_um")
        self._pixel_size.native.setDecimals(4)
        self._pixel_size.native.setSpecialValueText("the system's")
        self._dark = LayerOrFile(napari_viewer, "dark",
                                 tooltip="optional: a frame (H×W) or frames (M×H×W, "
                                         "averaged) with the source off")
        self._tolerance = FloatSpinBox(label="tolerance", min=0.0, max=0.5, step=1e-3, value=0.0,
                                       tooltip="low-rank tolerance: the PSF energy fraction "
                                               "the operator may leave out (e.g. 0.001)")
        self._tolerance.native.setDecimals(5)
        self._tolerance.native.setSpecialValueText("the system's")
        self._calibrate = PushButton(text="Calibrate")
        self._cancel = PushButton(text="Cancel", enabled=False)
        self._progress = ProgressBar(min=0, max=STEPS, value=0, label="progress")
        self._status = Label(value="")
        self._spot_frame = SpinBox(label="spots of frame", min=0, max=0, value=0,
                                   tooltip="the scan frame whose measured and predicted spot "
                                           "centroids the 'spots' layer shows")
        self._report = TextEdit(value="", visible=False)
        self._report.read_only = True
        self._report.native.setLineWrapMode(self._report.native.LineWrapMode.NoWrap)
        self._report.native.setFont(QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont))
        self._show_psfs = PushButton(
            text="Show PSF grid", enabled=False,
            tooltip="add the calibrated PSFs as a layer: one square per lens (row by row), "
                    "its field points inside")
        self._folder = FileEdit(label="save calibration to", mode="d", value="calibration")
        self._save_calibration = PushButton(text="Save calibration", enabled=False)
        self._register_title = Label(value="<b>Self-register from the raw frame</b>")
        self._register_folder = FileEdit(
            label="save registration to", mode="d", value="registration",
            tooltip="receives system.json (the moved chief rays), psfs.tif and "
                    "registration.json (the lens offsets found)")
        self._register = PushButton(
            text="Self-register",
            tooltip="estimate a drift of the lens array (up to a pixel or two) from the raw "
                    f"layer: the mean of its first {REGISTRATION_FRAMES} frames, about "
                    "two minutes on cm2-mini")
        super().__init__(widgets=[
            self._layer, self._system_choice, self._show, self._lens,
            Container(layout="horizontal", labels=False, widgets=[self._undo, self._reset]),
            self._offsets, self._out, self._save,
            self._scan_title, self._scan, self._positions, self._pixel_size, self._dark,
            self._tolerance,
            self._calibrate, self._cancel, self._progress, self._status, self._spot_frame,
            self._report, self._show_psfs, self._folder, self._save_calibration,
            self._register_title, self._register_folder, self._register,
        ])
        self._show.changed.connect(self.show_sub_views)
        self._save.changed.connect(self.save)
        self._lens.changed.connect(self._draw_box)
        self._undo.changed.connect(self.undo)
        self._reset.changed.connect(self.reset)
        self._calibrate.changed.connect(self.start_calibration)
        self._cancel.changed.connect(self.cancel)
        self._spot_frame.changed.connect(self._draw_spots)
        self._save_calibration.changed.connect(self.save_calibration)
        self._show_psfs.changed.connect(self.show_psf_grid)
        self._register.changed.connect(self.start_registration)
        self._relay = _ProgressRelay()
        self._relay.progress.connect(self._on_progress, Qt.ConnectionType.QueuedConnection)
        self.system: SystemConfig | None = None
        self.calibration: Calibration | None = None
        self.registration: Registration | None = None
        self._calibrated_from: dict[str, Any] = {}  # the nominal system and the frames
        self.worker: FunctionWorker | None = None
        self._raw: napari.layers.Image | None = None
        self._updating = False
        self._drawn_rays: tuple = ()  # the chief rays of the system as drawn
        self._history: list[tuple] = []  # the chief rays before each move, for *Undo*
        self._drag: Any = None  # the drag (its press) the last move belonged to
        self._press: object | None = None  # the mouse press on the rays going on
        self._run: dict[str, Any] = {}

    def show_sub_views(self) -> None:
        """Apply the chosen system to the raw layer and draw its chief rays and one box."""
        chosen = self._raw_layer_and_system(keep_current=False)
        if chosen is not None:
            self._raw = chosen[0]
            self._apply(chosen[1])
            self._draw()

    def _raw_layer_and_system(
        self, keep_current: bool
    ) -> tuple[napari.layers.Image, SystemConfig] | None:
        """The raw layer and its system (the chosen one, or with ``keep_current`` the one
        already applied to that layer); ``None`` after a notice if either is missing or
        they do not fit."""
        layer = self._layer.value
        if layer is None:
            notify_error("No raw image layer.", "open a raw CM² frame first (File ▸ Open)")
            return None
        current = self.system if keep_current and self._raw is layer else None
        try:
            system = current or self._system_choice.system(layer.metadata)
        except (ConfigError, FileNotFoundError) as err:
            notify_error(err, "fix the system.json, or choose a preset")
            return None
        if system is None:
            notify_error(f"Layer {layer.name!r} has no system configuration.",
                         "choose a preset or a system.json file above")
            return None
        if tuple(layer.data.shape[-2:]) != tuple(system.sensor_shape):
            notify_error(
                f"Layer {layer.name!r} is {layer.data.shape[-2]}×{layer.data.shape[-1]} "
                f"pixels but system {system.name!r} has a {system.sensor_shape[0]}×"
                f"{system.sensor_shape[1]} sensor.",
                "choose the system of the instrument that recorded this frame",
            )
            return None
        return layer, system

    def _apply(self, system: SystemConfig) -> None:
        self.system = system
        self._raw.metadata = {**self._raw.metadata, SYSTEM_KEY: system}
        place_layer(self._raw, system)
        if in_micrometres(self._raw):
            show_scale_bar(self._viewer)

    # ---------------------------------------------------------------- drawing
    def _draw(self) -> None:
        layers, system = self._viewer.layers, self.system
        for name in (BOXES, RAYS):
            if name in layers:
                layers.remove(name)
        place = placement_over(self._raw)
        size = max(8, system.sub_view_size // 24)
        boxes = self._viewer.add_shapes(
            [self._box(self._lens.value)], shape_type="rectangle", name=BOXES,
            edge_color=LENS_COLOURS[self._lens.value], face_color="transparent",
            edge_width=2, **place,
        )
        rays = self._viewer.add_points(
            self._ray_positions(), name=RAYS, features={"lens": np.arange(9)},
            face_color=LENS_COLOURS, border_color="white", size=size, **place,
            text={"string": "lens {lens}", "color": "white", "size": 10,
                  "anchor": "center", "translation": [-1.2 * size, 0]},
        )
        boxes.events.data.connect(self._on_box_moved)
        rays.events.data.connect(self._on_rays_moved)
        rays.mouse_drag_callbacks.append(self._track_press)
        rays.selected_data.events.items_changed.connect(self._on_ray_selected)
        rays.mode = "select"
        layers.selection.active = rays
        self._drawn_rays, self._history, self._drag = system.chief_rays, [], None
        self._show_offsets()

    def _box(self, lens: int) -> np.ndarray:
        return sub_view_boxes(self.system)[lens]

    def _draw_box(self, *_: Any) -> None:
        """Show the box of the chosen lens."""
        layers = self._viewer.layers
        if self.system is None or BOXES not in layers:
            return
        boxes = layers[BOXES]
        self._updating = True
        try:
            boxes.data = [self._box(self._lens.value)]
            boxes.shape_type = ["rectangle"]
            boxes.edge_color = [LENS_COLOURS[self._lens.value]]
        finally:
            self._updating = False

    def _ray_positions(self) -> np.ndarray:
        return np.asarray(self.system.chief_rays, dtype=float) - np.asarray(self.system.padding)

    # ---------------------------------------------------------------- editing
    def _set_rays(self, rays: tuple, lens: int, redraw_rays: bool, drag: Any = None) -> None:
        """Apply moved chief rays and show lens ``lens``'s box; redraw the rays when they
        were moved through the box, or were refused (a ray being dragged is left alone).
        The rays before are kept for *Undo*, once per ``drag`` (its press; ``None``: once)."""
        before = self.system.chief_rays
        try:
            self._apply(self.system.replace(chief_rays=rays))
        except ConfigError as err:
            notify_error(err, "keep each chief ray inside the padded sensor frame")
            redraw_rays = True
        else:
            if rays != before and (drag is None or drag is not self._drag):
                self._history.append(before)
                self._drag = drag
        if redraw_rays:
            self._updating = True
            try:
                self._viewer.layers[RAYS].data = self._ray_positions()
            finally:
                self._updating = False
        if self._lens.value != lens:
            self._lens.value = lens  # draws the box
        else:
            self._draw_box()
        self._show_offsets()

    def _on_rays_moved(self, event) -> None:
        if self._updating or event.action != "changed":
            return
        rays = self._viewer.layers[RAYS]
        if len(rays.data) != 9:
            notify_error("The chief-ray layer must keep exactly nine points.",
                         "press 'Show sub-views' to draw them again")
            return
        moved = list(getattr(event, "data_indices", ()) or ())
        lens = int(moved[0]) if len(moved) == 1 and moved[0] >= 0 else self._lens.value
        padding = np.asarray(self.system.padding)
        positions = np.rint(np.asarray(rays.data, dtype=float) + padding).astype(int)
        self._set_rays(tuple((int(row), int(col)) for row, col in positions), lens, False,
                       self._press)

    def _track_press(self, _layer: Any, event: Any) -> Any:
        """A mouse drag callback of the rays: the moves between a press and its release
        are one drag, one step to undo (napari hands the later events in as ``event``)."""
        self._press = object()
        yield
        while event.type == "mouse_move":
            yield
        self._press = None

    def _on_box_moved(self, event) -> None:
        if self._updating or event.action != "changed":
            return
        boxes = self._viewer.layers[BOXES]
        if len(boxes.data) != 1:
            notify_error("The sub-view layer shows one box at a time.",
                         "choose the lens above, or press 'Show sub-views' to draw it again")
            return
        lens = self._lens.value
        all_boxes = sub_view_boxes(self.system)
        all_boxes[lens] = boxes.data[0]
        self._set_rays(chief_rays_from_boxes(all_boxes, self.system), lens, True)

    def undo(self) -> None:
        """Put the chief rays back as they were before the last move."""
        if self._history:
            self._restore(self._history.pop())

    def reset(self) -> None:
        """Put every chief ray back where the system drawn has it (*Undo* takes it back)."""
        if self.system is not None and self.system.chief_rays != self._drawn_rays:
            self._history.append(self.system.chief_rays)
            self._restore(self._drawn_rays)

    def _restore(self, rays: tuple) -> None:
        self._apply(self.system.replace(chief_rays=rays))
        self._drag = None
        if RAYS in self._viewer.layers:
            self._updating = True
            try:
                self._viewer.layers[RAYS].data = self._ray_positions()
            finally:
                self._updating = False
        self._draw_box()
        self._show_offsets()

    def _show_offsets(self) -> None:
        """Each moved ray's offset from the system drawn, in pixels (and µm)."""
        def pair(offset: np.ndarray, unit: str) -> str:
            return f"({offset[0]:+.1f}, {offset[1]:+.1f}) {unit}".replace("-", "−")

        lines = []
        current = self.system.chief_rays if self.system is not None else ()
        pixel = self.system.object_pixel_um if self.system is not None else None
        for lens, (now, drawn) in enumerate(zip(current, self._drawn_rays, strict=False)):
            offset = np.subtract(now, drawn, dtype=float)
            if offset.any():
                text = f"lens {lens}: {pair(offset, 'px')}"
                lines.append(text + (f", {pair(offset * pixel, 'µm')}" if pixel else ""))
        self._offsets.value = "\n".join(lines) or "no ray moved"
        self._undo.enabled = bool(self._history)
        self._reset.enabled = bool(lines)

    def _on_ray_selected(self, *_: Any) -> None:
        selected = self._viewer.layers[RAYS].selected_data
        if len(selected) == 1:
            self._lens.value = int(next(iter(selected)))

    def save(self) -> None:
        """Write the current system (with any moved chief rays) to the chosen JSON file."""
        if self.system is None:
            notify_error("No system to save yet.", "press 'Show sub-views' first")
            return
        try:
            path = self.system.save(self._out.value)
        except OSError as err:
            notify_error(err, "choose a folder you can write to")
            return
        show_info(f"Saved system {self.system.name!r} to {path}")

    # ------------------------------------------------------- scan calibration
    def _read_scan(self) -> dict[str, Any] | None:
        """The scan, positions, dark frame and nominal system; ``None`` after a notice."""
        try:
            scan = self._scan.read()
        except (FileNotFoundError, ValueError) as err:
            notify_error(err, "choose a TIFF file of N×H×W raw frames")
            return None
        if scan is None:
            notify_error("No scan chosen.",
                         "choose a scan layer, or a TIFF file of N×H×W raw frames")
            return None
        frames, metadata, name, layer = scan
        frames = frames[None] if frames.ndim == 2 else frames
        try:
            nominal = self._system_choice.system(metadata)
        except (ConfigError, FileNotFoundError) as err:
            notify_error(err, "fix the system.json, or choose a preset")
            return None
        if nominal is None:
            notify_error(f"Scan {name!r} has no system configuration.",
                         "choose the nominal system (a preset or a system.json) above")
            return None
        if frames.ndim != 3 or tuple(frames.shape[1:]) != tuple(nominal.sensor_shape):
            shape = "×".join(str(n) for n in frames.shape)
            notify_error(f"Scan {name!r} is {shape} pixels but system {nominal.name!r} has a "
                         f"{nominal.sensor_shape[0]}×{nominal.sensor_shape[1]} sensor.",
                         "choose the nominal system of the instrument that recorded the scan")
            return None
        if str(self._positions.value) in ("", "."):
            notify_error("No positions file chosen.",
                         "choose the CSV of the source positions (header row,col or x_um,y_um)")
            return None
        pixel_size = self._pixel_size.value or nominal.object_pixel_um  # 0: the system's
        try:
            positions = read_positions(self._positions.value, pixel_size,
                                       size=nominal.sub_view_size)
        except (CalibrationError, FileNotFoundError, UnicodeDecodeError) as err:
            notify_error(err, "fix the positions file: a header line row,col (object pixels, "
                              "fractions allowed) or x_um,y_um (micrometres; set the pixel "
                              "size), then one line per frame")
            return None
        try:
            dark = self._dark.read()
        except (FileNotFoundError, ValueError) as err:
            notify_error(err, "choose a TIFF file of the dark frame(s), or none")
            return None
        tolerance = self._tolerance.value or None  # 0: the system's
        return dict(frames=frames, name=name, layer=layer, nominal=nominal,
                    positions=positions, dark=None if dark is None else dark[0],
                    tolerance=tolerance)

    def start_calibration(self) -> FunctionWorker | None:
        """Check the inputs and start calibrating in a worker thread (errors become notices).

        Returns ``None`` without running when a check fails.
        """
        run = self._read_scan()
        if run is None:
            return None
        return self._start(
            calibrate, (run["frames"], run["positions"], run["nominal"]),
            dict(dark=run["dark"], tolerance=run["tolerance"]), run,
            f"Calibrating {run['nominal'].name} from {len(run['frames'])} frames…")

    def start_registration(self) -> FunctionWorker | None:
        """Check the raw layer and start self-registering it in a worker thread.

        Returns ``None`` without running when a check fails.
        """
        chosen = self._raw_layer_and_system(keep_current=True)
        if chosen is None:
            return None
        layer, system = chosen
        frames = np.asarray(layer.data[:REGISTRATION_FRAMES] if layer.ndim == 3 else layer.data)
        folder = Path(self._register_folder.value)
        run = {"layer": layer, "nominal": system, "folder": folder}
        return self._start(register_recording, (frames.reshape(-1, *frames.shape[-2:]),
                                                system, folder), {}, run,
                           f"Self-registering {layer.name!r}…")

    def _start(self, work: Any, args: tuple, kwargs: dict, run: dict[str, Any],
               status: str) -> FunctionWorker:
        """Run ``work(*args, progress=..., **kwargs)`` in a worker with progress and cancel."""
        stop = threading.Event()
        relay = self._relay

        def progress(stage: str, fraction: float) -> None:  # in the worker thread
            if stop.is_set():
                raise _Cancelled
            relay.progress.emit(stage, fraction)

        worker = thread_worker(returning_failure, start_thread=False)(
            work, *args, progress=progress, **kwargs)
        worker.returned.connect(self._on_returned)
        worker.finished.connect(self._on_finished)
        self._run = {**run, "stop": stop, "work": work}
        self.worker = worker
        self._calibrate.enabled = self._register.enabled = False
        self._cancel.enabled = True
        self._progress.value = 0
        self._status.value = status
        worker.start()
        return worker

    def cancel(self) -> None:
        """Ask the running calibration or registration to stop at its next step."""
        if self._run:
            self._run["stop"].set()
        self._cancel.enabled = False
        self._status.value = "Cancelling…"

    def _on_progress(self, stage: str, fraction: float) -> None:
        # Widget updates only: never process events from a worker callback.
        if self._cancel.enabled:
            self._progress.value = round(STEPS * fraction)
            self._status.value = f"{self._activity()}: {stage}"

    def _activity(self) -> str:
        return "Calibrating" if self._run.get("work") is calibrate else "Self-registering"

    def _on_returned(self, result: Any) -> None:
        if isinstance(result, Failed):
            self._on_error(result.error)
        elif self._run["work"] is calibrate:
            self._on_calibrated(result)
        else:
            self._on_registered(*result)

    def _on_error(self, err: Exception) -> None:
        what = "Calibration" if self._run["work"] is calibrate else "Self-registration"
        if isinstance(err, _Cancelled):
            self._status.value = f"{what} cancelled."
            show_info(f"{what} cancelled; nothing was changed.")
            return
        self._status.value = f"{what} failed (see the notification)."
        if isinstance(err, RegistrationRejected):
            notify_error(err, "calibrate from a bead scan, or keep the system as it is")
        elif self._run["work"] is calibrate:
            notify_error(err, "check the scan, its positions and the nominal system")
        else:
            notify_error(err, "check the raw frame, its system and the folder")

    def _on_finished(self) -> None:
        self._calibrate.enabled = self._register.enabled = True
        self._cancel.enabled = False

    def _on_registered(self, system: SystemConfig, registration: Registration) -> None:
        """Apply the registered system to the raw layer and redraw its chief rays."""
        self.registration = registration
        self._raw = self._run["layer"]
        self._apply(system)
        self._draw()
        shift, moves = registration.shift, np.linalg.norm(registration.offsets, axis=1)
        self._progress.value = STEPS
        self._status.value = (f"Registered: array shift ({shift[0]:+.2f}, {shift[1]:+.2f}) px, "
                              f"rotation {registration.rotation_deg:+.3f}°, lens offsets up "
                              f"to {moves.max():.2f} px")
        show_info(f"Self-registration saved to {self._run['folder']}: system.json, psfs.tif "
                  "and registration.json.")

    def _on_calibrated(self, calibration: Calibration) -> None:
        """Apply the calibrated system, draw its chief rays and spots, show the report."""
        run = self._run
        self.calibration = calibration
        self._calibrated_from = {"nominal": run["nominal"], "frames": run["frames"]}
        self._raw = self._target_layer(run)
        self._apply(calibration.system)
        self._draw()
        self._spot_frame.max = len(run["frames"]) - 1
        middle = len(run["frames"]) // 2  # the centre of a raster: a spot in every lens
        if self._spot_frame.value == middle:
            self._draw_spots()
        else:
            self._spot_frame.value = middle  # draws the spots
        self._report.value = report_text(calibration, run["nominal"])
        self._report.visible = True
        self._save_calibration.enabled = self._show_psfs.enabled = True
        if PSF_GRID in self._viewer.layers:  # an earlier calibration's
            self.show_psf_grid()
        shift = calibration.array_shift
        self._progress.value = STEPS
        self._status.value = (f"Calibrated: array shift ({shift[0]:+.2f}, {shift[1]:+.2f}) px, "
                              f"rotation {calibration.array_rotation_deg:+.3f}°, "
                              f"K = {max(calibration.ranks)}")

    def _target_layer(self, run: dict[str, Any]) -> napari.layers.Image:
        """The layer to apply the calibration to: the raw layer if it has the scan's sensor
        shape, else the scan's layer; a scan read from a file is added as one."""
        sensor = tuple(run["nominal"].sensor_shape)
        raw = self._layer.value
        if raw is not None and tuple(raw.data.shape[-2:]) == sensor:
            return raw
        if run["layer"] is not None:
            return run["layer"]
        return self._viewer.add_image(run["frames"], name=f"{run['name']} (scan)",
                                      colormap="gray",
                                      metadata=layer_metadata(run["nominal"], "scan"),
                                      **placement(run["nominal"], 3))

    def _draw_spots(self, *_: Any) -> None:
        """Show the measured and predicted spot centroids of the chosen scan frame."""
        if self.calibration is None or self._raw is None:
            return
        frame = self._spot_frame.value
        kinds, lenses, points = [], [], []
        for kind, centroids in (("measured", self.calibration.centroids[frame]),
                                ("predicted", self.calibration.predicted[frame])):
            found = np.flatnonzero(np.isfinite(centroids).all(axis=1))
            kinds += [kind] * len(found)
            lenses += found.tolist()
            points.append(centroids[found])
        layers = self._viewer.layers
        if SPOTS in layers:
            layers.remove(SPOTS)
        size = max(3.0, 3.0 * self.system.optics.airy_radius)
        self._viewer.add_points(
            np.concatenate(points).reshape(-1, 2), name=SPOTS,
            features={"kind": kinds, "lens": lenses},
            symbol=[SPOT_STYLE[kind][0] for kind in kinds],
            face_color=[SPOT_STYLE[kind][1] for kind in kinds], border_width=0,
            size=size, **placement_over(self._raw),
        )
        if self._raw.ndim == 3 and self._raw.data.shape[0] == len(self.calibration.centroids):
            self._viewer.dims.set_point(0, float(self._raw.translate[0]
                                                 + frame * self._raw.scale[0]))
        layers.selection.active = layers[RAYS]

    def show_psf_grid(self) -> napari.layers.Image | None:
        """Add (or refresh) the calibrated PSF grid as the layer ``"calibrated PSFs"``:
        one ``G·k`` square per lens, row by row, shown with gamma 0.5 (faint tails), in
        object-space µm when the system knows its pixel size; over it the layer
        ``"PSF FWHM"``, one cell per PSF centred on it: its FWHM in µm (else pixels)."""
        if self.calibration is None:
            notify_error("No calibration yet.", "press 'Calibrate' first")
            return None
        system, psfs = self.calibration.system, self.calibration.psfs
        grid = psf_montage(psfs)
        fwhm = psf_montage(psf_fwhm(psfs)[..., None, None])  # (3G, 3G)
        pixel = system.object_pixel_um
        if pixel is not None:
            fwhm = fwhm * pixel
        place = placement(system)
        k = psfs.shape[-1]
        cells = {  # each cell spans the k × k pixels of its PSF
            "scale": tuple(k * value for value in place["scale"]),
            "translate": tuple((k - 1) / 2 * value for value in place["scale"]),
            **({"units": place["units"]} if "units" in place else {}),
        }
        low, high = float(np.nanmin(fwhm)), float(np.nanmax(fwhm))
        layers = self._viewer.layers
        for name in (PSF_GRID, FWHM_MAP):
            if name in layers:
                layers.remove(name)
        layer = self._viewer.add_image(grid, name=PSF_GRID, colormap="magma", gamma=0.5,
                                       **place)  # fmt: skip
        self._viewer.add_image(
            np.nan_to_num(fwhm, nan=low), name=FWHM_MAP, colormap="viridis", opacity=0.4,
            blending="additive", contrast_limits=(low, high if high > low else low + 1e-6),
            metadata={"unit": "µm" if pixel is not None else "pixel"}, **cells,
        )
        if in_micrometres(place):
            show_scale_bar(self._viewer)
        if RAYS in layers:
            layers.selection.active = layers[RAYS]
        return layer

    def save_calibration(self) -> dict[str, Path] | None:
        """Write the calibration (``system.json``, its PSF stack, the report) to the chosen
        folder and apply the saved system, which names its PSFs, to the raw layer."""
        calibration = self.calibration
        if calibration is None:
            notify_error("No calibration to save yet.", "press 'Calibrate' first")
            return None
        folder = Path(self._folder.value)
        try:
            files = save_calibration(calibration, folder, self._calibrated_from["nominal"])
            files["figure"] = calibration_figure(folder / "report.png", calibration,
                                                 self._calibrated_from["frames"])
        except OSError as err:
            notify_error(err, "choose a folder you can write to")
            return None
        moved = self.system.chief_rays != calibration.system.chief_rays
        self._apply(SystemConfig.load(files["system"]))
        if moved:
            self._draw()
            notify_warning("Chief rays moved after calibrating: saved the fitted ones.",
                           "use 'Save system.json' to keep moved rays (without the PSFs)")
        show_info(f"Saved the calibration to {folder}: system.json, psfs.tif and the report.")
        return files
