"""Writer: an image layer (a reconstruction) to TIFF with its system and model recorded."""

from __future__ import annotations

from typing import Any

from svcode_core.io import write_tiff

from ._layers import FRAMES_KEY, KIND_KEY, MICROMETRE, MODEL_KEY, layer_system

__all__ = ["write_image"]


def write_image(path: str, data: Any, attributes: dict) -> list[str]:
    """Write one image layer as a float32 TIFF readable by :func:`svcode_core.io.read_tiff`.

    The layer's system (``svcode_system``), kind (``svcode_kind``, default
    ``"reconstruction"``), model description (``svcode_model``) and, for a stack, the
    raw frames it holds (``svcode_frames``: ``first``, ``stop``, ``total``; a cancelled
    run keeps part of the stack) go into the file's metadata (keys ``model``, ``frames``),
    so the file can be reopened and traced to the model and frames that made it. The
    pixel size (the system's, else the layer's scale when its units are µm) goes into the
    resolution tags (:func:`svcode_core.io.write_tiff`).

    Returns
    -------
    list of str
        The path written.
    """
    metadata = attributes.get("metadata") or {}
    system = layer_system(metadata)
    extra = {"layer": attributes.get("name", "")}
    if metadata.get(MODEL_KEY) is not None:
        extra["model"] = metadata[MODEL_KEY]
    if metadata.get(FRAMES_KEY) is not None:
        extra["frames"] = dict(metadata[FRAMES_KEY])
    kind = metadata.get(KIND_KEY) or "reconstruction"
    size = system.object_pixel_um if system is not None else None
    write_tiff(path, data, system, kind=kind, extra=extra,
               pixel_size_um=size if size is not None else _layer_pixel_size(attributes))
    return [path]


def _layer_pixel_size(attributes: dict) -> float | None:
    """The layer's column scale if its units say micrometres, else ``None``."""
    units, scale = attributes.get("units"), attributes.get("scale")
    if not units or scale is None or len(scale) == 0:
        return None
    unit = str(units[-1])
    return float(scale[-1]) if unit in (MICROMETRE, "micrometer", "um") else None
