"""Calibration dock widget: chief rays over the raw frame and one sub-view box, editable."""

from __future__ import annotations

from typing import Any

import napari
import numpy as np
from magicgui.widgets import Container, FileEdit, PushButton, SpinBox
from napari.utils.notifications import show_info

from svcode_core.config import ConfigError, SystemConfig

from .._layers import (
    SYSTEM_KEY,
    chief_rays_from_boxes,
    notify_error,
    sub_view_boxes,
)
from ._choosers import SystemChooser, image_layer_box, raw_frame_fit

__all__ = ["CalibrationWidget"]

BOXES = "sub-views"
RAYS = "chief rays"
LENS_COLOURS = ["#e6194b", "#3cb44b", "#ffe119", "#4363d8", "#f58231",
                "#911eb4", "#42d4f4", "#f032e6", "#bfef45"]


class CalibrationWidget(Container):
    """Check and nudge the nine chief rays of a raw CM² frame, then save ``system.json``.

    *Show sub-views* applies the chosen system to the raw layer and draws a Points layer
    ``"chief rays"`` (one point per lens, labelled ``lens ℓ`` beside it) and a Shapes layer
    ``"sub-views"`` with the ``S × S`` box of one lens at a time (the *lens* box, or the
    ray last clicked or moved), both placed like the raw layer. Dragging a ray moves its
    box, dragging the box moves its ray; either updates the system, and *Save* writes it
    to a ``system.json``.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "raw layer", fit=raw_frame_fit)
        self._system_choice = SystemChooser()
        self._show = PushButton(text="Show sub-views")
        self._lens = SpinBox(label="lens", min=0, max=8, value=4,
                             tooltip="the lens whose sub-view box is drawn (0–8, row by row); "
                                     "clicking a chief ray chooses it too")
        self._out = FileEdit(label="save to", mode="w", filter="*.json", value="system.json")
        self._save = PushButton(text="Save system.json")
        super().__init__(widgets=[self._layer, self._system_choice, self._show, self._lens,
                                  self._out, self._save])
        self._show.changed.connect(self.show_sub_views)
        self._save.changed.connect(self.save)
        self._lens.changed.connect(self._draw_box)
        self.system: SystemConfig | None = None
        self._raw: napari.layers.Image | None = None
        self._updating = False

    def show_sub_views(self) -> None:
        """Apply the chosen system to the raw layer and draw its chief rays and one box."""
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

    # ---------------------------------------------------------------- drawing
    def _draw(self) -> None:
        layers, system = self._viewer.layers, self.system
        for name in (BOXES, RAYS):
            if name in layers:
                layers.remove(name)
        translate = tuple(self._raw.translate[-2:])
        size = max(8, system.sub_view_size // 24)
        boxes = self._viewer.add_shapes(
            [self._box(self._lens.value)], shape_type="rectangle", name=BOXES,
            edge_color=LENS_COLOURS[self._lens.value], face_color="transparent",
            edge_width=2, translate=translate,
        )
        rays = self._viewer.add_points(
            self._ray_positions(), name=RAYS, features={"lens": np.arange(9)},
            face_color=LENS_COLOURS, border_color="white", size=size, translate=translate,
            text={"string": "lens {lens}", "color": "white", "size": 10,
                  "anchor": "center", "translation": [-1.2 * size, 0]},
        )
        boxes.events.data.connect(self._on_box_moved)
        rays.events.data.connect(self._on_rays_moved)
        rays.selected_data.events.items_changed.connect(self._on_ray_selected)
        rays.mode = "select"
        layers.selection.active = rays

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
    def _set_rays(self, rays: tuple, lens: int, redraw_rays: bool) -> None:
        """Apply moved chief rays and show lens ``lens``'s box; redraw the rays when they
        were moved through the box, or were refused (a ray being dragged is left alone)."""
        try:
            self._apply(self.system.replace(chief_rays=rays))
        except ConfigError as err:
            notify_error(err, "keep each chief ray inside the padded sensor frame")
            redraw_rays = True
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
        self._set_rays(tuple((int(row), int(col)) for row, col in positions), lens, False)

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
