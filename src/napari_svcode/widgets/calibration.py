"""Calibration dock widget: sub-view boxes and chief rays over the raw frame, editable."""

from __future__ import annotations

import napari
import numpy as np
from magicgui.widgets import Container, FileEdit, PushButton
from napari.utils.notifications import show_info

from svcode_core.config import ConfigError, SystemConfig

from .._layers import (
    SYSTEM_KEY,
    chief_rays_from_boxes,
    notify_error,
    sub_view_boxes,
)
from ._choosers import SystemChooser, image_layer_box

__all__ = ["CalibrationWidget"]

BOXES = "sub-views"
RAYS = "chief rays"
LENS_COLOURS = ["#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231",
                "#911eb4", "#42d4f4", "#f032e6", "#bfef45"]


class CalibrationWidget(Container):
    """Check and nudge the nine sub-views of a raw CM² frame, then save ``system.json``.

    *Show sub-views* applies the chosen system to the raw layer and draws a Shapes layer
    ``"sub-views"`` (one box per lens) and a Points layer ``"chief rays"``, both labelled
    by lens and placed like the raw layer. Moving a box moves its chief ray and updates the
    system; *Save* writes it to a ``system.json``.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "raw layer")
        self._system_choice = SystemChooser()
        self._show = PushButton(text="Show sub-views")
        self._out = FileEdit(label="save to", mode="w", filter="*.json", value="system.json")
        self._save = PushButton(text="Save system.json")
        super().__init__(widgets=[self._layer, self._system_choice, self._show, self._out,
                                  self._save])
        self._show.changed.connect(self.show_sub_views)
        self._save.changed.connect(self.save)
        self.system: SystemConfig | None = None
        self._raw: napari.layers.Image | None = None

    def show_sub_views(self) -> None:
        """Apply the chosen system to the raw layer and draw its boxes and chief rays."""
        layer = self._layer.value
        if layer is None:
            notify_error("No raw image layer.", "open a raw CM² frame first (File ▸ Open)")
            return
        try:
            system = self._system_choice.system(layer.metadata)
        except (ConfigError, FileNotFoundError) as err:
            notify_error(err, "fix the system.json, or choose a preset")
            return
        if system is None:
            notify_error(f"Layer {layer.name!r} has no system configuration.",
                         "choose a preset or a system.json file above")
            return
        if tuple(layer.data.shape[-2:]) != tuple(system.sensor_shape):
            notify_error(
                f"Layer {layer.name!r} is {layer.data.shape[-2]}×{layer.data.shape[-1]} "
                f"pixels but system {system.name!r} has a {system.sensor_shape[0]}×"
                f"{system.sensor_shape[1]} sensor.",
                "choose the system of the instrument that recorded this frame",
            )
            return
        self._raw = layer
        self._apply(system)
        self._draw()

    def _apply(self, system: SystemConfig) -> None:
        self.system = system
        self._raw.metadata = {**self._raw.metadata, SYSTEM_KEY: system}

    def _draw(self) -> None:
        layers, system = self._viewer.layers, self.system
        for name in (BOXES, RAYS):
            if name in layers:
                layers.remove(name)
        translate = tuple(self._raw.translate[-2:])
        lenses = {"lens": np.arange(9)}
        boxes = self._viewer.add_shapes(
            sub_view_boxes(system), shape_type="rectangle", name=BOXES, features=lenses,
            edge_color=LENS_COLOURS, face_color="transparent", edge_width=2,
            text={"string": "lens {lens}", "color": "white", "anchor": "upper_left", "size": 9},
            translate=translate,
        )
        rays = self._viewer.add_points(
            self._ray_positions(), name=RAYS, features=lenses, face_color=LENS_COLOURS,
            size=max(4, system.sub_view_size // 40), text={"string": "{lens}", "color": "white"},
            translate=translate,
        )
        rays.editable = False
        boxes.events.data.connect(self._on_boxes_changed)
        boxes.mode = "select"

    def _ray_positions(self) -> np.ndarray:
        return np.asarray(self.system.chief_rays, dtype=float) - np.asarray(self.system.padding)

    def _on_boxes_changed(self, event) -> None:
        if event.action not in ("changed", "added", "removed"):  # act once an edit is done
            return
        boxes = self._viewer.layers[BOXES]
        if len(boxes.data) != 9:
            notify_error("The sub-view layer must keep exactly nine boxes.",
                         "press 'Show sub-views' to draw them again")
            return
        try:
            system = self.system.replace(chief_rays=chief_rays_from_boxes(boxes.data, self.system))
        except ConfigError as err:
            notify_error(err, "keep each chief ray inside the padded sensor frame")
            return
        self._apply(system)
        self._viewer.layers[RAYS].data = self._ray_positions()

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
