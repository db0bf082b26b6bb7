"""What the plugin records on napari layers, and where CM² data sit in the viewer.

Layer metadata keys
    ``SYSTEM_KEY``: the :class:`~svcode_core.config.SystemConfig` of the data;
    ``KIND_KEY``: what the data is (``"measurement"``, ``"reconstruction"``, ...);
    ``MODEL_KEY``: a JSON-serialisable description of the model that made it;
    ``SCENE_KEY``: an id of the simulated scene, shared by a raw frame and its ground truth
    (sample data, Simulate), so a truth is only scored against its own frame;
    ``FRAMES_KEY``: which frames of the raw stack a reconstruction holds
    (``{"first", "stop", "total"}``: a cancelled stack keeps a contiguous range).

Placement
    Raw frames are shown with the origin at the first sensor pixel. Data on the ``S × S``
    object grid (reconstructions, demixed views, ground truth, coordinate masks) are
    translated to where the central lens (lens 4) images the object grid on the sensor:
    ``c_4 - S // 2 - padding`` sensor pixels (one object pixel images onto one sensor
    pixel, so both have one size). Sub-view ``ℓ`` starts at ``origin_ℓ - padding``.

Physical units
    When the system knows its ``object_pixel_um``, the layers the plugin adds have that
    ``scale`` (µm per pixel, a sensor pixel taken to object space), translations in µm
    and ``units`` µm (napari 0.6 and later), so the viewer's coordinates, its scale bar
    and distances read in object-space micrometres; else everything is in pixels.
    :func:`placement` gives the keyword arguments.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from napari.layers import Layer

from svcode_core.config import SystemConfig
from svcode_core.physics.geometry import sub_view_origins

from ._errors import notify_error

__all__ = [
    "AXIS_LABELS",
    "CENTRAL_LENS",
    "FRAMES_KEY",
    "KIND_KEY",
    "MODEL_KEY",
    "SCENE_KEY",
    "SYSTEM_KEY",
    "chief_rays_from_boxes",
    "current_index",
    "layer_metadata",
    "layer_system",
    "notify_error",
    "object_translate",
    "in_micrometres",
    "place_layer",
    "placement",
    "placement_over",
    "same_scene",
    "show_scale_bar",
    "sub_view_boxes",
]

SYSTEM_KEY = "svcode_system"
KIND_KEY = "svcode_kind"
MODEL_KEY = "svcode_model"
SCENE_KEY = "svcode_scene"
FRAMES_KEY = "svcode_frames"
CENTRAL_LENS = 4
MICROMETRE = "µm"
#: whether napari layers take ``units`` (0.6 and later); before, world units are unnamed
LAYER_UNITS = "units" in inspect.signature(Layer.__init__).parameters
#: whether napari's layers take axis labels (napari 0.5 and later)
AXIS_LABELS = "axis_labels" in inspect.signature(Layer.__init__).parameters


def layer_system(metadata: Mapping[str, Any]) -> SystemConfig | None:
    """The system recorded in a layer's ``metadata`` (a config or its dictionary), if any."""
    system = metadata.get(SYSTEM_KEY)
    if isinstance(system, dict):
        return SystemConfig.from_dict(system)
    return system


def layer_metadata(system: SystemConfig | None, kind: str, model: dict | None = None,
                   scene: str | None = None) -> dict:  # fmt: skip
    """Metadata dictionary for a layer holding data of ``kind`` made with ``system``
    (of the simulated ``scene``, if given)."""
    meta: dict[str, Any] = {SYSTEM_KEY: system, KIND_KEY: kind}
    if model is not None:
        meta[MODEL_KEY] = model
    if scene is not None:
        meta[SCENE_KEY] = scene
    return meta


def same_scene(first: Mapping[str, Any], second: Mapping[str, Any]) -> bool:
    """Whether two layers' metadata record the same simulated scene (never for layers
    that record none, such as real recordings).

    Examples
    --------
    >>> same_scene({SCENE_KEY: "cells"}, {SCENE_KEY: "cells"}), same_scene({}, {})
    (True, False)
    """
    scene = first.get(SCENE_KEY)
    return scene is not None and scene == second.get(SCENE_KEY)


def object_translate(system: SystemConfig) -> tuple[float, float]:
    """Sensor-pixel position ``(row, col)`` of object-grid pixel ``(0, 0)`` (lens 4)."""
    origin = sub_view_origins(system)[CENTRAL_LENS] - np.asarray(system.padding)
    return float(origin[0]), float(origin[1])


def placement(
    system: SystemConfig | None,
    ndim: int = 2,
    origin: Sequence[float] = (0.0, 0.0),
    lead: Sequence[float] = (),
    pixel_size_um: float | None = None,
) -> dict[str, Any]:
    """Layer keyword arguments ``scale``, ``translate`` and ``units`` for data of ``system``.

    Parameters
    ----------
    system : SystemConfig or None
        Its ``object_pixel_um`` sizes the last two axes (µm per pixel).
    ndim : int
        Axes of the layer; the leading ``ndim - 2`` (frames, lenses) keep scale 1.
    origin : (float, float)
        Sensor pixel where data pixel ``(0, 0)`` lies (:func:`object_translate` for data on
        the object grid).
    lead : sequence of float
        Translations of the leading axes (world units), zero for those not given.
    pixel_size_um : float, optional
        The pixel size when the system has none (e.g. read from a file's resolution).

    Returns
    -------
    dict
        ``scale`` and ``translate`` in µm, ``units`` µm on the last two axes (napari
        0.6 and later); in pixels, without ``units``, when no pixel size is known.

    Examples
    --------
    >>> place = placement(SystemConfig.tiny(), 3, origin=(6.0, 16.0))
    >>> place["scale"], place["translate"]
    ((1.0, 10.0, 10.0), (0.0, 60.0, 160.0))
    >>> placement(None)
    {'scale': (1.0, 1.0), 'translate': (0.0, 0.0)}
    """
    size = system.object_pixel_um if system is not None else None
    size = pixel_size_um if size is None else size
    step = 1.0 if size is None else float(size)
    leading = ndim - 2
    lead = tuple(float(value) for value in lead)[:leading]
    lead += (0.0,) * (leading - len(lead))
    kwargs: dict[str, Any] = {
        "scale": (1.0,) * leading + (step, step),
        "translate": lead + (float(origin[0]) * step, float(origin[1]) * step),
    }
    if size is not None and LAYER_UNITS:
        kwargs["units"] = ("pixel",) * leading + (MICROMETRE, MICROMETRE)
    return kwargs


def placement_over(layer: Layer, ndim: int = 2, origin: Sequence[float] = (0.0, 0.0),
                   lead: Sequence[float] = ()) -> dict[str, Any]:  # fmt: skip
    """:func:`placement` in the frame of an existing layer (the raw frame): its pixel size,
    translation and units on the last two axes, so data placed by it overlay that layer
    whatever its system says.

    Examples
    --------
    >>> from napari.layers import Image
    >>> raw = Image(np.zeros((60, 80)), **placement(SystemConfig.tiny()))
    >>> placement_over(raw, 2, (6.0, 16.0))["translate"]
    (60.0, 160.0)
    """
    scale = tuple(float(value) for value in layer.scale[-2:])
    start = tuple(float(value) for value in layer.translate[-2:])
    leading = ndim - 2
    lead = tuple(float(value) for value in lead)[:leading]
    lead += (0.0,) * (leading - len(lead))
    kwargs: dict[str, Any] = {
        "scale": (1.0,) * leading + scale,
        "translate": lead + tuple(s + o * k for s, o, k in zip(start, origin, scale, strict=True)),
    }
    if LAYER_UNITS:
        kwargs["units"] = ("pixel",) * leading + tuple(str(unit) for unit in layer.units[-2:])
    return kwargs


def in_micrometres(place: Mapping[str, Any] | Layer) -> bool:
    """Whether a layer, or the keyword arguments of :func:`placement`, are in µm (on
    napari before 0.6, without units: whether the scale is not 1)."""
    units = place.get("units") if isinstance(place, Mapping) else getattr(place, "units", None)
    if LAYER_UNITS:
        return bool(units) and str(units[-1]) in (MICROMETRE, "micrometer", "um")
    scale = place["scale"] if isinstance(place, Mapping) else place.scale
    return float(scale[-1]) != 1.0


def place_layer(layer: Layer, system: SystemConfig | None) -> None:
    """Give an existing layer the pixel size of ``system`` on its last two axes, keeping
    where its pixels are relative to the sensor (its translation scales with it)."""
    if system is None or system.object_pixel_um is None:
        return
    size = float(system.object_pixel_um)
    scale = np.asarray(layer.scale, dtype=float)
    translate = np.asarray(layer.translate, dtype=float)
    translate[-2:] *= size / scale[-2:]
    scale[-2:] = size
    layer.scale, layer.translate = tuple(scale), tuple(translate)
    if LAYER_UNITS:
        layer.units = ("pixel",) * (layer.ndim - 2) + (MICROMETRE, MICROMETRE)


def show_scale_bar(viewer: Any = None) -> None:
    """Show the viewer's scale bar (the current viewer's if none is given), which reads
    µm on layers placed by :func:`placement`. On napari before 0.6, which has no layer
    units, the scale bar is told µm itself."""
    if viewer is None:
        import napari

        viewer = napari.current_viewer()
        if viewer is None:  # a reader called outside a viewer
            return
    canvas = getattr(viewer, "canvas", None)  # napari 0.9 moved the overlays there
    overlays = getattr(canvas, "overlays", None)
    scale_bar = getattr(overlays, "scale_bar", None) or viewer.scale_bar
    scale_bar.visible = True
    if not LAYER_UNITS:
        scale_bar.unit = "um"


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
