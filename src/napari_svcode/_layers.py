"""What the plugin records on napari layers, and where CM² data sit in the viewer.

Layer metadata keys
    ``SYSTEM_KEY``: the :class:`~svcode_core.config.SystemConfig` of the data;
    ``KIND_KEY``: what the data is (``"measurement"``, ``"reconstruction"``, ...);
    ``MODEL_KEY``: a JSON-serialisable description of the model that made it.

Placement
    Raw frames are shown in sensor pixels with the origin at the first sensor pixel. Data
    on the ``S × S`` object grid (reconstructions, demixed views, ground truth, coordinate
    masks) are translated to where the central lens (lens 4) images the object grid on
    the sensor: ``c_4 - S // 2 - padding`` (one object pixel images onto one sensor pixel,
    so the scale is 1). Sub-view ``ℓ`` starts at ``origin_ℓ - padding`` in sensor pixels.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from napari.layers import Layer

from svcode_core.config import SystemConfig
from svcode_core.physics.geometry import sub_view_origins

from ._errors import notify_error

__all__ = [
    "CENTRAL_LENS",
    "KIND_KEY",
    "MODEL_KEY",
    "SYSTEM_KEY",
    "chief_rays_from_boxes",
    "current_index",
    "layer_metadata",
    "layer_system",
    "notify_error",
    "object_translate",
    "sub_view_boxes",
]

SYSTEM_KEY = "svcode_system"
KIND_KEY = "svcode_kind"
MODEL_KEY = "svcode_model"
CENTRAL_LENS = 4


def layer_system(metadata: Mapping[str, Any]) -> SystemConfig | None:
    """The system recorded in a layer's ``metadata`` (a config or its dictionary), if any."""
    system = metadata.get(SYSTEM_KEY)
    if isinstance(system, dict):
        return SystemConfig.from_dict(system)
    return system


def layer_metadata(system: SystemConfig | None, kind: str, model: dict | None = None) -> dict:
    """Metadata dictionary for a layer holding data of ``kind`` made with ``system``."""
    meta: dict[str, Any] = {SYSTEM_KEY: system, KIND_KEY: kind}
    if model is not None:
        meta[MODEL_KEY] = model
    return meta


def object_translate(system: SystemConfig) -> tuple[float, float]:
    """Sensor-pixel position ``(row, col)`` of object-grid pixel ``(0, 0)`` (lens 4)."""
    origin = sub_view_origins(system)[CENTRAL_LENS] - np.asarray(system.padding)
    return float(origin[0]), float(origin[1])


def sub_view_boxes(system: SystemConfig) -> list[np.ndarray]:
    """The nine sub-views as napari rectangles ``[[r0, c0], [r1, c1]]`` in sensor pixels.

    A box spans the pixel edges of its ``S × S`` crop (pixel ``i`` covers ``i ± ½``).
    """
    size = system.sub_view_size
    starts = sub_view_origins(system) - np.asarray(system.padding) - 0.5
    return [np.array([start, start + size], dtype=float) for start in starts]


def chief_rays_from_boxes(boxes: list[np.ndarray], system: SystemConfig) -> tuple:
    """Chief rays (padded-sensor pixels) of nine boxes drawn as by :func:`sub_view_boxes`.

    Each box's centre gives its sub-view origin (rounded to a whole pixel), so a moved box
    keeps the crop it covers; a resized one keeps its centre.
    """
    size = system.sub_view_size
    rays = []
    for vertices in boxes:
        centre = np.asarray(vertices, dtype=float).reshape(-1, 2).mean(axis=0)
        origin = np.rint(centre - (size - 1) / 2).astype(int)
        ray = origin + size // 2 + np.asarray(system.padding)
        rays.append((int(ray[0]), int(ray[1])))
    return tuple(rays)


def current_index(layer: Layer, point: tuple[float, ...]) -> tuple[int, ...]:
    """Indices of ``layer``'s leading (non-displayed) axes at the viewer's ``point``."""
    position = np.asarray(layer.world_to_data(point), dtype=float)
    leading = layer.data.shape[: layer.ndim - 2]
    return tuple(
        int(np.clip(np.rint(value), 0, extent - 1))
        for value, extent in zip(position[: len(leading)], leading, strict=True)
    )
