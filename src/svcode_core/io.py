"""TIFF input and output that records the system configuration in every file.

Files are written with :mod:`tifffile` as float32 "shaped" TIFFs whose JSON description
holds ``{"svcode": {"system": {...}, "kind": ..., ...}}``. Reading gives back the array,
the :class:`~svcode_core.config.SystemConfig` (from the description, or from a
``system.json`` beside the file) and the remaining metadata.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from .config import SystemConfig

__all__ = ["read_tiff", "system_beside", "tiff_metadata", "write_json_atomic", "write_tiff"]

METADATA_KEY = "svcode"


def write_tiff(
    path: str | Path,
    array: np.ndarray,
    system: SystemConfig | None,
    kind: str = "",
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``array`` as a float32 TIFF that records ``system`` and what the data is.

    The file is written to a temporary name and renamed, so a crash never leaves a
    half-written file under ``path``.

    Parameters
    ----------
    path : str or Path
        Destination ``.tif`` file; parent folders are created.
    array : numpy.ndarray
        Image data; stored as float32.
    system : SystemConfig or None
        The system the data belongs to (``None`` only for data independent of one).
    kind : str
        What the data is, e.g. ``"measurement"``, ``"object"``, ``"reconstruction"``.
    extra : dict, optional
        Further JSON-serialisable metadata (seed, model, method ...).

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {"kind": kind}
    if system is not None:
        meta["system"] = system.to_dict()
    if extra:
        meta.update(extra)
    json.dumps(meta)  # fail here, before writing, on non-serialisable metadata
    partial = path.with_name(path.name + ".partial")
    tifffile.imwrite(
        partial, np.asarray(array, dtype=np.float32), photometric="minisblack",
        metadata={METADATA_KEY: meta},
    )
    os.replace(partial, path)
    return path


def system_beside(path: str | Path) -> SystemConfig | None:
    """The ``system.json`` in the folder of ``path``, if there is one."""
    candidate = Path(path).with_name("system.json")
    return SystemConfig.load(candidate) if candidate.is_file() else None


def read_tiff(path: str | Path) -> tuple[np.ndarray, SystemConfig | None, dict[str, Any]]:
    """Read a TIFF and the system it was made with.

    Parameters
    ----------
    path : str or Path
        A TIFF written by this package or any other TIFF.

    Returns
    -------
    array : numpy.ndarray
        The image data as stored.
    system : SystemConfig or None
        From the file's metadata, else from ``system.json`` beside it, else ``None``.
    metadata : dict
        The remaining ``svcode`` metadata (empty for foreign files).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    with tifffile.TiffFile(path) as tif:
        array = tif.asarray()
        system, meta = tiff_metadata(tif)
    return array, system, meta


def tiff_metadata(tif: tifffile.TiffFile) -> tuple[SystemConfig | None, dict[str, Any]]:
    """The system and the other ``svcode`` metadata of an open TIFF.

    The system comes from the file's description, else from ``system.json`` beside it.
    """
    shaped = tif.shaped_metadata or ({},)
    meta = dict((shaped[0] or {}).get(METADATA_KEY, {}))
    system_dict = meta.pop("system", None)
    if system_dict:
        return SystemConfig.from_dict(system_dict), meta
    return system_beside(tif.filehandle.path), meta


def write_json_atomic(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON through a temporary file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    os.replace(partial, path)
    return path
