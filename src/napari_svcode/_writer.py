"""Writer: an image layer (a reconstruction) to TIFF with its system and model recorded."""

from __future__ import annotations

from typing import Any

from svcode_core.io import write_tiff

from ._layers import KIND_KEY, MODEL_KEY, layer_system

__all__ = ["write_image"]


def write_image(path: str, data: Any, attributes: dict) -> list[str]:
    """Write one image layer as a float32 TIFF readable by :func:`svcode_core.io.read_tiff`.

    The layer's system (``svcode_system``), kind (``svcode_kind``, default
    ``"reconstruction"``) and model description (``svcode_model``) go into the file's
    metadata, so the file can be reopened and traced to the model that made it.

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
    kind = metadata.get(KIND_KEY) or "reconstruction"
    write_tiff(path, data, system, kind=kind, extra=extra)
    return [path]
