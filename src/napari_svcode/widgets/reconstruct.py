"""Reconstruct dock widget: any method of the core, or two compared, in a worker thread.

The widget checks the input, builds the chosen method's reconstructor through
:mod:`svcode_core.methods`, runs it in a worker thread and adds the results as layers; it
draws its own progress bar and never processes events from inside a worker callback.
"""

from __future__ import annotations

import shlex
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any

import napari
import numpy as np
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    Label,
    ProgressBar,
    PushButton,
    TextEdit,
)
from napari.qt.threading import GeneratorWorker, thread_worker
from napari.utils.notifications import show_info
from qtpy.QtCore import QTimer

from svcode_core.config import SystemConfig, available_presets
from svcode_core.evaluation.metrics import image_quality
from svcode_core.methods import (
    LEARNED_METHODS,
    METHOD_TITLES,
    build_reconstructor,
    cli_arguments,
    iter_method,
    registry,
)
from svcode_core.methods.base import FrameProgress, ReconstructionResult, check_frame_shape
from svcode_core.methods.frames import few_bits_scale, few_bits_warning, frame_warnings

from .._errors import LOG, notify_error, notify_warning
from .._layers import (
    FRAMES_KEY,
    LAYER_UNITS,
    current_index,
    in_micrometres,
    layer_metadata,
    layer_system,
    object_translate,
    placement_over,
    same_scene,
    show_scale_bar,
)
from .._resources import available_devices, cached_model
from .._workers import Failed, yielding_failure
from ._choosers import ground_truth_fit, image_layer_box, raw_frame_fit
from ._methods import MethodPanel

__all__ = ["Job", "ReconstructWidget", "frame_order", "reconstruct_frames", "run_jobs"]

RECONSTRUCTION = "reconstruction"
DEMIXED = "demixed views"
QUALITY_KEY = "svcode_quality"
#: which panel of a comparison (``"A"``, ``"B"``) a layer shows
COMPARE_KEY = "svcode_compare"
#: how the knobs of a method read in a layer name (``None``: not named)
KNOBS = {"tile_size": "tile {}", "refine_periphery": "periphery ×{}", "rank": "K = {}",
         "iterations": "{} iterations", "tv_weight": "λ {}", "balance": "balance {}",
         "boundary": "{} boundary", "precision": "{}"}
#: progress-bar steps per frame: the bar and its text change at most this often a frame
#: (every Qt call from Python has a cost, so tile-by-tile updates are coalesced)
STEPS = 100


#: the full scales offered for integer frames: (label, count); ``None``: the type's
FULL_SCALES = [("the type's (255, 65535)", None), ("10 bits: 1023", 1023.0),
               ("12 bits: 4095", 4095.0), ("14 bits: 16383", 16383.0)]


class ScaledFrames:
    """A ``(T, H, W)`` stack of sensor counts read as float32 frames of full scale 1: each
    frame divided by ``scale`` when it is read."""

    def __init__(self, frames: np.ndarray, scale: float) -> None:
        self.frames, self.scale = frames, float(scale)
        self.shape = frames.shape

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int | slice) -> Any:
        if isinstance(index, slice):
            return ScaledFrames(self.frames[index], self.scale)
        return (np.asarray(self.frames[index], np.float64) / self.scale).astype(np.float32)


def frame_order(count: int, first: int = 0) -> list[int]:
    """Frames ``first, first + 1, ..., count - 1``, then ``first - 1, ..., 0``: the frames
    done at any time form one contiguous range."""
    return [*range(first, count), *range(first - 1, -1, -1)]


@dataclass
class Job:
    """One method's run: how to build its reconstructor and what it is called."""

    method: str
    build: Callable[[], Any]
    description: dict[str, Any] = field(default_factory=dict)
    layer_name: str = RECONSTRUCTION
    slot: str | None = None  # "A" or "B" in a comparison


@dataclass(frozen=True)
class Started:
    """Yielded by :func:`run_jobs` when job ``job`` starts building its reconstructor."""

    job: int


@dataclass(frozen=True)
class FrameDone:
    """Yielded by :func:`run_jobs` when a frame is reconstructed."""

    job: int
    index: int
    result: ReconstructionResult
    seconds: float


def run_jobs(
    jobs: list[Job], frames: np.ndarray, first: int = 0, return_views: bool = False
) -> Generator[Started | FrameProgress | FrameDone, None, None]:
    """Run every job over the ``(T, H, W)`` stack in :func:`frame_order`.

    Yields :class:`Started` at once for each job, the core's
    :class:`~svcode_core.methods.base.FrameProgress` while a frame runs and
    :class:`FrameDone` after it. Closing the generator stops it at the next yield.
    """
    for number, job in enumerate(jobs):
        yield Started(number)
        reconstructor = job.build()
        for index in frame_order(len(frames), first):
            start = time.perf_counter()
            result = yield from _frame_steps(reconstructor, frames[index], return_views)
            yield FrameDone(number, index, result, time.perf_counter() - start)


def _frame_steps(reconstructor: Any, frame: np.ndarray, return_views: bool
                 ) -> Generator[FrameProgress, None, ReconstructionResult]:  # fmt: skip
    """:func:`iter_method` without the report that every tile or iteration is done: what
    follows it is cheap, so a cancel pressed during the last step keeps the frame instead
    of throwing it away at that report."""
    steps = iter_method(reconstructor, frame, return_views)
    try:
        while True:
            try:
                item = next(steps)
            except StopIteration as finished:
                return finished.value
            last = item.tiles_total and item.tiles_done == item.tiles_total
            if not last or item.refining:
                yield item
    finally:
        steps.close()


def reconstruct_frames(
    reconstructor: Any, frames: np.ndarray, first: int = 0, return_views: bool = False
) -> Generator[FrameProgress | tuple[int, ReconstructionResult], None, None]:
    """Reconstruct a ``(T, H, W)`` stack with one reconstructor in :func:`frame_order`,
    yielding progress and ``(frame index, result)``."""
    job = Job("", lambda: reconstructor)
    for item in run_jobs([job], frames, first, return_views):
        if isinstance(item, FrameDone):
            yield item.index, item.result
        elif isinstance(item, FrameProgress):
            yield item


class ReconstructWidget(Container):
    """Reconstruct a raw CM² frame or stack with any method, or compare two methods.

    *Reconstruct* runs the chosen method in a worker thread (progress and time left below
    the button; *Cancel* stops within one batch of tiles or before a frame's periphery
    refinement (the status line says when one runs), within one iteration of LSV-ADMM or
    RL, or after the current frame for the other methods; a frame stopped part way is not
    added) and adds ``"reconstruction"`` (``(S, S)`` or ``(T, S, S)``) and, if asked,
    ``"demixed views"`` (``(9, S, S)`` or ``(9, T, S, S)``, axis ``lens`` first), placed
    over the raw frame. A stack runs from the current frame to the end, then backwards,
    and its layers hold only the frames done (``svcode_frames`` in their metadata says
    which). *Compare* runs two methods on the current frame and shows them side by side
    (grid view, one contrast range for both) as layers ``"A: <method>, <knobs>"`` and
    ``"B: …"``, with the seconds each took and PSNR / SSIM (centre and ring) against the
    ground truth of the raw frame's own simulated scene (``svcode_scene``), if there is
    one; a truth of another scene is not used, and the status line says so. The status
    line tells how the last run ended (done, cancelled, failed, not run). Runs estimated
    to take very long or not to fit in memory, and integer frames that use fewer bits than
    their type with no full scale set (their notice sets it), ask for a second press.
    *Copy CLI command* gives the equivalent ``svcode reconstruct`` command for a folder of
    recordings.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "raw layer", fit=raw_frame_fit,
                                      tooltip="a raw sensor frame (H×W) or stack (T×H×W)")
        self._panel = MethodPanel("method")
        self._compare = CheckBox(text="compare with a second method", value=False)
        self._second = MethodPanel("second method", "admm")
        self._truth = image_layer_box(napari_viewer, "ground truth", fit=self._truth_fit,
                                      nullable=True,
                                      tooltip="optional: the true object (S×S) of the raw "
                                              "frame's simulated scene, for PSNR/SSIM")
        self._device = ComboBox(label="device", choices=available_devices())
        self._full_scale = ComboBox(
            label="full scale", choices=FULL_SCALES, value=None,
            tooltip="the sensor's full-scale count of integer frames (svcode reconstruct "
                    "--input-scale): a 12-bit camera's counts stored in 16-bit words need "
                    "4095, not the type's 65535")
        self._views = CheckBox(text="add the demixed views", value=False)
        self._warning = Label(value="")
        self._run = PushButton(text="Reconstruct")
        self._cancel = PushButton(text="Cancel", enabled=False)
        self._progress = ProgressBar(min=0, max=STEPS, value=0, label="progress")
        self._status = Label(value="")
        self._status.native.setWordWrap(True)
        self._results = Label(value="")
        self._results.native.setWordWrap(True)
        self._command = PushButton(text="Copy CLI command (for a folder)")
        self._command_text = TextEdit(value="", visible=False)
        self._command_text.read_only = True
        super().__init__(widgets=[
            self._layer, self._panel, self._compare, self._second, self._truth, self._device,
            self._full_scale, self._views, self._warning, self._run, self._cancel,
            self._progress, self._status, self._results, self._command, self._command_text,
        ])
        self._second.visible = False
        self._warning.visible = False
        self._run.changed.connect(self.start)
        self._cancel.changed.connect(self.cancel)
        self._command.changed.connect(self.copy_command)
        self._compare.changed.connect(self._on_compare)
        self._layer.changed.connect(self._on_layer)
        for widget in (self._panel, self._second, self._compare, self._layer, self._device,
                       self._full_scale,
                       self._views):
            widget.changed.connect(self._update_warning)
        self._ticker = QTimer()
        self._ticker.setInterval(1000)
        self._ticker.timeout.connect(self._tick)
        self.worker: GeneratorWorker | None = None
        self.frames_done = 0
        self.results: list[dict[str, Any]] = []
        self._confirmed: tuple | None = None
        self._state: dict[str, Any] = {}
        self._on_layer(self._layer.value)

    # ------------------------------------------------------------------ set-up
    def _on_compare(self, on: bool) -> None:
        self._second.visible = on

    def _warn_about(self, frames: np.ndarray, scale: float | None) -> None:
        """Toast what the core would warn about ``frames``; 12-bit counts in 16-bit words
        come with a button that sets the full scale to 4095."""
        fitting = few_bits_scale(frames) if scale is None else None
        for problem, fix in frame_warnings(frames, scale):
            actions = ()
            if fitting is not None and (problem, fix) == few_bits_warning(frames.dtype):
                actions = ((f"Use {fitting:g}", lambda _toast: self._use_full_scale(fitting)),)
            notify_warning(problem, fix, actions)

    def _use_full_scale(self, scale: float) -> None:
        self._full_scale.value = scale
        show_info(f"Full scale set to {scale:g}: press Reconstruct again.")

    def _on_layer(self, layer: napari.layers.Image | None) -> None:
        if hasattr(self, "_truth"):  # the raw frame's own truth, or none
            self._truth.refit()
        self._update_warning()

    def _truth_fit(self, layer: Any) -> int:
        """A ground truth fits when it is an object layer of the raw frame's scene."""
        raw = self._layer.value
        return ground_truth_fit(layer) * int(raw is not None and
                                             same_scene(layer.metadata, raw.metadata))

    def _scored_truth(self, raw: napari.layers.Image) -> tuple[Any, str | None]:
        """The chosen ground truth if it is of ``raw``'s scene, else ``None`` and why."""
        truth = self._truth.value
        if truth is None or same_scene(truth.metadata, raw.metadata):
            return truth, None
        return None, (f"{truth.name!r} is the truth of another scene than {raw.name!r}, "
                      "so the run is not scored")

    @staticmethod
    def _layer_system(layer: napari.layers.Image | None) -> SystemConfig | None:
        try:
            return layer_system(layer.metadata) if layer is not None else None
        except (TypeError, ValueError):
            return None

    def _panels(self) -> list[MethodPanel]:
        return [self._panel, self._second] if self._compare.value else [self._panel]

    def _frame_count(self, layer: napari.layers.Image) -> int:
        if self._compare.value or layer.ndim == 2:
            return 1
        return int(layer.data.shape[0])

    def _cost_warning(self) -> str | None:
        layer = self._layer.value
        system = self._layer_system(layer)
        if system is None:
            return None
        frames = self._frame_count(layer)
        for panel in self._panels():
            warning = panel.cost(system, frames, self._device.value, self._views.value).warning()
            if warning:
                return f"{panel.describe()} {warning}"
        return None

    def _update_warning(self, *_: Any) -> None:
        warning = self._cost_warning()
        self._warning.value = f"⚠ {warning}" if warning else ""
        self._warning.visible = bool(warning)
        self._run.text = "Reconstruct"
        self._confirmed = None
        if self._command_text.value:  # a command shown follows the settings
            try:
                self._command_text.value = self.command()
            except ValueError:
                self._command_text.value = ""
                self._command_text.visible = False

    def _settings_key(self) -> tuple:
        panels = tuple((panel.method.value, tuple(sorted(panel.options().items())))
                       for panel in self._panels())
        return (id(self._layer.value), panels, self._device.value, self._views.value,
                self._full_scale.value)

    def _job(self, panel: MethodPanel, system: SystemConfig | None, name: str) -> tuple:
        """The job of ``panel`` and the system it runs on (SV-CoDe: the model's)."""
        method, device, options = panel.method.value, self._device.value, panel.options()
        description = {"method": method, "device": device, **options}
        if method == "svcode":
            path = panel.weights_path(system.name if system else None)
            model, trained_for = cached_model(path, system)  # chief rays may differ
            if system is None:
                show_info(f"The layer has no system configuration; using the model's "
                          f"training system {trained_for.name!r}.")
                system = trained_for
            description.update(path=str(path), architecture=type(model).__name__,
                               system=trained_for.name)

            def build() -> Any:  # the sub-views are cut at the layer's chief rays
                return build_reconstructor("svcode", system, model=model, device=device,
                                           **options)
        else:
            if system is None:
                raise ValueError("the layer has no system configuration; "
                                 "choose its system in the Calibration widget")
            weights = panel.weights_path()
            if weights is not None:
                description["path"] = str(weights)

            def build() -> Any:
                return build_reconstructor(method, system, weights=weights, device=device,
                                           **options)

            if method in LEARNED_METHODS:  # quick to load: its errors show at once
                build = _returning(build())
        return Job(method, build, description, name), system

    @staticmethod
    def _frames(layer: napari.layers.Image, system: SystemConfig) -> np.ndarray:
        frames = np.asarray(layer.data)
        if layer.rgb or frames.ndim not in (2, 3):
            raise ValueError(f"layer {layer.name!r} has shape {frames.shape}; expected a raw "
                             "grey frame (H×W) or a frame stack (T×H×W)")
        check_frame_shape(frames.shape[-2:], system)
        bad = frames.size - np.count_nonzero(np.isfinite(frames))
        if bad:
            raise ValueError(f"layer {layer.name!r} holds {bad} NaN or Inf values")
        return frames if frames.ndim == 3 else frames[None]

    def _truth_plane(self, layer: Any, system: SystemConfig) -> np.ndarray | None:
        if layer is None:
            return None
        plane = np.asarray(layer.data[current_index(layer, self._viewer.dims.point)],
                           dtype=np.float64)
        size = system.sub_view_size
        if plane.shape != (size, size):
            raise ValueError(f"ground truth {layer.name!r} is {plane.shape[0]}×"
                             f"{plane.shape[1]} pixels, not the {size}×{size} object grid; "
                             "choose the object layer of this frame, or none")
        return plane

    def start(self) -> GeneratorWorker | None:
        """Check the inputs and start the reconstruction worker (errors become notices).

        Returns ``None`` without running when a check fails, or when the run would take
        very long or not fit in memory and has not been confirmed by a second press.
        """
        layer = self._layer.value
        if layer is None:
            self._status.value = "Not run: no raw image layer."
            notify_error("No raw image layer to reconstruct.",
                         "open a raw CM² frame (File ▸ Open) or a sample (File ▸ Open Sample)")
            return None
        compare = self._compare.value
        slots = ["A", "B"] if compare else [None]
        truth_layer, unscored = self._scored_truth(layer)
        try:
            system = self._layer_system(layer)
            jobs, systems = [], []
            for panel, slot in zip(self._panels(), slots, strict=True):
                name = f"{slot}: {_label(panel)}" if slot else RECONSTRUCTION
                job, job_system = self._job(panel, system, name)
                job.slot = slot
                jobs.append(job)
                systems.append(job_system)
            system = systems[0]
            frames = self._frames(layer, system)
            truth = self._truth_plane(truth_layer, system)
        except (ValueError, FileNotFoundError) as err:
            self._status.value = f"Not run: {str(err).splitlines()[0]}"
            notify_error(err, "check the raw layer, its system (Calibration) and the model")
            return None
        scale = self._full_scale.value
        self._warn_about(frames, scale)
        warning = self._cost_warning()
        few_bits = scale is None and few_bits_scale(frames) is not None
        if (warning or few_bits) and self._confirmed != self._settings_key():
            self._confirmed = self._settings_key()
            self._run.text = "Reconstruct anyway"
            self._status.value = "Not run yet: press 'Reconstruct anyway' to confirm."
            if few_bits:  # its notice, just shown, has the one-click fix
                self._status.value = ("Not run yet: set the full scale (the notice's button) "
                                      "or press 'Reconstruct anyway'.")
            if warning:
                notify_warning(warning, "press 'Reconstruct anyway' to run, or change the "
                                        "settings (tile size, frames, iterations)")
            return None
        first = current_index(layer, self._viewer.dims.point)[0] if frames.shape[0] > 1 else 0
        if compare:
            frames, first = frames[first:first + 1], 0
        views = self._views.value and not compare
        if scale is not None:
            frames = ScaledFrames(frames, scale)
        if compare:
            self._remove_compared(jobs)
        if unscored:
            show_info(f"Not scored: {unscored}.")
        self._prepare(layer, system, jobs, frames.shape[0], first, truth, views)
        self._state.update(truth_layer=truth_layer, unscored=unscored)
        worker = thread_worker(yielding_failure, start_thread=False)(
            run_jobs, jobs, frames, first, views)
        worker.yielded.connect(self._on_yielded)
        worker.aborted.connect(self._on_aborted)
        worker.finished.connect(self._on_finished)
        self.worker = worker
        self._run.enabled, self._cancel.enabled = False, True
        self._run.text = "Reconstruct"
        self._confirmed = None
        worker.start()
        return worker

    def _remove_compared(self, jobs: list[Job]) -> None:
        """Remove the panels of an earlier comparison whose names (knobs) differ."""
        names = {job.layer_name for job in jobs}
        layers = self._viewer.layers
        for layer in [layer for layer in layers if layer.metadata.get(COMPARE_KEY)]:
            if layer.name not in names:
                layers.remove(layer)

    def _prepare(self, layer: napari.layers.Image, system: SystemConfig, jobs: list[Job],
                 count: int, first: int, truth: np.ndarray | None, views: bool) -> None:
        size = system.sub_view_size
        lead = (float(layer.translate[0]),) if count > 1 else ()
        self._state = dict(
            system=system, jobs=jobs, count=count, first=first, truth=truth,
            lead=lead, translate=object_translate(system), raw=layer,
            shapes=((count, size, size), (9, count, size, size) if views else None),
            done=[], started=time.perf_counter(), outcome=None,
        )
        self.frames_done = 0
        self.results = []
        self._results.value = ""
        self._progress.max = STEPS * count * len(jobs)
        self._progress.value = 0
        self._status.value = f"Starting {METHOD_TITLES[jobs[0].method]}…"

    # ---------------------------------------------------------------- running
    def cancel(self) -> None:
        """Ask the worker to stop after the batch of tiles, iteration or frame it is running."""
        if self.worker is not None:
            self.worker.quit()
        self._cancel.enabled = False
        if self._state:
            self._state["outcome"] = "cancelled"
        self._status.value = "Cancelling after the current step…"

    def _set_progress(self, job: int, frames_done: int, fraction: float, text: str,
                      force: bool = True, busy: bool = False) -> None:
        """Show the progress (coalesced to :data:`STEPS` a frame) and ``text``. ``busy``:
        a step that reports nothing of its own (building a forward model, a frame without
        tiles or iterations) leaves the bar where it is and the status line counts its
        seconds (:meth:`_tick`); an indeterminate bar's animation cost such a frame as much
        CPU again under software rendering."""
        state = self._state
        if busy:
            if (state.get("busy") or ("",))[0] != text:
                state["busy"] = (text, time.perf_counter())
                self._status.value = text
            self._ticker.start()
            return
        state["busy"] = None
        self._ticker.stop()
        total = STEPS * state["count"] * len(state["jobs"])
        value = min(int(STEPS * (job * state["count"] + frames_done + fraction)), total)
        if value == state.get("shown") and not force:
            return
        state["shown"] = value
        self._progress.value = value
        self._status.value = text

    def _tick(self) -> None:
        """Once a second during a busy step: its text and the seconds it has taken."""
        busy = self._state.get("busy") if self._state else None
        if busy:
            text, since = busy
            self._status.value = f"{text} {time.perf_counter() - since:.0f} s"

    def _time_left(self, frames: float) -> str:
        """``", about N s left"`` for the running job, ``frames`` of its frames done, at
        its pace since its first report; empty for the first second."""
        state = self._state
        now = time.perf_counter()
        since, start = state.setdefault("pace", (now, frames))
        seconds, gained = now - since, frames - start
        if seconds < 1.0 or gained <= 0:
            return ""
        return f", about {(state['count'] - frames) * seconds / gained:.0f} s left"

    def _on_yielded(self, item: Started | FrameProgress | FrameDone | Failed) -> None:
        # Only widget and layer updates here: never process events from a worker callback.
        if isinstance(item, Failed):
            self._on_errored(item.error)
            return
        state = self._state
        job = state["jobs"][getattr(item, "job", state.get("job", 0))]
        title = METHOD_TITLES[job.method]
        if isinstance(item, Started):  # each job fills arrays of its own
            recon, views = state["shapes"]
            state.update(job=item.job, done=[], recon=np.zeros(recon, np.float32),
                         views=None if views is None else np.zeros(views, np.float32))
            state.pop("pace", None)
            self._set_progress(item.job, 0, 0.0, f"{title}: preparing…", busy=True)
            return
        done = len(state["done"])
        where = f"frame {done + 1} of {state['count']}" if state["count"] > 1 else "frame"
        if isinstance(item, FrameProgress):
            fraction = item.tiles_done / item.tiles_total if item.tiles_total else 0.0
            # SV-CoDe counts tiles, LSV-ADMM and RL iterations; a one-step frame (0 of 1)
            # reports nothing until it is done
            svcode = job.method == "svcode"
            stepped = not item.refining and (svcode or item.tiles_total > 1)
            unit = "tiles" if svcode else "iteration"
            steps = f", {unit} {item.tiles_done}/{item.tiles_total}" if stepped else " running…"
            if item.refining:
                steps = ", refining the periphery…"
            self._set_progress(state["job"], done, fraction,
                               f"{title}: {where}{steps}{self._time_left(done + fraction)}",
                               force=False, busy=not stepped)
            return
        state["done"].append(item.index)
        state["recon"][item.index] = item.result.reconstruction
        if state["views"] is not None:
            state["views"][:, item.index] = item.result.views
        self.frames_done = len(state["done"])
        self._set_progress(item.job, self.frames_done, 0.0,
                           f"{title}: {where} done{self._time_left(self.frames_done)}")
        self._show(job)
        if self.frames_done == 1:
            self._record(item, job)

    def _record(self, item: FrameDone, job: Job) -> None:
        """The seconds and (with a ground truth) quality of the job's first frame."""
        label = job.layer_name.split(": ", 1)[-1] if job.slot else METHOD_TITLES[job.method]
        entry = {"method": job.method, "layer": job.layer_name, "label": label,
                 "seconds": item.seconds}
        truth = self._state["truth"]
        if truth is not None:
            span = float(truth.max() - truth.min()) or 1.0
            try:
                entry.update(image_quality(truth, item.result.reconstruction, span))
            except ValueError as err:
                notify_error(err, "choose a ground truth of the object grid, or none")
        self.results.append(entry)
        layer = self._viewer.layers[job.layer_name]
        layer.metadata = {**layer.metadata, QUALITY_KEY: entry}
        self._results.value = "\n".join(_summary(result) for result in self.results)

    def _show(self, job: Job) -> None:
        state = self._state
        done = state["done"]
        low, high = min(done), max(done) + 1  # frame_order keeps the done frames contiguous
        single = state["count"] == 1
        lead = tuple(value + low for value in state["lead"])
        raw, origin = state["raw"], state["translate"]
        meta = layer_metadata(state["system"], RECONSTRUCTION, job.description)
        frames = {} if single else {FRAMES_KEY: {"first": low, "stop": high,
                                                 "total": state["count"]}}
        meta.update(frames)
        if job.slot:
            meta[COMPARE_KEY] = job.slot
        data = state["recon"][0] if single else state["recon"][low:high]
        self._put_layer(job.layer_name, data, placement_over(raw, data.ndim, origin, lead), meta,
                        ("frame",) if not single else (), colormap="magma")
        if state["views"] is not None:
            views = state["views"][:, 0] if single else state["views"][:, low:high]
            meta = {**layer_metadata(state["system"], "demixed", job.description), **frames}
            self._put_layer(DEMIXED, views, placement_over(raw, views.ndim, origin, (0.0, *lead)),
                            meta, ("lens",) + (("frame",) if not single else ()),
                            colormap="gray", visible=False)

    def _put_layer(self, name: str, data: np.ndarray, place: dict[str, Any], meta: dict,
                   leading: tuple[str, ...], **kwargs: Any) -> None:
        """Add or update the layer ``name``, placed by ``place`` (scale, translate, units:
        over the raw layer, :func:`~napari_svcode._layers.placement_over`)."""
        layers = self._viewer.layers
        labels = (*leading, "y", "x")
        if name in layers and layers[name].ndim == data.ndim:
            layer = layers[name]
            layer.data = data
            layer.scale, layer.translate = place["scale"], place["translate"]
            if LAYER_UNITS:
                layer.units = place.get("units") or ("pixel",) * data.ndim
            layer.metadata = meta
        else:
            if name in layers:
                layers.remove(name)
            layer = self._viewer.add_image(data, name=name, metadata=meta, **place, **kwargs)
            if in_micrometres(place):
                show_scale_bar(self._viewer)
        layer.axis_labels = labels
        if self.frames_done == 1:
            layer.reset_contrast_limits()

    def _on_errored(self, err: Exception) -> None:
        self._state["outcome"] = "failed"
        self._state["error"] = str(err).splitlines()[0] if str(err) else type(err).__name__
        notify_error(err, "check the method's options and model file")

    def _on_aborted(self) -> None:
        state = self._state
        state["outcome"] = "cancelled"
        show_info(f"Reconstruction cancelled after {self.frames_done} of {state['count']} "
                  "frames; only those were added.")

    def _on_finished(self) -> None:
        state = self._state
        self._run.enabled, self._cancel.enabled = True, False
        total = STEPS * state["count"] * len(state["jobs"])
        state["busy"] = None
        self._ticker.stop()
        elapsed = time.perf_counter() - state["started"]
        # the bar shows what was kept: the jobs finished and this job's frames done
        kept = STEPS * (state.get("job", 0) * state["count"] + self.frames_done)
        outcome = state["outcome"]
        if outcome is None and kept < total:
            outcome = "cancelled"  # stopped without an error: a cancel
        if outcome == "failed":
            self._progress.value = min(kept, total)
            self._status.value = f"Failed after {elapsed:.1f} s: {state['error']}"
        elif outcome == "cancelled":
            self._progress.value = min(kept, total)
            self._status.value = (f"Cancelled after {elapsed:.1f} s: {self.frames_done} of "
                                  f"{state['count']} frames kept.")
        else:
            self._progress.value = total
            self._status.value = f"Done in {elapsed:.1f} s."
        if state.get("unscored"):
            self._status.value += f" Not scored: {state['unscored']}."
        if len(state["jobs"]) > 1 and all(job.layer_name in self._viewer.layers
                                          for job in state["jobs"]):
            self._show_side_by_side()

    def _show_side_by_side(self) -> None:
        """Grid view: the ground truth (if scored) and both reconstructions, each in a cell
        named by its method and knobs, with one contrast range for both."""
        layers = self._viewer.layers
        names = [job.layer_name for job in self._state["jobs"]]
        truth = self._state.get("truth_layer")
        for layer in layers:
            layer.visible = layer.name in names or layer is truth
        panels = [layers[name] for name in names]
        low = min(float(np.min(layer.data)) for layer in panels)
        high = max(float(np.max(layer.data)) for layer in panels)
        layers.unlink_layers(panels, attributes=("contrast_limits",))
        for layer in panels:
            layer.contrast_limits_range = (low, high if high > low else low + 1.0)
        layers.link_layers(panels, attributes=("contrast_limits",))
        panels[0].contrast_limits = (low, high if high > low else low + 1.0)
        for layer in [*panels, *([truth] if truth is not None else [])]:
            overlay = getattr(layer, "name_overlay", None)  # napari 0.6 and later
            if overlay is not None:
                overlay.visible = True
        canvas = getattr(self._viewer, "canvas", None)
        grid = canvas.grid if canvas is not None and hasattr(canvas, "grid") else \
            self._viewer.grid
        grid.shape = (1, len(names) + (truth is not None))  # one row, side by side
        grid.enabled = True
        self._viewer.reset_view()

    # ---------------------------------------------------------------- hand-off
    def command(self) -> str:
        """The ``svcode reconstruct`` command of the current settings, for every TIFF of a
        folder (a shell loop; replace ``FOLDER``)."""
        layer = self._layer.value
        system = self._layer_system(layer)
        panel = self._panel
        path = panel.weights_path(system.name if system else None) \
            if panel.method.value != "svcode" or panel.model.source.value != panel.model.BUNDLED \
            else None
        default = registry.method(panel.method.value).precisions[0]
        options = {key: value for key, value in panel.options().items()
                   if not (key == "precision" and value == default)}
        if self._device.value != "cpu":
            options["device"] = self._device.value
        arguments = cli_arguments(panel.method.value, path, **options)
        if system is not None:
            preset = system.name if system.name in available_presets() and \
                SystemConfig.preset(system.name) == system else "system.json"
            arguments = ["--system", preset, *arguments]
        if self._full_scale.value is not None:
            arguments += ["--input-scale", f"{self._full_scale.value:g}"]
        if self._views.value:
            arguments += ["--views", '"${f%.tif}.views.tif"']
        flags = " ".join(arg if arg.startswith('"') else shlex.quote(arg) for arg in arguments)
        return ('for f in FOLDER/*.tif; do svcode reconstruct "$f" --out "${f%.tif}.recon.tif" '
                f"{flags}; done")

    def copy_command(self) -> str | None:
        """Show the folder command in the widget and copy it to the clipboard."""
        try:
            text = self.command()
        except ValueError as err:
            notify_error(err, "choose a model file for this method first")
            return None
        self._command_text.value = text
        self._command_text.visible = True
        from qtpy.QtWidgets import QApplication

        clipboard = QApplication.clipboard()
        if clipboard is not None:
            clipboard.setText(text)
        LOG.info("svcode reconstruct command: %s", text)
        show_info("Copied the `svcode reconstruct` command for a folder (replace FOLDER).")
        return text


def _returning(value: Any) -> Callable[[], Any]:
    """A function that returns ``value`` (an already built reconstructor)."""
    return lambda: value


def _label(panel: MethodPanel) -> str:
    """The method and its knobs, e.g. ``"LSV-ADMM (TV), 10 iterations, λ auto"``."""
    default = registry.method(panel.method.value).precisions[0]
    knobs = [KNOBS[key].format(value) for key, value in panel.options().items()
             if key in KNOBS and value is not None
             and not (key == "precision" and value == default)]
    return ", ".join([panel.describe(), *knobs])


def _summary(entry: dict[str, Any]) -> str:
    label = entry.get("label") or METHOD_TITLES[entry["method"]]
    text = f"{label}: {entry['seconds']:.1f} s"
    if "psnr" in entry:
        text += (f" · PSNR {entry['psnr']:.1f} dB (centre {entry['psnr_centre']:.1f}, "
                 f"ring {entry['psnr_ring']:.1f}) · SSIM {entry['ssim']:.3f}")
    return text

