"""Small compound widgets shared by the dock widgets: system, model and layer choice."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import napari
from magicgui.widgets import ComboBox, Container, FileEdit
from napari.layers import Image

from svcode_core.config import SystemConfig, available_presets

from .._layers import layer_system
from .._resources import NO_BUNDLED_MODEL, bundled_model

__all__ = ["ModelChooser", "SystemChooser", "image_layer_box"]


def image_layer_box(viewer: napari.viewer.Viewer, label: str) -> ComboBox:
    """A combo box of the viewer's image layers that follows the layer list."""

    def choices(_widget: Any) -> list[tuple[str, Image]]:
        return [(layer.name, layer) for layer in viewer.layers if isinstance(layer, Image)]

    box = ComboBox(label=label, choices=choices)
    for event in (viewer.layers.events.inserted, viewer.layers.events.removed):
        event.connect(box.reset_choices)
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
