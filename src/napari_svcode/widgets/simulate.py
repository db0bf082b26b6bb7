"""Simulate dock widget: any image layer → a raw CM² frame of the chosen system."""

from __future__ import annotations

import uuid
from pathlib import Path

import napari
import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, FloatSpinBox, PushButton, SpinBox
from napari.qt.threading import FunctionWorker
from napari.utils.notifications import show_warning

from svcode_core.config import ConfigError, SystemConfig
from svcode_core.phantoms import from_image
from svcode_core.physics.cm2 import simulation_cost
from svcode_core.physics.departures import NAMED_SETS
from svcode_core.physics.simulate import Simulation

from .._errors import notify_warning
from .._layers import (
    current_index,
    in_micrometres,
    layer_metadata,
    notify_error,
    object_translate,
    placement,
    show_scale_bar,
)
from .._resources import simulator
from .._workers import function_worker
from ._choosers import SystemChooser, image_layer_box

__all__ = ["SimulateWidget"]

#: simulations estimated above these are announced before they start
LARGE_MEMORY, LONG_SECONDS = 1 << 30, 10.0
#: a simulated frame with more of its pixels at the sensor's full scale is warned about
SATURATED = 0.01


class SimulateWidget(Container):
    """Image an object through a CM² system: for teaching and for checking a calibration.

    The displayed plane of the chosen layer is cropped to a square, resized to the
    ``S × S`` object grid and normalised (:func:`svcode_core.phantoms.from_image`), then
    scaled to the chosen *object peak* (its brightest pixel, in units of the sensor's full
    scale: the brightness) and imaged with the system's SV forward model and sensor noise
    in a worker thread, or through an *instrument* that departs from the system by a named
    set of departures (as ``svcode simulate --departures``; the frame records the nominal
    system). The raw frame is added as ``"<layer> (simulated raw)"`` and the
    object as ``"<layer> (simulated truth)"`` on the object grid over it (hidden), both
    with the system and one scene id in their metadata (the Reconstruct widget scores
    against this truth), in object-space µm when the system knows its pixel size. A frame
    with more than 1 % of its pixels saturated is warned about. An object layer in pixels
    is placed over the truth in µm (its centred square on the object grid), so that every
    layer shares one unit.
    A simulation estimated (:func:`svcode_core.physics.cm2.simulation_cost`) to need more than
    1 GiB or 10 s is announced with its estimate first; one needing more memory than the
    machine has available is refused.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "object layer")
        self._system_choice = SystemChooser(from_layer=False)
        self._seed = SpinBox(label="noise seed", min=0, max=2**31 - 1, value=0)
        self._noise = CheckBox(text="sensor noise", value=True)
        self._departures = ComboBox(
            label="instrument", choices=list(NAMED_SETS), value="none",
            tooltip="the true instrument: the system itself (none) or a named set of "
                    "departures from it, as svcode simulate --departures (realistic: a "
                    "drifted array, other aberrations, haze and a real camera); the frame "
                    "records the nominal system, as a recording would")
        self._peak = FloatSpinBox(label="object peak", min=0.001, max=100.0, step=0.05,
                                  value=1.0, tooltip="brightness: the object's brightest pixel "
                                  "in units of the sensor's full scale (lower it if the raw "
                                  "frame saturates)")
        self._run = PushButton(text="Simulate")
        super().__init__(widgets=[self._layer, self._system_choice, self._departures,
                                  self._peak, self._seed, self._noise, self._run])
        self._run.changed.connect(self.start)
        self.worker: FunctionWorker | None = None

    def start(self) -> FunctionWorker | None:
        """Start simulating the chosen layer's displayed plane (errors become notices)."""
        layer = self._layer.value
        if layer is None:
            notify_error("No image layer to simulate.", "open or draw an image first")
            return None
        try:
            system = self._system_choice.system()
        except (ConfigError, FileNotFoundError) as err:
            notify_error(err, "fix the system.json, or choose a preset")
            return None
        plane = np.asarray(layer.data[current_index(layer, self._viewer.dims.point)])
        try:
            obj = from_image(plane, system.sub_view_size) * np.float32(self._peak.value)
        except ValueError as err:
            notify_error(err, "choose a grey or RGB image without NaN or Inf values")
            return None

        if not self._affordable(system):
            return None

        departures = self._departures.value

        def run() -> Simulation:
            return simulator(system, departures).simulate(obj, seed=self._seed.value,
                                                          noise=self._noise.value)

        worker = function_worker(run, lambda scene: self._add(layer, scene, system),
                                 "choose a smaller system, or free memory and try again")
        self.worker = worker
        self._run.enabled = False
        worker.finished.connect(lambda: setattr(self._run, "enabled", True))
        worker.start()
        return worker

    @staticmethod
    def _affordable(system: SystemConfig) -> bool:
        """Announce a large simulation's estimated cost; ``False`` if memory is short."""
        cost = simulation_cost(system)
        need = f"about {cost.memory / 2**30:.1f} GiB of memory and {cost.seconds:.0f} s"
        available = _available_memory()
        if available is not None and cost.memory > available:
            notify_error(f"Simulating {system.name} needs {need}, but only "
                         f"{available / 2**30:.1f} GiB is available.",
                         "close other programs, or choose a smaller system")
            return False
        if cost.memory > LARGE_MEMORY or cost.seconds > LONG_SECONDS:
            show_warning(f"Simulating {system.name} (K = {cost.rank}): {need}.")
        return True

    def _add(self, source: napari.layers.Image, scene: Simulation,
             system: SystemConfig) -> None:
        name = source.name
        scene_id = f"simulated {name} seed {self._seed.value} {uuid.uuid4().hex[:8]}"
        on_grid = placement(system, 2, object_translate(system))
        if in_micrometres(on_grid) and not in_micrometres(source):
            _place_over_truth(source, on_grid, system.sub_view_size)
        self._viewer.add_image(scene.object, name=f"{name} (simulated truth)",
                               colormap="magma", visible=False,
                               metadata=layer_metadata(system, "object", scene=scene_id),
                               **on_grid)
        place = placement(system)
        self._viewer.add_image(scene.measurement, name=f"{name} (simulated raw)",
                               colormap="gray", **place,
                               metadata=layer_metadata(system, "measurement", scene=scene_id))
        if in_micrometres(place):
            show_scale_bar(self._viewer)
        full = system.noise.saturation  # the sensor's clipping level
        saturated = float(np.mean(scene.measurement >= full))
        if saturated > SATURATED:
            notify_warning(f"{saturated:.0%} of the simulated frame's pixels are saturated "
                           f"(at the sensor's full scale {full:g})",
                           "lower the object peak (brightness) and simulate again")


def _place_over_truth(source: napari.layers.Image, on_grid: dict, size: int) -> None:
    """Put a plain image layer in pixels where the simulation put its object: its centred
    square (what :func:`~svcode_core.phantoms.from_image` keeps) over the ``size``-pixel
    object grid placed by ``on_grid``, in the same units (mixed units make napari warn at
    every redraw and drop the units)."""
    rows, cols = source.data.shape[-3:-1] if source.rgb else source.data.shape[-2:]
    side = min(rows, cols)
    grid = [float(step) for step in on_grid["scale"]]
    pixel = [step * size / side for step in grid]
    # pixel centres: a resize maps areas, so the square's first centre sits half a source
    # pixel less half an object pixel from the grid's edge
    corner = [float(at) - (extent - side) // 2 * step + (step - unit) / 2
              for at, extent, step, unit
              in zip(on_grid["translate"], (rows, cols), pixel, grid, strict=True)]
    lead = source.ndim - 2
    source.scale = (*tuple(source.scale)[:lead], *pixel)
    source.translate = (*tuple(source.translate)[:lead], *corner)
    if "units" in on_grid:
        source.units = (*tuple(source.units)[:lead], *on_grid["units"])


def _available_memory() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes (``None`` where it is unknown)."""
    try:
        lines = Path("/proc/meminfo").read_text().splitlines()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in lines if ":" in line)
    value = fields.get("MemAvailable", "").split()
    return int(value[0]) * 1024 if value else None
