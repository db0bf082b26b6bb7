"""Reader: raw CM² frames and stacks (TIFF, OME-TIFF) with their system configuration."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from svcode_core.io import read_tiff

from ._layers import (
    AXIS_LABELS,
    FRAMES_KEY,
    in_micrometres,
    layer_metadata,
    object_translate,
    placement,
    show_scale_bar,
)

__all__ = ["get_reader", "read_cm2_tiff"]

SUFFIXES = (".tif", ".tiff")
OBJECT_GRID_KINDS = ("reconstruction", "object", "demixed")


def get_reader(path: str | list[str]) -> Callable[[str | list[str]], list[tuple]] | None:
    """The reader for ``path`` when it is a TIFF file (or a list of them), else ``None``."""
    paths = [path] if isinstance(path, str) else list(path)
    if not paths or not all(str(p).lower().endswith(SUFFIXES) for p in paths):
        return None
    return read_cm2_tiff


def read_cm2_tiff(path: str | list[str]) -> list[tuple]:
    """Image layers for TIFF files: a raw frame ``(H, W)`` or stack ``(T, H, W)`` each.

    The system comes from the file's metadata or a ``system.json`` beside it and is kept
    in the layer metadata (``svcode_system``); files without one open as plain images
    (set the system in the Calibration widget). Data on the object grid written by this
    package (reconstructions, ground truth, demixed views) are placed over the raw frame.
    Layers are in object-space µm (scale, units and the scale bar) when the system, else
    the file's resolution, gives the pixel size; in pixels otherwise. Leading axes are
    named (``frame``, ``lens``), and a partial stack (``svcode_frames``) sits at the raw
    frames it holds.
    """
    paths = [path] if isinstance(path, str) else list(path)
    layers = []
    sized = False
    for item in paths:
        array, system, meta = read_tiff(item)
        kind = meta.get("kind") or "measurement"
        model = meta.get("model")
        origin = (0.0, 0.0)
        if system is not None and kind in OBJECT_GRID_KINDS:
            origin = object_translate(system)
        lead = ("lens", "frame")[: array.ndim - 2] if kind == "demixed" else ("frame",)
        if len(lead) != array.ndim - 2:  # nothing this package writes
            lead = tuple(f"axis {axis}" for axis in range(array.ndim - 2))
        labels = (*lead, "y", "x")
        frames = meta.get("frames")  # a partial stack: which raw frames it holds
        lead = tuple(float(frames["first"]) if label == "frame" else 0.0
                     for label in labels[:-2]) if frames else ()  # fmt: skip
        place = placement(system, array.ndim, origin, lead,
                          pixel_size_um=meta.get("pixel_size_um"))
        sized = sized or in_micrometres(place)
        metadata = layer_metadata(system, kind, model)
        if frames is not None:
            metadata[FRAMES_KEY] = dict(frames)
        kwargs = {"name": Path(item).name.split(".")[0], "metadata": metadata, **place}
        if AXIS_LABELS:
            kwargs["axis_labels"] = labels
        layers.append((array, kwargs, "image"))
    if sized:
        show_scale_bar()
    return layers
