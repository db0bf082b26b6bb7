"""The method chooser of the Reconstruct widget: a method and its own options.

Every method of ``svcode reconstruct --method`` is offered
(:data:`svcode_core.methods.METHODS`); only the chosen method's options are shown. The
panel turns its values into the keyword arguments of
:func:`svcode_core.methods.build_reconstructor` and estimates what a run would cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
from magicgui.widgets import CheckBox, ComboBox, Container, FileEdit, FloatSpinBox, SpinBox

from svcode_core.config import SystemConfig
from svcode_core.methods import (
    LEARNED_METHODS,
    METHOD_TITLES,
    METHODS,
    reconstructor_defaults,
    registry,
)
from svcode_core.methods.baselines import AdmmSettings
from svcode_core.methods.tiling import TileGrid

from ._choosers import ModelChooser

__all__ = ["Cost", "MethodPanel"]

#: rough CPU seconds per SV-CoDe tile of 96 × 96 pixels (larger tiles scale with area)
SECONDS_PER_TILE = 0.15
#: rough CPU seconds per LSV-ADMM / RL iteration on a 384 × 384 object grid
SECONDS_PER_ITERATION = 1.0
#: a GPU is taken to be this much faster
GPU_SPEED_UP = 20.0
#: runs estimated to take longer ask first
LONG_RUN_SECONDS = 15 * 60
#: runs estimated to need more than this share of the free memory ask first
MEMORY_SHARE = 0.8

_ADMM = registry.method("admm").defaults
_WIENER = registry.method("wiener").defaults


#: the model-based methods' options that have a widget here
_BASELINE_WIDGETS = ("rank", "iterations", "tv_weight", "balance", "boundary")


def _option_widgets(name: str) -> tuple[str, ...]:
    """The option widgets method ``name`` shows, in order."""
    if name in registry.MODEL_BASED_METHODS:
        return ("precision", *(o for o in registry.method(name).options if o in _BASELINE_WIDGETS))
    if name in LEARNED_METHODS:
        return ("weights", "precision")
    return ("model", "precision", "tile", "batch", "skip", "refine")


_OPTIONS = {name: _option_widgets(name) for name in METHODS}
_PRECISIONS = {name: registry.method(name).precisions for name in METHODS}


@dataclass
class Cost:
    """What a run is estimated to take: ``seconds`` and ``memory`` (bytes), with reasons."""

    seconds: float
    memory: int
    detail: str

    def warning(self) -> str | None:
        """A one-line warning when the run would take very long or not fit in memory."""
        available = psutil.virtual_memory().available
        if self.memory > MEMORY_SHARE * available:
            return (f"needs about {self.memory / 2**30:.1f} GiB, {available / 2**30:.1f} GiB "
                    f"free ({self.detail})")
        if self.seconds > LONG_RUN_SECONDS:
            return f"would take about {_duration(self.seconds)} ({self.detail})"
        return None


def _duration(seconds: float) -> str:
    if seconds >= 5400:
        return f"{seconds / 3600:.1f} h"
    return f"{math.ceil(seconds / 60)} min"


class MethodPanel(Container):
    """A method and its options; only the chosen method's options are visible.

    Parameters
    ----------
    label : str
        Label of the method box.
    method : str
        The method chosen at first.
    """

    def __init__(self, label: str = "method", method: str = "svcode") -> None:
        defaults = reconstructor_defaults()
        self.method = ComboBox(label=label, value=method,
                               choices=[(METHOD_TITLES[name], name) for name in METHODS],
                               tooltip="the reconstruction method (svcode reconstruct --method)")
        self.model = ModelChooser()
        self.weights = FileEdit(label="model file", mode="r", filter="*.safetensors",
                                tooltip="a model trained with svcode train --method ...")
        self.precision = ComboBox(label="precision", choices=list(_PRECISIONS["svcode"]))
        self.tile = SpinBox(label="tile size", min=0, max=8192,
                            value=defaults.get("tile_size") or 0,
                            tooltip="tile side P in pixels; 0: planned by the core "
                                    "(the whole sub-view when it fits in memory)")
        batch = defaults.get("batch_size")
        self.batch = SpinBox(label="batch size", min=0, max=1024,
                             value=batch if isinstance(batch, int) else 0,
                             tooltip="tiles per model call (more: faster, more memory); "
                                     "0: the core's default")
        self.skip = CheckBox(text="skip empty tiles", value=defaults["skip_empty"],
                             tooltip="do not run tiles without signal above the noise")
        self.refine = SpinBox(label="refine periphery", min=0, max=1000,
                              value=defaults["refine_periphery"],
                              tooltip="LSV-ADMM iterations that refine the outer ring and edge "
                                      "strips from the network's reconstruction (10: higher "
                                      "held-out scores for 2–3× the time); 0: none")
        self.rank = SpinBox(label="rank K", min=0, max=1024, value=0,
                            tooltip="low-rank order of the forward model; 0: "
                                    f"{registry.DEFAULT_RANK}, or the system's K when smaller "
                                    "(the system's K: a fraction of a dB, many times slower)")
        self.iterations = SpinBox(label="iterations", min=1, max=100_000, value=1)
        self.tv_weight = FloatSpinBox(label="TV weight λ", min=0.0, max=10.0, step=1e-5,
                                      value=AdmmSettings().tv_weight,
                                      tooltip="total-variation weight of LSV-ADMM")
        self.tv_auto = CheckBox(text="λ from each frame's noise",
                                value=_ADMM["tv_weight"] == "auto",
                                tooltip="set λ from the frame's estimated noise and mean "
                                        "level (better for dim, few-photon frames)")
        self.tv_auto.changed.connect(lambda auto: setattr(self.tv_weight, "enabled", not auto))
        self.tv_weight.enabled = not self.tv_auto.value
        self.balance = FloatSpinBox(label="balance", min=0.0, max=10.0, step=1e-4,
                                    value=_WIENER["balance"],
                                    tooltip="Laplacian regularisation weight of the Wiener "
                                            "filter")
        self.boundary = ComboBox(label="boundary", choices=["reflect", "periodic"],
                                 value=_WIENER["boundary"],
                                 tooltip="how the Wiener filter treats a view's edges")
        self._widgets = {"model": self.model, "weights": self.weights,
                         "precision": self.precision, "tile": self.tile, "batch": self.batch,
                         "skip": self.skip, "refine": self.refine, "rank": self.rank,
                         "iterations": self.iterations,
                         "tv_weight": self.tv_weight, "tv_auto": self.tv_auto,
                         "balance": self.balance, "boundary": self.boundary}
        super().__init__(widgets=[self.method, *self._widgets.values()], labels=True)
        self.margins = (0, 0, 0, 0)
        self._system = SystemConfig.preset("cm2-mini")
        self.method.changed.connect(self._show_options)
        self._show_options(self.method.value)

    # ---------------------------------------------------------------- showing
    def _show_options(self, method: str) -> None:
        shown = _OPTIONS[method]
        for name, widget in self._widgets.items():
            widget.visible = name in shown
        self.tv_auto.visible = "tv_weight" in shown
        self.precision.choices = list(_PRECISIONS[method])
        self.precision.value = "fp32"
        self.set_system(self._system)

    def set_system(self, system: SystemConfig) -> None:
        """Show the chosen method's iteration count (its default, the same for every
        system: :mod:`svcode_core.methods.registry`)."""
        self._system = system
        if "iterations" in registry.method(self.method.value).options:
            self.iterations.value = registry.method(self.method.value).defaults["iterations"]

    # ---------------------------------------------------------------- values
    def options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~svcode_core.methods.build_reconstructor` (without
        ``device``, ``weights`` and ``model``)."""
        method = self.method.value
        values = {"precision": self.precision.value}
        if method == "svcode":
            values.update(tile_size=self.tile.value or None, skip_empty=self.skip.value)
            if self.batch.value:  # else the core's default
                values["batch_size"] = self.batch.value
            if self.refine.value:
                values["refine_periphery"] = self.refine.value
        elif method in registry.MODEL_BASED_METHODS:
            values["rank"] = self.rank.value or None
            shown = {"iterations": self.iterations, "tv_weight": self.tv_weight,
                     "balance": self.balance, "boundary": self.boundary}  # fmt: skip
            values.update({option: shown[option].value
                           for option in registry.method(method).options if option in shown})
            if "tv_weight" in values and self.tv_auto.value:
                values["tv_weight"] = "auto"
        return values

    def weights_path(self, system_name: str | None = None) -> Path | None:
        """The model file of the method: SV-CoDe's (bundled or chosen), a learned baseline's
        (``None`` when none is chosen), ``None`` for the model-based baselines.

        Raises
        ------
        ValueError
            SV-CoDe without a bundled model or chosen file.
        """
        method = self.method.value
        if method == "svcode":
            return self.model.model_path(system_name)
        if method in LEARNED_METHODS:
            path = Path(self.weights.value)
            return path if path.is_file() else None
        return None

    def cost(self, system: SystemConfig, frames: int, device: str, views: bool) -> Cost:
        """Rough time and memory of reconstructing ``frames`` frames of ``system``."""
        method, size = self.method.value, system.sub_view_size
        speed = 1.0 if device == "cpu" else GPU_SPEED_UP
        memory = frames * size * size * 4 * (10 if views else 1)
        if method == "svcode":
            tile = self.tile.value or system.patch_size
            stride = system.patch_stride if not self.tile.value else max(tile // 2, 1)
            try:
                per_frame = len(TileGrid(size, tile, stride))
            except ValueError:  # the core refuses the tile size when the run starts
                return Cost(0.0, memory, "")
            tiles = per_frame * frames
            seconds = tiles * SECONDS_PER_TILE * max(1.0, (tile / 96) ** 2) / speed
            memory += reconstructor_defaults()["mask_cache_bytes"]
            detail = f"{tiles:,} tiles" if frames == 1 else (
                f"{tiles:,} tiles: {per_frame:,} a frame × {frames} frames")
            if self.refine.value:
                iterations = self.refine.value * frames
                seconds += iterations * SECONDS_PER_ITERATION * (size / 384) ** 2 / speed
                detail += f" and {iterations:,} refinement iterations"
            return Cost(seconds, memory, detail)
        if "iterations" in registry.method(method).options:
            iterations = self.iterations.value * frames
            seconds = iterations * SECONDS_PER_ITERATION * (size / 384) ** 2 / speed
            return Cost(seconds, memory, f"{iterations:,} iterations")
        return Cost(0.1 * frames, memory, f"{frames} frames")

    def describe(self) -> str:
        """The method's title."""
        return METHOD_TITLES[self.method.value]
