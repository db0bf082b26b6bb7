"""TIFF input and output that records the system configuration in every file.

Files are written with :mod:`tifffile` as float32 "shaped" TIFFs whose JSON description
holds ``{"svcode": {"system": {...}, "kind": ..., ...}}``. Reading gives back the array,
the :class:`~svcode_core.config.SystemConfig` (from the description, or from a
``system.json`` beside the file) and the remaining metadata.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import tifffile

from .config import SystemConfig
from .outputs import temporary_sibling

__all__ = [
    "atomic_path",
    "read_tiff",
    "system_beside",
    "tiff_metadata",
    "write_json_atomic",
    "write_text_atomic",
    "write_tiff",
]

METADATA_KEY = "svcode"
OME_METADATA_TAG = 65000
"""Private TIFF tag holding the ``svcode`` JSON in OME-TIFF files (whose image description
is the OME-XML)."""


def is_ome_path(path: str | Path) -> bool:
    """Whether ``path`` names an OME-TIFF (``.ome.tif`` or ``.ome.tiff``)."""
    return Path(path).name.lower().endswith((".ome.tif", ".ome.tiff"))


def write_tiff(
    path: str | Path,
    array: np.ndarray,
    system: SystemConfig | None,
    kind: str = "",
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``array`` as a float32 TIFF that records ``system`` and what the data is.

    The file is written to a unique temporary name beside ``path`` and renamed, so a crash
    never leaves a half-written file under ``path``, and two writers of one path leave one
    of the two files whole (the last rename wins), never a mixture. The temporary file is
    removed if writing fails.

    Parameters
    ----------
    path : str or Path
        Destination ``.tif`` file; parent folders are created. A name ending in
        ``.ome.tif`` or ``.ome.tiff`` gives an OME-TIFF (axes ``YX``, ``CYX`` for nine
        views, ``TYX`` for a stack) with the metadata in private tag 65000.
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
    data = np.asarray(array, dtype=np.float32)
    with atomic_path(path) as partial:
        _write_tiff_data(partial, data, kind, meta, ome=is_ome_path(path))
    return path


def _write_tiff_data(
    partial: Path, data: np.ndarray, kind: str, meta: dict[str, Any], ome: bool
) -> None:
    if ome:
        axes = {2: "YX", 3: "CYX" if kind in ("views", "demixed") else "TYX", 4: "TCYX"}
        if data.ndim not in axes:
            raise ValueError(f"an OME-TIFF takes 2 to 4 dimensions, got shape {data.shape}")
        tifffile.imwrite(
            partial, data, ome=True, photometric="minisblack",
            metadata={"axes": axes[data.ndim]},
            extratags=[(OME_METADATA_TAG, "s", 0, json.dumps({METADATA_KEY: meta}), True)],
        )
    else:
        tifffile.imwrite(partial, data, photometric="minisblack", metadata={METADATA_KEY: meta})


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A unique temporary path to write; renamed to ``path`` on success, removed on error.

    Every file the package replaces in place (TIFFs, JSON, checkpoints) is written so:
    a reader never sees a half-written file.
    """
    partial = temporary_sibling(path)
    try:
        yield partial
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


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
    tag = tif.pages[0].tags.get(OME_METADATA_TAG) if tif.pages else None
    if not meta and tag is not None:
        meta = dict(json.loads(tag.value).get(METADATA_KEY, {}))
    system_dict = meta.pop("system", None)
    if system_dict:
        return SystemConfig.from_dict(system_dict), meta
    return system_beside(tif.filehandle.path), meta


def write_json_atomic(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON through a temporary file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=2) + "\n"
    return write_text_atomic(path, text)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) through a temporary file and an atomic rename."""
    path = Path(path)
    with atomic_path(path) as partial:
        partial.write_text(text, encoding="utf-8")
    return path
