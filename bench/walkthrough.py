"""A scripted GUI walk-through of the napari plugin on frames the project has never seen.

What it does
    1. Makes raw frames of images that neither training (``TRAINING_PHOTOS``, the Hubble
       deep field, the retina) nor the benchmarks (``HELD_OUT_IMAGES``) use, through a
       *departed* cm2-mini instrument (the ``realistic`` set of departures, with its camera
       set so that the 12-bit converter's full scale is the reconstructors' full scale
       1.0: 10 000 photo-electrons at intensity 1 and a 10 000 e full well):

       * ``frame12.tif``: matplotlib's MRI slice ``s1045.ima.gz`` at a dim exposure (frame
         peak about 7 % of full scale), stored as a camera would: uint16 holding 12-bit
         counts (0..4095), no svcode metadata, a ``system.json`` beside it;
       * ``stack6.tif``: scikit-image's Shepp-Logan ``phantom.png`` moving 2, 3 pixels a
         frame, six frames, float32 (written with :func:`svcode_core.io.write_tiff`);
       * ``zeros.tif``: an all-zero frame of the sensor's size;
       * the ground truths on the object grid (``*_truth.tif``) for scoring.

    2. Walks through the plugin in real ``napari.Viewer`` windows, pressing the widgets'
       buttons as a user would (and driving them as ``tests/test_napari_widgets.py`` does
       where a mouse is needed): (a) the reader, (b) SV-CoDe on the 12-bit frame and the
       12-bit notice's one-click fix, (c) LSV-ADMM at its defaults, its progress and
       Cancel, (d) Wiener and Richardson-Lucy, (e) compare mode, (f) the stack with a
       cancel half way and the partial stack saved by the plugin's writer, (g) the all-zero
       frame, (h) the Simulate widget, (i) the Calibration widget's drag / undo / reset.

    3. Writes ``bench/results/walkthrough.md`` (what was done at each step, the figures
       measured, the messages shown verbatim, a verdict per check) and a few screenshots
       in ``bench/results/walkthrough/``.

Every notification is recorded from napari's notification manager (nothing is patched
away, so the toasts appear as they would for a user). Waiting for a worker runs the Qt
event loop from the script's main loop, never from inside a worker callback. PSNR is
computed here with :func:`svcode_core.evaluation.metrics.psnr` against the truth of the
same scene (data range: the truth's span).

Run (about 5 minutes on one CPU thread)::

    xvfb-run -a python bench/walkthrough.py

Options: ``--data DIR`` keeps the simulated files there (default: a temporary folder).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads (tests/conftest.py)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import gzip  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

import napari  # noqa: E402
import tifffile  # noqa: E402
from napari.utils.notifications import notification_manager  # noqa: E402
from qtpy.QtWidgets import QApplication  # noqa: E402

from svcode_core.config import SystemConfig  # noqa: E402
from svcode_core.evaluation.metrics import psnr  # noqa: E402
from svcode_core.io import read_tiff, write_tiff  # noqa: E402
from svcode_core.phantoms import HELD_OUT_IMAGES, TRAINING_PHOTOS, from_image  # noqa: E402
from svcode_core.physics.departures import Departures  # noqa: E402
from svcode_core.physics.simulate import Simulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
REPORT = RESULTS / "walkthrough.md"
SHOTS = RESULTS / "walkthrough"
MAX_SHOT_BYTES = 300_000
PLUGIN = "napari-svcode"
#: the dim exposure of the 12-bit frame: its peak as a fraction of the full scale
DIM_PEAK = 0.07
#: brightness (object peak, in units of the sensor's full scale) of the moving stack
STACK_PEAK = 0.5
STACK_SHIFT = (2, 3)  # pixels a frame (rows, columns)
FRAMES = 6


# ------------------------------------------------------------------ report
class Report:
    """The walk-through's Markdown report: per step what was done, the figures, the
    messages verbatim and a verdict per check; written again after every step."""

    def __init__(self, path: Path) -> None:
        self.path, self.sections, self.head = path, [], []
        self.started = time.perf_counter()

    def step(self, title: str) -> None:
        self.sections.append({"title": title, "lines": [], "verdicts": []})
        print(f"\n== {title}", flush=True)

    def note(self, text: str) -> None:
        self.sections[-1]["lines"].append(f"- {text}")
        print(f"   {text}", flush=True)

    def quote(self, label: str, text: str) -> None:
        """A message shown by the plugin, verbatim (as a block quote)."""
        body = "\n".join(f"  > {line}" if line else "  >" for line in str(text).split("\n"))
        self.sections[-1]["lines"].append(f"- {label}:\n\n{body}\n")
        print(f"   {label}: {text!r}", flush=True)

    def verdict(self, ok: bool, what: str) -> None:
        self.sections[-1]["verdicts"].append(("works" if ok else "problem", what))
        print(f"   [{'works' if ok else 'PROBLEM'}] {what}", flush=True)

    def write(self) -> None:
        lines = ["# GUI walk-through of the napari plugin on frames it has never seen", "",
                 "Made by `xvfb-run -a python bench/walkthrough.py` (its docstring says how the "
                 "frames are made and how each step is driven). Verdicts: **works**, or "
                 "**problem** and what.", "", *self.head, "", "## Verdicts", "",
                 "| step | works | problems |", "|---|---|---|"]
        for section in self.sections:
            works = sum(kind == "works" for kind, _ in section["verdicts"])
            problems = [what for kind, what in section["verdicts"] if kind == "problem"]
            lines.append(f"| {section['title']} | {works} | "
                         f"{'; '.join(problems) if problems else '–'} |")
        for section in self.sections:
            lines += ["", f"## {section['title']}", "", *section["lines"], "", "Verdicts:", ""]
            lines += [f"- **{kind}**: {what}" for kind, what in section["verdicts"]]
        lines += ["", f"Whole script: {time.perf_counter() - self.started:.0f} s wall.", ""]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text("\n".join(lines), encoding="utf-8")


class Notices:
    """Every notification napari shows (the plugin's toasts, its infos, napari's own),
    recorded in order as the notification manager dispatches them."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        notification_manager.notification_ready.connect(self.items.append)

    def mark(self) -> int:
        return len(self.items)

    def since(self, mark: int) -> list[Any]:
        return self.items[mark:]


def severity(notice: Any) -> str:
    return str(getattr(notice.severity, "value", notice.severity))


def quote_notices(report: Report, notices: list[Any], label: str) -> None:
    if not notices:
        report.note(f"{label}: no notification")
    for notice in notices:
        actions = [name for name, _ in (getattr(notice, "actions", ()) or ())]
        extra = f", buttons {actions}" if actions else ""
        report.quote(f"{label} ({severity(notice)}{extra})", notice.message)


# ------------------------------------------------------------------ Qt helpers
def wait_until(condition: Callable[[], bool], timeout: float, step: float = 0.02) -> bool:
    """Run the Qt event loop from here (the script's main loop) until ``condition``."""
    app = QApplication.instance()
    end = time.perf_counter() + timeout
    while time.perf_counter() < end:
        app.processEvents()
        if condition():
            return True
        time.sleep(step)
    app.processEvents()
    return condition()


def pause(seconds: float) -> None:
    wait_until(lambda: False, seconds)


def idle(widget: Any) -> bool:
    return widget._run.enabled and (widget.worker is None or not widget.worker.is_running)


class ProgressLog:
    """What the Reconstruct widget's bar and status line showed, each time it updated
    them: ``(seconds since the press, status, bar maximum, bar value)``."""

    def __init__(self, widget: Any) -> None:
        self.widget, self.rows, self.t0 = widget, [], time.perf_counter()
        original = widget._set_progress

        def spy(*args: Any, **kwargs: Any) -> None:
            original(*args, **kwargs)
            self.rows.append((time.perf_counter() - self.t0, widget._status.value,
                              widget._progress.native.maximum(), widget._progress.value))

        widget._set_progress = spy

    def start(self) -> None:
        self.rows, self.t0 = [], time.perf_counter()

    def texts(self) -> list[str]:
        return [row[1] for row in self.rows]

    def sample(self, count: int = 8) -> str:
        """A few rows, evenly spread, as text."""
        if not self.rows:
            return "(none)"
        picks = sorted(set(np.linspace(0, len(self.rows) - 1, count).round().astype(int)))
        return "; ".join(f"{self.rows[i][0]:.1f} s: bar {self.rows[i][3]}/{self.rows[i][2]} "
                         f"'{self.rows[i][1]}'" for i in picks)


def press(widget: Any, timeout: float = 300.0, cancel_when: Callable[[], bool] | None = None
          ) -> dict[str, Any]:
    """Press *Reconstruct* (or *Simulate*) as a user does, wait until the widget is idle
    again; with ``cancel_when``, press *Cancel* as soon as it holds. Returns the seconds
    and whether a worker started, and when the cancel was pressed."""
    before = widget.worker
    t0 = time.perf_counter()
    widget._run.native.click()
    out: dict[str, Any] = {"started": widget.worker is not before and widget.worker is not None}
    if not out["started"]:
        out["seconds"] = time.perf_counter() - t0
        return out
    if cancel_when is not None:
        wait_until(lambda: cancel_when() or idle(widget), timeout)
        if not idle(widget):
            out["status_at_cancel"] = widget._status.value
            out["cancel_at"] = time.perf_counter() - t0
            tc = time.perf_counter()
            widget._cancel.native.click()
            wait_until(lambda: idle(widget), timeout)
            out["stop_latency"] = time.perf_counter() - tc
    else:
        wait_until(lambda: idle(widget), timeout)
    out["seconds"] = time.perf_counter() - t0
    out["finished"] = idle(widget)
    return out


def screenshot(viewer: napari.Viewer, name: str, report: Report, reset: bool = True) -> None:
    """The window (canvas and docks) as a palette PNG under ``MAX_SHOT_BYTES``."""
    from PIL import Image

    if reset:
        viewer.reset_view()
    pause(0.4)
    image = viewer.screenshot(canvas_only=False, flash=False)
    picture = Image.fromarray(np.ascontiguousarray(image[..., :3]))
    path = SHOTS / name
    SHOTS.mkdir(parents=True, exist_ok=True)
    for factor in (1.0, 0.8, 0.65, 0.5):
        scaled = picture if factor == 1.0 else picture.resize(
            (int(picture.width * factor), int(picture.height * factor)), Image.LANCZOS)
        scaled.quantize(colors=128).save(path, optimize=True)
        if path.stat().st_size <= MAX_SHOT_BYTES:
            break
    report.note(f"screenshot `walkthrough/{name}` ({picture.width}×{picture.height}, "
                f"{path.stat().st_size / 1e3:.0f} kB)")


def show_only(viewer: napari.Viewer, *names: str) -> None:
    """Hide every layer but ``names`` (for a readable screenshot)."""
    for layer in viewer.layers:
        layer.visible = layer.name in names


def new_viewer() -> napari.Viewer:
    viewer = napari.Viewer(show=True)
    viewer.window.resize(1500, 950)
    return viewer


def dock(viewer: napari.Viewer, name: str) -> Any:
    """A plugin widget as the Plugins menu docks it."""
    _, widget = viewer.window.add_plugin_dock_widget(PLUGIN, name)
    return widget


# ------------------------------------------------------------------ frames
def fluorescence(grey: np.ndarray) -> np.ndarray:
    """A grey image as a bright-on-dark map in [0, 1] (the darkest 1 % cut to 0)."""
    grey = np.asarray(grey, dtype=np.float64)
    low, high = np.percentile(grey, [1, 99.9])
    return np.clip((grey - low) / (high - low), 0, 1).astype(np.float32)


def mri_slice() -> np.ndarray:
    import matplotlib.cbook as cbook

    with gzip.open(cbook.get_sample_data("s1045.ima.gz", asfileobj=False)) as handle:
        return np.frombuffer(handle.read(), ">u2").reshape(256, 256).astype(np.float64)


def hopper_edges() -> np.ndarray:
    """Grace Hopper's portrait as bright edges on dark (a membrane-like stain)."""
    import matplotlib.cbook as cbook
    import matplotlib.image as mpimg
    from skimage.color import rgb2gray
    from skimage.filters import gaussian, sobel

    rgb = mpimg.imread(cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))
    return fluorescence(sobel(gaussian(rgb2gray(rgb), 1.5)))


def phantom() -> np.ndarray:
    import skimage

    return skimage.io.imread(Path(skimage.__file__).parent / "data" / "phantom.png",
                             as_gray=True)


def shifted(obj: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``obj`` moved by whole pixels, the uncovered edge dark."""
    out = np.zeros_like(obj)
    h, w = obj.shape
    out[max(rows, 0):h + min(rows, 0), max(cols, 0):w + min(cols, 0)] = \
        obj[max(-rows, 0):h - max(rows, 0), max(-cols, 0):w - max(cols, 0)]
    return out


def make_frames(folder: Path, report: Report) -> dict[str, Any]:
    """Simulate the never-seen frames through the departed instrument; write them."""
    system = SystemConfig.preset("cm2-mini")
    sources = ("s1045.ima.gz", "phantom.png", "grace_hopper.jpg")
    unseen = all(name not in TRAINING_PHOTOS + tuple(HELD_OUT_IMAGES) +
                 ("hubble_deep_field.jpg", "retina.jpg") for name in sources)
    named = Departures.named("realistic", system)
    # the realistic camera, with 10 000 e at intensity 1 and a 10 000 e full well: its
    # 12-bit converter's full scale (4095) is the reconstructors' full scale 1.0
    departures = dataclasses.replace(named, name="realistic, 12-bit full scale = 1.0",
                                     photons=10_000.0, full_well_e=10_000.0)
    t0 = time.perf_counter()
    simulator = Simulator(system, departures=departures)
    build = time.perf_counter() - t0
    folder.mkdir(parents=True, exist_ok=True)
    system.save(folder / "system.json")

    mri = from_image(fluorescence(mri_slice()), system.sub_view_size)
    clean = simulator.simulate(mri, noise=False).measurement
    peak = DIM_PEAK / float(np.percentile(clean, 99.99))
    truth12 = (mri * np.float32(peak)).astype(np.float32)
    measured = simulator.simulate(truth12, seed=1).measurement
    counts = np.clip(np.rint(measured * 4095), 0, 4095).astype(np.uint16)
    tifffile.imwrite(folder / "frame12.tif", counts, photometric="minisblack")  # a camera's
    write_tiff(folder / "frame12_truth.tif", truth12, system, kind="object")

    moving = from_image(fluorescence(phantom()), system.sub_view_size)
    truths = np.stack([shifted(moving, STACK_SHIFT[0] * t, STACK_SHIFT[1] * t)
                       for t in range(FRAMES)]) * np.float32(STACK_PEAK)
    stack = np.stack([simulator.simulate(truths[t], seed=20 + t).measurement
                      for t in range(FRAMES)]).astype(np.float32)
    write_tiff(folder / "stack6.tif", stack, system, kind="measurement")
    write_tiff(folder / "stack6_truth.tif", truths, system, kind="object")
    write_tiff(folder / "zeros.tif", np.zeros(system.sensor_shape, np.float32), system,
               kind="measurement")
    seconds = time.perf_counter() - t0
    report.note(f"departed instrument: {departures.name} (`Departures.named('realistic')` "
                "with `photons` and `full_well_e` 10 000): MLA shift (0.5, −0.3) px, rotation "
                "0.05°, lens jitter 0.25 px, aberration errors, defocus 0.25 waves and depth "
                "spread 0.5, truth PSFs on a 13-grid, haze 25 %, read noise 1.6 e, hot pixels, "
                "PRNU 1 %, DSNU 0.5 e, 12-bit ADC; the files record only the nominal cm2-mini "
                f"system (forward model build {build:.1f} s, all frames {seconds:.1f} s)")
    report.note(f"`frame12.tif`: MRI slice (matplotlib `s1045.ima.gz`), object peak "
                f"{truth12.max():.4f} of full scale, uint16 counts {counts.min()}..{counts.max()} "
                f"(peak {counts.max() / 4095:.1%} of 4095; 99.9th percentile "
                f"{np.percentile(counts, 99.9):.0f}), mean {counts.mean():.1f}; no svcode "
                "metadata, `system.json` beside it")
    report.note(f"`stack6.tif`: Shepp–Logan `phantom.png` (scikit-image), object peak "
                f"{STACK_PEAK}, moving {STACK_SHIFT} px a frame, {FRAMES} frames float32, "
                f"values {stack.min():.3f}..{stack.max():.3f}")
    report.note("`zeros.tif`: 480×640 float32 zeros; truths `frame12_truth.tif`, "
                "`stack6_truth.tif` (kind `object`, 384×384 object grid)")
    report.verdict(unseen, f"the source images {sources} are in neither TRAINING_PHOTOS (nor "
                   "the Hubble field, the retina) nor HELD_OUT_IMAGES")
    return {"system": system, "folder": folder, "truth12": truth12, "counts": counts,
            "truths": truths, "stack": stack}


def quality(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """PSNR (data range: the truth's span) and the ratio of the means (units check)."""
    span = float(truth.max() - truth.min()) or 1.0
    return psnr(truth, np.asarray(estimate, np.float64), span), \
        float(np.mean(estimate) / np.mean(truth))


def fmt_place(layer: Any) -> str:
    units = [str(u) for u in getattr(layer, "units", ())]
    return (f"shape {tuple(layer.data.shape)} {layer.data.dtype}, scale "
            f"{tuple(round(float(s), 4) for s in layer.scale)}, translate "
            f"{tuple(round(float(t), 2) for t in layer.translate)}, units {units}")


# ------------------------------------------------------------------ steps
def step_a(viewer: napari.Viewer, data: dict, report: Report, notices: Notices) -> dict:
    report.step("a. Open the files with the plugin's reader")
    folder, system = data["folder"], data["system"]
    opened = {}
    for name in ("frame12", "stack6", "zeros", "frame12_truth", "stack6_truth"):
        mark = notices.mark()
        layers = viewer.open(folder / f"{name}.tif", plugin=PLUGIN)
        [layer] = layers
        opened[name] = layer
        kind = layer.metadata.get("svcode_kind")
        sys_name = getattr(layer.metadata.get("svcode_system"), "name", None)
        report.note(f"`{name}.tif` → layer **{layer.name}**: {fmt_place(layer)}, kind "
                    f"{kind}, system {sys_name}, contrast limits "
                    f"{tuple(round(float(c), 3) for c in layer.contrast_limits)}")
        quote_notices(report, notices.since(mark), f"notices opening {name}")
        micron = [str(u) for u in layer.units][-2:] == ["micrometer"] * 2
        pixel = system.object_pixel_um
        report.verdict(micron and np.allclose(layer.scale[-2:], pixel),
                       f"{name}: in µm ({pixel} µm pixels from the system)" if micron else
                       f"{name}: units {[str(u) for u in layer.units]}, not µm")
    bar = viewer.canvas.overlays.scale_bar  # napari 0.9: the unit comes from the layers
    units = {str(u) for layer in opened.values() for u in layer.units[-2:]}
    report.note(f"scale bar: visible {bar.visible}, layer units {sorted(units)}")
    report.verdict(bool(bar.visible) and units == {"micrometer"},
                   "scale bar shown, the layers in µm (the bar reads µm: screenshot)")
    truth, raw = opened["frame12_truth"], opened["frame12"]
    report.verdict(raw.data.dtype == np.uint16,
                   f"the 12-bit frame kept as {raw.data.dtype} counts")
    # a 12-bit frame in a uint16 layer: is it visible at once?
    low, high = raw.contrast_limits
    visible = high <= 2 * float(raw.data.max())
    report.verdict(visible, f"12-bit frame's contrast limits ({low:g}, {high:g}) fit its "
                   f"counts (max {raw.data.max()})" if visible else
                   f"12-bit frame shown with contrast limits ({low:g}, {high:g}) while its "
                   f"counts reach {raw.data.max()}: the frame looks black until the user "
                   "adjusts the contrast")
    report.note(f"truth placed at {tuple(float(t) for t in truth.translate)} (object grid "
                "over lens 4)")
    label = viewer.dims.axis_labels[0]
    report.verdict(not label.lstrip("-").isdigit(), f"the stack's frame slider is labelled "
                   f"{label!r}" + ("" if not label.lstrip("-").isdigit() else
                                   " (the reader does not name the frame axis)"))
    return opened


def new_reconstruct(viewer: napari.Viewer) -> tuple[Any, ProgressLog]:
    widget = dock(viewer, "Reconstruct")
    return widget, ProgressLog(widget)


def take_result(viewer: napari.Viewer, new_name: str) -> Any:
    """Rename the widget's ``reconstruction`` layer so the next run adds its own."""
    layer = viewer.layers["reconstruction"]
    layer.name = new_name
    return layer


def step_b(viewer, data, opened, widget, log, report, notices) -> None:
    report.step("b. SV-CoDe (default method) on the 12-bit frame")
    truth = data["truth12"]
    report.note(f"raw layer the widget chose when docked: "
                f"{getattr(widget._layer.value, 'name', None)!r}")
    widget._layer.value = opened["frame12"]
    panel = widget._panel
    report.note(f"widget defaults: method {panel.method.value!r}, model "
                f"{panel.model.source.value!r}, full scale {widget._full_scale.value!r}, "
                f"ground truth chooser: {getattr(widget._truth.value, 'name', None)!r} "
                f"(open: `frame12_truth` from the file and the `cells` sample's truth)")
    report.verdict(widget._truth.value is None,
                   "no ground truth of another scene is chosen for the frame (the file's own "
                   "truth has no scene id either, so the widget cannot score it)")
    mark = notices.mark()
    log.start()
    run = press(widget)
    shown = notices.since(mark)
    quote_notices(report, shown, "notifications on pressing Reconstruct")
    bits = [n for n in shown if "12 bits" in str(n.message)]
    report.verdict(bool(bits), "the 12-bit notice is shown" if bits else
                   "no 12-bit notice for uint16 counts ≤ 4095")
    duplicates = [n for n in shown if "12 bits" in str(n.message)]
    report.verdict(len(duplicates) <= 1, f"the 12-bit problem is told {len(duplicates)} "
                   "time(s)" + ("" if len(duplicates) <= 1 else
                                ": the widget's toast and again the core's warning"))
    if run["started"]:
        first = take_result(viewer, "b1: SV-CoDe, type's scale 65535")
        p1, r1 = quality(truth, first.data)
        report.note(f"run without the fix: {run['seconds']:.1f} s, status "
                    f"'{widget._status.value}'; PSNR {p1:.2f} dB, mean ratio to truth {r1:.3f}")
        report.note(f"progress seen: {log.sample()}")
        report.verdict(False, "the run is not held back by the 12-bit notice: it goes on "
                       f"dividing by 65535 and adds a 'reconstruction' 16× too dim (mean ratio "
                       f"{r1:.3f}, PSNR {p1:.1f} dB); the fix costs a second run")
    else:
        report.verdict(True, "the press is held until the full scale is set or the run "
                       f"confirmed: status '{widget._status.value}', button "
                       f"'{widget._run.text}'")
    actions = [action for n in bits for action in (getattr(n, "actions", ()) or ())]
    if not actions:
        report.verdict(False, "the 12-bit notice has no button to fix it")
        widget._full_scale.value = 4095.0
    else:
        label, callback = actions[0]
        mark = notices.mark()
        callback(None)  # the toast's button
        report.note(f"pressed the notice's button {label!r}: full scale is now "
                    f"{widget._full_scale.value!r}")
        quote_notices(report, notices.since(mark), "after the button")
        report.verdict(widget._full_scale.value == 4095.0,
                       f"the button {label!r} sets the full scale to 4095")
    mark = notices.mark()
    log.start()
    run = press(widget)
    again = [n for n in notices.since(mark) if "12 bits" in str(n.message)]
    quote_notices(report, notices.since(mark), "notifications on the second press")
    report.verdict(not again, "no 12-bit notice once the full scale is 4095")
    fixed = take_result(viewer, "b2: SV-CoDe, full scale 4095")
    p2, r2 = quality(truth, fixed.data)
    report.note(f"run with the fix: {run['seconds']:.1f} s (wall, press to idle), status "
                f"'{widget._status.value}'; **PSNR {p2:.2f} dB**, mean ratio to truth "
                f"{r2:.3f}; results box {widget._results.value!r}")
    report.note(f"progress seen: {log.sample()}")
    report.verdict(abs(r2 - 1) < 0.3, f"SV-CoDe output in the object's units (mean ratio "
                   f"{r2:.3f})")
    report.verdict("PSNR" not in widget._results.value and not any(
        "psnr" in entry for entry in widget.results),
        "the widget does not score the run (no truth of this scene)")
    report.verdict(tuple(fixed.translate) == tuple(opened["frame12_truth"].translate),
                   "reconstruction placed over the truth "
                   f"({tuple(float(t) for t in fixed.translate)} µm)")
    text = widget.copy_command()
    report.quote("Copy CLI command", text)
    report.verdict("--input-scale 4095" in (text or ""), "the folder command carries "
                   "--input-scale 4095")
    data["results"] = {"SV-CoDe (bundled, full scale 4095)": (p2, r2, run["seconds"])}
    show_only(viewer, "frame12", fixed.name)
    screenshot(viewer, "b_svcode_12bit.png", report)
    timing_check(widget, data, report)


def timing_check(widget, data, report) -> None:
    """The same frame through the core, in this process: on the main thread, in a plain
    thread while the Qt loop runs, and through the widget again (seconds a frame)."""
    import threading

    from napari_svcode._resources import bundled_model, cached_model
    from svcode_core.methods.build import build_reconstructor

    frame = (data["counts"] / 4095.0).astype(np.float32)
    model, _ = cached_model(bundled_model("cm2-mini"), data["system"])
    rec = build_reconstructor("svcode", data["system"], model=model, device="cpu")
    rec.reconstruct(frame)  # masks cached, as for the widget's later presses
    t0 = time.perf_counter()
    rec.reconstruct(frame)
    main = time.perf_counter() - t0
    box: dict[str, float] = {}

    def work() -> None:
        start = time.perf_counter()
        rec.reconstruct(frame)
        box["s"] = time.perf_counter() - start

    thread = threading.Thread(target=work)
    thread.start()
    wait_until(lambda: not thread.is_alive(), 120)
    before = widget.results[0]["seconds"] if widget.results else float("nan")
    press(widget)
    again = widget.results[0]["seconds"] if widget.results else float("nan")
    load = os.getloadavg()[0]
    report.note(f"timing check (same frame, SV-CoDe, masks cached): core on the main thread "
                f"{main:.2f} s; core in a plain thread while the Qt loop runs {box['s']:.2f} s; "
                f"the widget's own frame time {before:.2f} s (second press), {again:.2f} s "
                f"(third press); load average {load:.1f} on {os.cpu_count()} cores")
    report.verdict(again < 1.5 * max(main, box["s"]),
                   f"the widget's frame time ({again:.2f} s) against the core's "
                   f"({main:.2f} s main thread, {box['s']:.2f} s thread under the Qt loop)" + (
                       "" if again < 1.5 * max(main, box["s"]) else
                       ": more than 1.5x (on a loaded machine the ratio varies run to run)"))
    viewer_layers = widget._viewer.layers
    if "reconstruction" in viewer_layers:
        viewer_layers.remove("reconstruction")


def step_c(viewer, data, opened, widget, log, report, notices) -> None:
    report.step("c. LSV-ADMM at the widget's defaults: progress, time left, Cancel")
    truth = data["truth12"]
    panel = widget._panel
    panel.method.value = "admm"
    stale = widget._command_text.visible and "--method svcode" in widget._command_text.value
    report.verdict(not stale, "the CLI command box follows the method" if not stale else
                   "after switching to LSV-ADMM the CLI command box still shows "
                   "'--method svcode' (stale text from the last copy)")
    report.note(f"defaults: {panel.options()}, cost warning shown: "
                f"{widget._warning.visible} {widget._warning.value!r}")
    # a whole run at the defaults
    mark = notices.mark()
    log.start()
    run = press(widget, timeout=400)
    quote_notices(report, notices.since(mark), "notifications")
    rows = log.rows
    within = [row for row in rows if "iteration" in row[1]]
    determinate = [row for row in within if row[2] > 0 and 0 < row[3] < row[2]]
    busy = [row for row in rows if row[2] == 0]
    first_iter = within[0][0] if within else float("nan")
    report.note(f"whole run: {run['seconds']:.1f} s, status '{widget._status.value}'; "
                f"{len(rows)} updates, first iteration reported at {first_iter:.1f} s, "
                f"indeterminate (busy) updates {len(busy)}")
    report.note(f"progress seen: {log.sample(10)}")
    report.verdict(bool(determinate), f"the bar is determinate within the frame "
                   f"({len(determinate)} updates part-way, e.g. "
                   f"{determinate[len(determinate) // 2][3] if determinate else '-'}"
                   f"/{determinate[0][2] if determinate else '-'})")
    left = [text for text in log.texts() if "left" in text]
    report.verdict(bool(left), f"a time-left estimate is shown (e.g. '{left[len(left) // 2]}')"
                   if left else "no time-left estimate in the status line")
    admm = take_result(viewer, "c: LSV-ADMM defaults")
    p, r = quality(truth, admm.data)
    report.note(f"**PSNR {p:.2f} dB**, mean ratio to truth {r:.3f}")
    data["results"]["LSV-ADMM (defaults)"] = (p, r, run["seconds"])
    iterations = [int(text.split("iteration ")[1].split("/")[0]) for _, text, _, _ in within]
    per_iteration = ((within[-1][0] - within[0][0]) / max(1, iterations[-1] - iterations[0])
                     if len(within) > 1 else float("nan"))
    report.note(f"about {per_iteration:.2f} s an iteration")

    # cancel about 2 s after the press, and about 2 s into the iterations
    for label, when in (("0.5 s after the press", 0.5), ("2 s after the press", 2.0),
                        ("2 s into the iterations", "iter")):
        mark = notices.mark()
        log.start()
        shot: dict[str, bool] = {}

        def cancel_when(when=when, shot=shot) -> bool:
            if when == "iter":
                its = [row for row in log.rows if "iteration" in row[1]]
                ready = bool(its) and time.perf_counter() - log.t0 - its[0][0] >= 2.0
            else:
                ready = time.perf_counter() - log.t0 >= when
            if ready and not shot:  # the screenshot of a run under way
                shot["done"] = True
                if when == "iter":
                    show_only(viewer, "frame12", "c: LSV-ADMM defaults")
                    screenshot(viewer, "c_admm_running.png", report, reset=False)
            return ready

        run = press(widget, timeout=400, cancel_when=cancel_when)
        if "stop_latency" not in run:
            report.verdict(False, f"cancel {label}: the run ended before the cancel")
            continue
        its = [int(t.split("iteration ")[1].split("/")[0]) for t in log.texts()
               if "iteration" in t]
        firsts = [row[0] for row in log.rows if "iteration" in row[1]]
        if firsts:
            report.note(f"cancel {label}: first iteration reported {firsts[0]:.1f} s after "
                        "the press (the preparation before it runs again at every press)")
        report.note(f"cancel {label}: pressed at {run['cancel_at']:.1f} s while "
                    f"'{run['status_at_cancel']}'; stopped {run['stop_latency']:.2f} s later "
                    f"(last iteration shown {its[-1] if its else 'none'}); status "
                    f"'{widget._status.value}'; bar {widget._progress.value}/"
                    f"{widget._progress.max}")
        quote_notices(report, notices.since(mark), "notifications")
        preparing = "preparing" in run["status_at_cancel"]
        limit = max(1.0, 2 * per_iteration)
        report.verdict(run["stop_latency"] <= limit,
                       f"cancel {label} stopped in {run['stop_latency']:.2f} s "
                       f"(an iteration ≈ {per_iteration:.2f} s)" + (
                           "; pressed during 'preparing…', it waits for the preparation "
                           "(building the reconstructor) to end" if preparing and
                           run["stop_latency"] > limit else ""))
        report.verdict("reconstruction" not in viewer.layers and widget.frames_done == 0,
                       f"cancel {label}: nothing added for the cancelled frame")


def step_d(viewer, data, opened, widget, log, report, notices) -> None:
    report.step("d. Wiener and Richardson–Lucy at their defaults")
    truth = data["truth12"]
    for method, name in (("wiener", "Wiener"), ("rl", "Richardson–Lucy")):
        widget._panel.method.value = method
        options = widget._panel.options()
        mark = notices.mark()
        log.start()
        run = press(widget)
        quote_notices(report, notices.since(mark), f"{name} notifications")
        layer = take_result(viewer, f"d: {name} defaults")
        p, r = quality(truth, layer.data)
        report.note(f"{name} {options}: {run['seconds']:.1f} s, status "
                    f"'{widget._status.value}', **PSNR {p:.2f} dB**, mean ratio to truth "
                    f"{r:.3f}, range {float(layer.data.min()):.4f}..{float(layer.data.max()):.4f} "
                    f"(truth 0..{truth.max():.4f})")
        report.note(f"progress seen: {log.sample(5)}")
        data["results"][f"{name} (defaults)"] = (p, r, run["seconds"])
        caveat = widget._panel.caveat.value
        in_units = abs(r - 1) < 0.3
        report.verdict(in_units or bool(caveat), f"{name} output in the object's units (mean "
                       f"ratio {r:.3f})" if in_units else
                       f"{name} output off the object's units (mean ratio {r:.3f}), "
                       + (f"which the widget says where the method is chosen: {caveat!r}"
                          if caveat else "which the widget does not mention"))
    report.note("all methods on this frame (PSNR dB, mean ratio, seconds press→idle): " +
                "; ".join(f"{k}: {p:.2f}, {r:.3f}, {s:.1f} s"
                          for k, (p, r, s) in data["results"].items()))


def step_e(viewer, data, opened, widget, log, report, notices) -> None:
    report.step("e. Compare mode")
    truth = data["truth12"]
    widget._panel.method.value = "svcode"
    widget._compare.value = True
    second = widget._second
    report.note(f"second method by default: {second.method.value!r} {second.options()}")
    mark = notices.mark()
    log.start()
    run = press(widget, timeout=400)
    quote_notices(report, notices.since(mark), "notifications")
    panels = [layer for layer in viewer.layers if layer.metadata.get("svcode_compare")]
    names = [layer.name for layer in panels]
    report.note(f"{run['seconds']:.1f} s; status '{widget._status.value}'; panels {names}; "
                f"results box {widget._results.value!r}")
    report.verdict(len(panels) == 2 and names[0].startswith("A: SV-CoDe") and
                   names[1].startswith("B: LSV-ADMM") and "iterations" in names[1],
                   f"panels named by method and knobs: {names}")
    grid = viewer.canvas.grid
    overlays = [bool(getattr(getattr(layer, "name_overlay", None), "visible", False))
                for layer in panels]
    shown = [layer.name for layer in viewer.layers if layer.visible]
    report.note(f"grid enabled {grid.enabled} shape {tuple(grid.shape)}; name overlays "
                f"{overlays}; visible layers {shown}")
    report.verdict(grid.enabled and all(overlays), "side by side in a grid, each labelled "
                   "in its cell")
    if len(panels) == 2:
        a, b = panels
        report.note("contrast limits A " + str(tuple(round(float(c), 4) for c in
                                                    a.contrast_limits)) + ", B " +
                    str(tuple(round(float(c), 4) for c in b.contrast_limits)))
        same = np.allclose(a.contrast_limits, b.contrast_limits)
        low, high = a.contrast_limits
        a.contrast_limits = (low, (low + high) / 2)
        pause(0.1)
        linked = np.allclose(b.contrast_limits, a.contrast_limits)
        report.verdict(same and linked, f"one contrast range for both, linked (A set to "
                       f"{tuple(round(float(c), 4) for c in a.contrast_limits)} → B "
                       f"{tuple(round(float(c), 4) for c in b.contrast_limits)})")
        a.contrast_limits = (low, high)
        for layer in panels:
            p, r = quality(truth, layer.data)
            report.note(f"{layer.name}: PSNR {p:.2f} dB, mean ratio {r:.3f}")
        report.verdict(not any("psnr" in entry for entry in widget.results),
                       "not scored by the widget (no truth of this scene)")
    screenshot(viewer, "e_compare.png", report)
    widget._compare.value = False
    grid.enabled = False
    for layer in panels:
        viewer.layers.remove(layer)


def step_f(viewer, data, opened, widget, log, report, notices, folder: Path) -> None:
    report.step("f. The 6-frame stack with SV-CoDe: progress, cancel half way, save")
    for layer in viewer.layers:
        layer.visible = layer is opened["stack6"]
    stack_layer = opened["stack6"]
    widget._layer.value = stack_layer
    widget._panel.method.value = "svcode"
    widget._full_scale.value = None  # float frames: the full scale stays 1
    viewer.dims.set_current_step(0, 2)  # the user looks at frame 2
    report.note(f"current frame {viewer.dims.current_step[0]}; the widget runs from it to the "
                "end, then backwards")
    mark = notices.mark()
    log.start()
    run = press(widget, timeout=400, cancel_when=lambda: widget.frames_done >= FRAMES // 2)
    quote_notices(report, notices.since(mark), "notifications")
    texts = log.texts()
    report.note(f"progress seen ({len(log.rows)} updates): {log.sample(10)}")
    left = [t for t in texts if "left" in t]
    report.verdict(bool(left), f"time left shown (e.g. '{left[-1]}')" if left else
                   "no time-left estimate during the stack")
    if "stop_latency" not in run:
        report.verdict(False, "the stack finished before the cancel")
        return
    report.note(f"cancel pressed at {run['cancel_at']:.1f} s with {FRAMES // 2} frames done, "
                f"while '{run['status_at_cancel']}'; stopped {run['stop_latency']:.2f} s "
                f"later; status '{widget._status.value}'; bar {widget._progress.value}/"
                f"{widget._progress.max}")
    recon = viewer.layers["reconstruction"]
    frames = recon.metadata.get("svcode_frames")
    finished = [t for t in texts if f"frame {widget.frames_done + 1} of {FRAMES}, tiles 1/1"
                in t]
    if finished:
        report.verdict(False, f"the cancel waited {run['stop_latency']:.1f} s for the frame "
                       f"under way, which reached '{finished[-1]}' (its only tile done) and was "
                       "then thrown away: with the default whole-sub-view tile 'within a batch' "
                       "means a whole frame")
    report.note(f"kept: layer {fmt_place(recon)}, frames {frames}, axis labels "
                f"{tuple(recon.axis_labels)}")
    kept = recon.data.shape[0]
    report.verdict(kept == widget.frames_done and frames is not None and
                   frames["stop"] - frames["first"] == kept,
                   f"only the {kept} frames done are kept, the metadata says which ({frames})")
    truths = data["truths"]
    if frames is not None:
        scores = [quality(truths[frames["first"] + i], recon.data[i]) for i in range(kept)]
        report.note("PSNR of the kept frames: " + ", ".join(
            f"frame {frames['first'] + i}: {p:.2f} dB (ratio {r:.3f})"
            for i, (p, r) in enumerate(scores)))
        report.verdict(tuple(recon.translate)[0] == frames["first"],
                       f"the kept frames sit at their frame index (translate "
                       f"{tuple(recon.translate)[0]})")
    path = folder / "partial_recon.tif"
    recon.save(str(path), plugin=PLUGIN)
    array, system, meta = read_tiff(path)
    report.note(f"saved with the plugin's writer → `{path.name}`: array {array.shape} "
                f"{array.dtype}, system {getattr(system, 'name', None)}, metadata "
                f"{ {k: v for k, v in meta.items() if k != 'model'} }, model "
                f"{meta.get('model', {}).get('method')!r}")
    report.verdict(meta.get("frames") == frames, f"the saved file records its frames "
                   f"({meta.get('frames')})")
    [back] = viewer.open(path, plugin=PLUGIN)
    report.note(f"reopened with the reader: {fmt_place(back)}, frames "
                f"{back.metadata.get('svcode_frames')}")
    report.verdict(tuple(back.translate)[0] == frames["first"] and
                   tuple(back.translate)[1:] == tuple(recon.translate)[1:],
                   f"reopened partial stack placed where it was: frame axis at "
                   f"{float(back.translate[0])}, expected {frames['first']}; object grid at "
                   f"{tuple(float(t) for t in back.translate[1:])} µm, before "
                   f"{tuple(float(t) for t in recon.translate[1:])} µm")
    viewer.layers.remove(back)
    show_only(viewer, "stack6", "reconstruction")
    screenshot(viewer, "f_stack_cancelled.png", report)
    take_result(viewer, "f: SV-CoDe stack (cancelled)")


def step_g(viewer, data, opened, widget, log, report, notices) -> None:
    report.step("g. The all-zero frame")
    zeros = opened["zeros"]
    for layer in viewer.layers:
        layer.visible = layer is zeros
    widget._layer.value = zeros
    for method in ("svcode", "admm"):
        widget._panel.method.value = method
        before = widget._status.value
        mark = notices.mark()
        log.start()
        run = press(widget)
        shown = notices.since(mark)
        report.note(f"{method}: status before '{before}' → after '{widget._status.value}' "
                    f"({run['seconds']:.2f} s press→idle, worker started {run['started']})")
        quote_notices(report, shown, f"{method} notifications")
        warnings = [n for n in shown if severity(n) in ("warning", "error")]
        blank = [n for n in warnings if "blank" in str(n.message)]
        report.verdict(len(blank) == 1, f"{method}: the blank frame is warned about "
                       f"{len(blank)} time(s), cause on one line "
                       f"({str(blank[0].message).splitlines()[0]!r})" if blank else
                       f"{method}: no blank-frame warning")
        status = widget._status.value
        if status.startswith("Done in"):  # its own seconds, whatever the status before
            fresh = abs(float(status.split("Done in ")[1].split(" s")[0]) - run["seconds"]) < 1.0
        else:
            fresh = status != before
        report.verdict(fresh, f"{method}: the status line tells this run ('{status}')")
        if "reconstruction" in viewer.layers:
            out = viewer.layers["reconstruction"].data
            report.note(f"{method}: output finite {bool(np.isfinite(out).all())}, range "
                        f"{float(out.min())}..{float(out.max())}")
            report.verdict(bool(np.isfinite(out).all()) and float(np.abs(out).max()) == 0.0,
                           f"{method}: the output is all zero")
            take_result(viewer, f"g: {method} zeros")
    screenshot(viewer, "g_zero.png", report)


def step_h(data, report, notices) -> None:
    report.step("h. Simulate widget, then Reconstruct on its frame")
    viewer = new_viewer()
    try:
        edges = hopper_edges()
        viewer.add_image(edges, name="hopper edges", colormap="gray")
        widget = dock(viewer, "Simulate")
        report.note(f"object layer: Grace Hopper (matplotlib `grace_hopper.jpg`) as Sobel "
                    f"edges, {edges.shape}; widget: system {widget._system_choice.source.value!r} "
                    f"(choices {list(widget._system_choice.source.choices)}), object peak "
                    f"{widget._peak.value}, noise {widget._noise.value}")
        widget._system_choice.source.value = "cm2-mini"
        scenes, recon, stray = [], None, []

        def simulate(peak: float) -> None:
            widget._peak.value = peak
            mark = notices.mark()
            count = len(viewer.layers)
            t0 = time.perf_counter()
            widget._run.native.click()
            wait_until(lambda: len(viewer.layers) >= count + 2 and widget._run.enabled, 300)
            seconds = time.perf_counter() - t0
            raw, truth = viewer.layers[-1], viewer.layers[-2]
            saturated = float(np.mean(raw.data >= 1.0))
            report.note(f"peak {peak}: {seconds:.1f} s; layers **{truth.name}** "
                        f"({fmt_place(truth)}, visible {truth.visible}, max "
                        f"{float(truth.data.max()):.3f}) and **{raw.name}** ({fmt_place(raw)}, "
                        f"max {float(raw.data.max()):.3f}, {saturated:.2%} of pixels at full "
                        "scale)")
            shown = notices.since(mark)
            quote_notices(report, shown, f"peak {peak} notifications")
            warned = any("saturated" in str(n.message) for n in shown)
            report.verdict(warned == (saturated > 0.01), f"peak {peak}: saturation "
                           f"{'warned' if warned else 'not warned'} at {saturated:.1%} "
                           "saturated (threshold 1 %)")
            stray.extend(n for n in shown if "Inconsistent units" in str(n.message))
            report.verdict(truth.metadata.get("svcode_scene") == raw.metadata.get(
                "svcode_scene") and truth.metadata.get("svcode_kind") == "object",
                f"peak {peak}: a ground-truth layer of the raw frame's scene")
            scenes.append((raw, truth))
            if recon is not None:
                report.note(f"Reconstruct now on raw {getattr(recon._layer.value, 'name', None)!r}"
                            f", truth {getattr(recon._truth.value, 'name', None)!r}")

        simulate(widget._peak.value)
        simulate(4.0)
        recon = dock(viewer, "Reconstruct")
        log = ProgressLog(recon)
        picked = recon._layer.value
        report.note(f"Reconstruct docked after two simulations: raw "
                    f"{getattr(picked, 'name', None)!r}, truth "
                    f"{getattr(recon._truth.value, 'name', None)!r}")
        report.verdict(picked is scenes[-1][0] or picked is scenes[0][0],
                       "Reconstruct docked late picks a simulated raw frame" if picked in
                       (scenes[0][0], scenes[1][0]) else
                       f"Reconstruct docked late picks {picked.name!r} (a plain image, fit 1) "
                       "although raw frames of the system's sensor (fit 2) are open")
        simulate(0.3)
        raw, truth = scenes[-1]
        report.verdict(recon._layer.value is raw and recon._truth.value is truth,
                       "after a new simulation Reconstruct moves to the new raw frame and "
                       "its own truth")
        recon._layer.value = scenes[0][0]
        report.verdict(recon._truth.value is scenes[0][1], "switching to the first raw frame "
                       "switches the truth to its own scene's")
        recon._layer.value = raw
        recon._truth.value = truth
        mark = notices.mark()
        log.start()
        run = press(recon)
        quote_notices(report, notices.since(mark), "notifications")
        out = viewer.layers["reconstruction"].data
        p, r = quality(truth.data, out)
        entry = recon.results[0] if recon.results else {}
        report.note(f"SV-CoDe on it: {run['seconds']:.1f} s, status '{recon._status.value}'")
        report.quote("results box", recon._results.value)
        report.note(f"own PSNR {p:.2f} dB (ratio {r:.3f}); widget's "
                    f"{entry.get('psnr', float('nan')):.2f} dB")
        report.verdict("psnr" in entry and abs(entry["psnr"] - p) < 0.05,
                       "the widget scores against the scene's own truth, same PSNR as here")
        stray.extend(n for n in notices.since(mark) if "Inconsistent units" in str(n.message))
        report.verdict(not stray, "no stray notices" if not stray else
                       f"{len(stray)} napari warning toasts 'Inconsistent units across layers; "
                       "units will not be used for rendering.' over 3 Simulate presses and 1 "
                       "Reconstruct press (the object layer is in pixels, the plugin's layers "
                       "in µm)")
        report.note(f"scale bar visible: {viewer.canvas.overlays.scale_bar.visible}")
        show_only(viewer, raw.name, "reconstruction")
        screenshot(viewer, "h_simulate.png", report)
    finally:
        viewer.close()


def step_i(data, report, notices) -> None:
    report.step("i. Calibration widget: drag, undo, reset a chief ray")
    viewer = new_viewer()
    try:
        [raw] = viewer.open(data["folder"] / "frame12.tif", plugin=PLUGIN)
        raw.contrast_limits = (0, float(raw.data.max()))
        widget = dock(viewer, "Calibration")
        report.note(f"raw layer chosen: {getattr(widget._layer.value, 'name', None)!r}, system "
                    f"{widget._system_choice.source.value!r}")
        mark = notices.mark()
        widget._show.native.click()
        quote_notices(report, notices.since(mark), "Show sub-views notifications")
        if "chief rays" not in viewer.layers:
            report.verdict(False, "Show sub-views drew no chief rays")
            return
        rays, boxes = viewer.layers["chief rays"], viewer.layers["sub-views"]
        system = widget.system
        report.note(f"chief rays: {len(rays.data)} points ({fmt_place(rays)}), labels "
                    f"{list(rays.text.values)[:3]}…; sub-views: {len(boxes.data)} box(es); "
                    f"offsets '{widget._offsets.value}'; undo {widget._undo.enabled}, reset "
                    f"{widget._reset.enabled}")
        report.verdict(len(rays.data) == 9 and len(boxes.data) == 1,
                       "nine labelled chief rays and one sub-view box over the raw frame")

        caught: list[warnings.WarningMessage] = []

        def drag(index: int, shift: tuple[float, float]) -> None:  # as the select mode does
            with warnings.catch_warnings(record=True) as seen:
                warnings.simplefilter("always")
                start = np.asarray(rays.data[index], dtype=float)
                rays.selected_data = {index}
                rays._move({index}, start)
                rays._move({index}, start + np.asarray(shift, dtype=float))
                rays._drag_start = None
            caught.extend(w for w in seen if "napari_svcode" in w.filename)

        drag(3, (1.0, -2.0))
        moved = widget._offsets.value
        report.quote("offsets after dragging lens 3 by (+1, −2) px", moved)
        report.note(f"lens box now {widget._lens.value}; undo {widget._undo.enabled}, reset "
                    f"{widget._reset.enabled}")
        pixel = system.object_pixel_um
        report.verdict(moved.startswith("lens 3: (+1.0, \u22122.0) px") and
                       f"{pixel:.1f}" in moved and widget._lens.value == 3,
                       "the offset is shown in pixels and µm, the box follows the ray")
        screenshot(viewer, "i_calibration.png", report)
        widget._undo.native.click()
        report.quote("offsets after Undo", widget._offsets.value)
        report.verdict(widget.system.chief_rays == system.chief_rays and
                       widget._offsets.value == "no ray moved", "Undo puts the ray back")
        drag(0, (2.0, 1.0))
        drag(8, (-1.0, 3.0))
        report.quote("offsets after dragging lens 0 and lens 8", widget._offsets.value)
        widget._reset.native.click()
        report.quote("offsets after Reset", widget._offsets.value)
        report.verdict(widget.system.chief_rays == system.chief_rays and
                       widget._offsets.value == "no ray moved" and not widget._reset.enabled,
                       "Reset puts every ray back")
        for item in {(Path(w.filename).name, w.lineno, str(w.message)) for w in caught}:
            report.quote(f"warning raised in the plugin's code ({item[0]}:{item[1]})", item[2])
        report.verdict(not caught, "no deprecation warnings from the plugin while dragging" if
                       not caught else f"{len(caught)} napari FutureWarning(s) while dragging: "
                       "the plugin reads the private `Points._drag_start` to group a drag "
                       "for Undo, which napari will remove (no earlier than 0.10)")
    finally:
        viewer.close()


# ------------------------------------------------------------------ main
def run_step(report: Report, function: Callable, *args: Any) -> None:
    try:
        function(*args)
    except Exception as err:  # recorded, and the walk-through goes on
        if not report.sections:
            report.step(function.__name__)
        report.note("exception:\n\n```\n" + traceback.format_exc() + "```")
        report.verdict(False, f"the step could not be completed: {type(err).__name__}: {err}")
    report.write()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=None,
                        help="folder for the simulated files (default: a temporary one)")
    args = parser.parse_args()
    folder = args.data or Path(tempfile.mkdtemp(prefix="svcode-walkthrough-"))
    report = Report(REPORT)
    report.head = [f"Run {time.strftime('%Y-%m-%d %H:%M')}, napari {napari.__version__}, "
                   f"torch {torch.__version__} on {torch.get_num_threads()} thread(s), Python "
                   f"{platform.python_version()}, load average "
                   f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} at the start (the "
                   "machine's 2 cores shared with other jobs: seconds are indicative).",
                   "", "PSNR: `svcode_core.evaluation.metrics.psnr` against the truth of the same "
                   "scene, data range the truth's span; *mean ratio*: mean of the output over "
                   "the mean of the truth (1 = the object's units). The departed instrument "
                   "adds 25 % out-of-focus haze that the truth does not hold, so a method that "
                   "does not model it lands near 1.2."]
    notices = Notices()
    report.step("Frames never seen by the project")
    data = make_frames(folder, report)
    report.write()

    viewer = new_viewer()
    opened: dict = {}
    run_step(report, lambda: opened.update(step_a(viewer, data, report, notices)))
    viewer.open_sample(PLUGIN, "cells")  # a truth of another scene in the viewer
    opened["frame12"].contrast_limits = (0, float(opened["frame12"].data.max()))
    widget, log = new_reconstruct(viewer)
    show_only(viewer, "frame12")
    screenshot(viewer, "a_opened.png", report)
    for function in (step_b, step_c, step_d, step_e):
        run_step(report, function, viewer, data, opened, widget, log, report, notices)
    run_step(report, step_f, viewer, data, opened, widget, log, report, notices, folder)
    run_step(report, step_g, viewer, data, opened, widget, log, report, notices)
    viewer.close()
    run_step(report, step_h, data, report, notices)
    run_step(report, step_i, data, report, notices)
    report.write()
    print(f"\nwrote {REPORT}", flush=True)


if __name__ == "__main__":
    main()
