"""Small compound widgets shared by the dock widgets: system, model and layer choice."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import napari
import numpy as np
from magicgui.widgets import ComboBox, Container, FileEdit
from napari.layers import Image

from svcode_core.config import ConfigError, SystemConfig, available_presets
from svcode_core.io import read_tiff

from .._layers import KIND_KEY, layer_metadata, layer_system
from .._resources import NO_BUNDLED_MODEL, bundled_model

__all__ = [
    "LayerOrFile",
    "ModelChooser",
    "SystemChooser",
    "ground_truth_fit",
    "image_layer_box",
    "raw_frame_fit",
    "scan_fit",
]


#: layer kinds that are never a raw frame
NOT_RAW = ("object", "reconstruction", "demixed", "mask")


def raw_frame_fit(layer: Any) -> int:
    """How well ``layer`` fits as a raw frame: 0 not at all, 1 maybe (a grey 2-D or 3-D
    image without a system), 2 a frame or stack of its system's sensor shape."""
    if not isinstance(layer, Image) or layer.rgb or layer.ndim not in (2, 3):
        return 0
    if layer.metadata.get(KIND_KEY) in NOT_RAW:
        return 0
    try:
        system = layer_system(layer.metadata)
    except (ConfigError, TypeError, ValueError):
        return 0
    if system is None:
        return 1
    return 2 if tuple(layer.data.shape[-2:]) == tuple(system.sensor_shape) else 0


def scan_fit(layer: Any) -> int:
    """How well ``layer`` fits as a point-source scan: 2 a layer read from a scan TIFF,
    1 another grey frame stack (``N × H × W``) that is not on the object grid, else 0."""
    if not isinstance(layer, Image) or layer.rgb or layer.ndim != 3:
        return 0
    kind = layer.metadata.get(KIND_KEY)
    return 2 if kind == "scan" else int(kind not in NOT_RAW)


def ground_truth_fit(layer: Any) -> int:
    """How well ``layer`` fits as a ground truth: 1 for an object layer, else 0."""
    return int(isinstance(layer, Image) and layer.metadata.get(KIND_KEY) == "object")


def image_layer_box(viewer: napari.viewer.Viewer, label: str,
                    fit: Callable[[Any], int] | None = None, nullable: bool = False,
                    tooltip: str | None = None) -> ComboBox:
    """A combo box of the viewer's image layers that follows the layer list.

    With ``fit`` (a score, 0 = does not fit), the box moves to the best-fitting layer
    whenever its current choice does not fit (or is empty) and a fitting one appears, and
    to a newly added layer that fits at least as well as its current choice (a raw frame of
    the system's shape over a plain image, a new raw frame over an older one); a new box
    starts on the best-fitting layer, the newest of equals.
    ``nullable`` adds an empty choice (shown as
    ``-----``), taken when nothing fits. ``box.refit()`` applies the rule again (for a
    ``fit`` that depends on another choice).
    """

    def choices(_widget: Any) -> list[tuple[str, Image]]:
        return [(layer.name, layer) for layer in viewer.layers if isinstance(layer, Image)]

    box = ComboBox(label=label, choices=choices, nullable=nullable, tooltip=tooltip)

    def choose_best() -> None:
        scored = [(fit(layer), index, layer) for index, layer in enumerate(viewer.layers)
                  if isinstance(layer, Image)]
        best = max(scored, key=lambda item: item[:2], default=None)
        if best is not None and best[0] > 0:
            box.value = best[2]
        elif nullable:
            box.value = None

    def refit(event: Any = None) -> None:
        box.reset_choices()
        if fit is None:
            return
        current = box.value
        score = fit(current) if current is not None else 0
        added = getattr(event, "type", None) == "inserted" and isinstance(event.value, Image)
        if added and fit(event.value) >= max(score, 1):  # the newest of the best fits
            box.value = event.value
        elif score <= 0:
            choose_best()

    for event in (viewer.layers.events.inserted, viewer.layers.events.removed):
        event.connect(refit)
    box.refit = refit
    box.reset_choices()
    if fit is not None:  # a new widget starts on the best fit, not on the first layer
        choose_best()
    return box


class SystemChooser(Container):
    """Where the system configuration comes from: the layer, a preset or a JSON file."""

    FROM_LAYER = "from the layer"
    FROM_FILE = "system.json file"

    def __init__(self, from_layer: bool = True) -> None:
        choices = ([self.FROM_LAYER] if from_layer else []) + available_presets()
        self.source = ComboBox(label="system", choices=[*choices, self.FROM_FILE])
        self.path = FileEdit(label="system file", mode="r", filter="*.json", visible=False)
        super().__init__(widgets=[self.source, self.path], labels=True)
        self.margins = (0, 0, 0, 0)
        self.source.changed.connect(self._toggle)

    def _toggle(self, source: str) -> None:
        self.path.visible = source == self.FROM_FILE

    def system(self, metadata: Mapping[str, Any] | None = None) -> SystemConfig | None:
        """The chosen system; ``None`` when it should come from a layer that has none.

        Raises
        ------
        ConfigError, FileNotFoundError
            For an invalid or missing ``system.json``.
        """
        source = self.source.value
        if source == self.FROM_LAYER:
            return layer_system(metadata or {})
        if source == self.FROM_FILE:
            return SystemConfig.load(self.path.value)
        return SystemConfig.preset(source)


class ModelChooser(Container):
    """The model: the bundled one for the system, or a ``.safetensors`` file."""

    BUNDLED = "bundled"
    FROM_FILE = "model file"

    def __init__(self) -> None:
        self.source = ComboBox(label="model", choices=[self.BUNDLED, self.FROM_FILE])
        self.path = FileEdit(label="model file", mode="r", filter="*.safetensors")
        super().__init__(widgets=[self.source, self.path], labels=True)
        self.margins = (0, 0, 0, 0)
        self.source.changed.connect(self._toggle)
        if bundled_model() is None:
            self.source.value = self.FROM_FILE
        self._toggle(self.source.value)

    def _toggle(self, source: str) -> None:
        self.path.visible = source == self.FROM_FILE

    def model_path(self, system_name: str | None = None) -> Path:
        """The model file to use (bundled for ``system_name``, or the chosen file).

        Raises
        ------
        ValueError
            No bundled model is installed, or no file is chosen.
        """
        if self.source.value == self.BUNDLED:
            path = bundled_model(system_name)
            if path is None:
                raise ValueError(NO_BUNDLED_MODEL)
            return path
        path = Path(self.path.value)
        if not path.is_file():
            raise ValueError(f"model file not found: {path}; choose a .safetensors model file")
        return path


class LayerOrFile(Container):
    """Image data from an open layer or, when no layer is chosen, from a TIFF file.

    ``label`` names both choices (``"<label> layer"``, ``"<label> file"``) and is the data
    kind recorded for a file that records none (see :func:`~napari_svcode._layers.layer_metadata`).
    """

    def __init__(self, viewer: napari.viewer.Viewer, label: str,
                 fit: Callable[[Any], int] | None = None, tooltip: str | None = None) -> None:
        self.kind = label
        self.layer = image_layer_box(viewer, f"{label} layer", fit=fit, nullable=True,
                                     tooltip=tooltip)
        self.path = FileEdit(label=f"{label} file", mode="r", filter="*.tif *.tiff",
                             tooltip="a TIFF file, read when no layer is chosen above")
        super().__init__(widgets=[self.layer, self.path], labels=True)
        self.margins = (0, 0, 0, 0)

    def read(self) -> tuple[np.ndarray, dict[str, Any], str, Image | None] | None:
        """``(data, layer metadata, name, layer)`` of the chosen layer, else of the chosen
        file (``layer`` is then ``None``); ``None`` when neither is chosen.

        Raises
        ------
        FileNotFoundError, ValueError
            A chosen file that does not exist or is not a readable TIFF.
        """
        layer = self.layer.value
        if layer is not None:
            return np.asarray(layer.data), dict(layer.metadata), layer.name, layer
        if str(self.path.value) in ("", "."):
            return None
        path = Path(self.path.value)
        if not path.is_file():
            raise FileNotFoundError(f"file not found: {path}")
        try:
            data, system, meta = read_tiff(path)
        except (OSError, ValueError) as err:  # tifffile raises both for a non-TIFF file
            raise ValueError(f"{path.name} is not a readable TIFF ({err})") from err
        return np.asarray(data), layer_metadata(system, meta.get("kind") or self.kind), \
            path.name.split(".")[0], None
