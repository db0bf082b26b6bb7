"""TIFF input and output that records the system configuration in every file.

Files are written with :mod:`tifffile` as float32 "shaped" TIFFs whose JSON description
holds ``{"svcode": {"system": {...}, "kind": ..., ...}}``. Reading gives back the array,
the :class:`~svcode_core.config.SystemConfig` (from the description, or from a
``system.json`` beside the file) and the remaining metadata.

Physical size: a file of a system with an ``object_pixel_um`` records the object-space
pixel size (raw sensor frames too: a sensor pixel over the magnification is one object
pixel, so a frame and its reconstruction overlay) in the TIFF resolution tags, in pixels
per centimetre (read by ImageJ/Fiji and most viewers), and an OME-TIFF also as
``PhysicalSizeX``/``PhysicalSizeY`` in µm. :func:`read_tiff` reports the size it finds.
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
    "add_tiff_metadata",
    "atomic_path",
    "mapped_tiff",
    "read_tiff",
    "resolution_tags",
    "system_beside",
    "tiff_metadata",
    "tiff_pixel_size",
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
    pixel_size_um: float | None = None,
) -> Path:
    """Write ``array`` as a float32 TIFF that records ``system``, what the data is and
    the size of its pixels.

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
    pixel_size_um : float, optional
        Pixel size in micrometres for the resolution tags; default: the system's
        ``object_pixel_um`` (none written when neither is known).

    Returns
    -------
    Path
        ``path``.

    Examples
    --------
    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "frame.tif"
    >>> _ = write_tiff(path, np.zeros((60, 80)), SystemConfig.tiny(), kind="measurement")
    >>> read_tiff(path)[2]
    {'kind': 'measurement', 'pixel_size_um': 10.0}
    """
    path = Path(path)
    if pixel_size_um is None and system is not None:
        pixel_size_um = system.object_pixel_um
    path.parent.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {"kind": kind}
    if system is not None:
        meta["system"] = system.to_dict()
    if extra:
        meta.update(extra)
    json.dumps(meta)  # fail here, before writing, on non-serialisable metadata
    data = np.asarray(array, dtype=np.float32)
    with atomic_path(path) as partial:
        _write_tiff_data(partial, data, kind, meta, is_ome_path(path), pixel_size_um)
    return path


def resolution_tags(pixel_size_um: float | None) -> dict[str, Any]:
    """``tifffile.imwrite`` arguments recording square pixels of ``pixel_size_um`` as
    TIFF resolution in pixels per centimetre (none for an unknown size).

    Examples
    --------
    >>> resolution_tags(3.25)
    {'resolution': (3076.923076923077, 3076.923076923077), 'resolutionunit': 'CENTIMETER'}
    """
    if pixel_size_um is None:
        return {}
    per_cm = _UM_PER["cm"] / float(pixel_size_um)
    return {"resolution": (per_cm, per_cm), "resolutionunit": "CENTIMETER"}


def _write_tiff_data(partial: Path, data: np.ndarray, kind: str, meta: dict[str, Any],
                     ome: bool, pixel_size_um: float | None) -> None:  # fmt: skip
    tags = resolution_tags(pixel_size_um)
    if ome:
        axes = {2: "YX", 3: "CYX" if kind in ("views", "demixed") else "TYX", 4: "TCYX"}
        if data.ndim not in axes:
            raise ValueError(f"an OME-TIFF takes 2 to 4 dimensions, got shape {data.shape}")
        ome_meta: dict[str, Any] = {"axes": axes[data.ndim]}
        if pixel_size_um is not None:
            for axis in "XY":
                ome_meta[f"PhysicalSize{axis}"] = float(pixel_size_um)
                ome_meta[f"PhysicalSize{axis}Unit"] = "µm"
        tifffile.imwrite(
            partial, data, ome=True, photometric="minisblack", metadata=ome_meta,
            extratags=[(OME_METADATA_TAG, "s", 0, json.dumps({METADATA_KEY: meta}), True)],
            **tags,
        )
    else:
        tifffile.imwrite(partial, data, photometric="minisblack", metadata={METADATA_KEY: meta},
                         **tags)  # fmt: skip


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
        The remaining ``svcode`` metadata (empty for foreign files), and
        ``"pixel_size_um"`` when the file records its pixel size
        (:func:`tiff_pixel_size`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    with tifffile.TiffFile(path) as tif:
        array = tif.asarray()
        system, meta = tiff_metadata(tif)
        size = tiff_pixel_size(tif)
    if size is not None:
        meta["pixel_size_um"] = size
    return array, system, meta


def mapped_tiff(path: str | Path) -> np.ndarray | None:
    """A TIFF's image data memory-mapped (read-only), or ``None`` where it cannot be:
    compressed or scattered data, or no readable TIFF (:func:`read_tiff` then says why)."""
    try:
        return tifffile.memmap(path, mode="r")
    except (OSError, ValueError, tifffile.TiffFileError):
        return None


#: micrometres per unit of the length units a TIFF may give its pixel size in
_UM_PER = {"nm": 1e-3, "um": 1.0, "µm": 1.0, "μm": 1.0, "micron": 1.0, "microns": 1.0,
           "mm": 1e3, "cm": 1e4, "m": 1e6, "inch": 25400.0}  # fmt: skip


def tiff_pixel_size(tif: tifffile.TiffFile) -> float | None:
    """The pixel size in micrometres an open TIFF records along its columns, or ``None``.

    Read from the OME ``PhysicalSizeX`` (with its unit, µm by default), else from the
    ImageJ calibration (``unit`` and resolution), else from the resolution tags in
    pixels per centimetre or per inch. A resolution without a unit (the TIFF default)
    gives ``None``.
    """
    if not tif.pages:
        return None
    page = tif.pages[0]
    if tif.is_ome and tif.ome_metadata:
        size = _ome_pixel_size(tif.ome_metadata)
        if size is not None:
            return size
    unit = None
    if tif.is_imagej:
        unit = str((tif.imagej_metadata or {}).get("unit", "")).replace("\\u00B5", "µ")
    if unit not in _UM_PER:
        unit = {2: "inch", 3: "cm"}.get(int(page.resolutionunit))
    if unit is None:
        return None
    per_unit = float(page.get_resolution()[0])  # (x, y): along the columns
    if not per_unit > 0:
        return None
    return _tidy(_UM_PER[unit] / per_unit)


def _ome_pixel_size(xml: str) -> float | None:
    import xml.etree.ElementTree as ElementTree

    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError:
        return None
    for element in root.iter():
        if element.tag.endswith("}Pixels") and "PhysicalSizeX" in element.attrib:
            unit = element.attrib.get("PhysicalSizeXUnit", "µm")
            try:
                size = float(element.attrib["PhysicalSizeX"])
            except ValueError:
                return None
            return _tidy(size * _UM_PER[unit]) if unit in _UM_PER and size > 0 else None
    return None


def _tidy(value: float) -> float:
    """``value`` to 12 significant digits: 3.25, not the 3.2500000000000004 of a ratio."""
    return float(f"{value:.12g}")


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


def add_tiff_metadata(path: str | Path, **fields: Any) -> None:
    """Add ``fields`` to the ``svcode`` metadata of a TIFF this package wrote, in place.

    Examples
    --------
    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "image.tif"
    >>> _ = write_tiff(path, np.zeros((4, 4)), None, kind="reconstruction")
    >>> add_tiff_metadata(path, exposure_gains=[2.0])
    >>> read_tiff(path)[2]
    {'kind': 'reconstruction', 'exposure_gains': [2.0]}
    """
    with tifffile.TiffFile(path, mode="r+b") as tif:
        tags = tif.pages[0].tags
        tag = tags.get(OME_METADATA_TAG) if tif.is_ome else tags.get("ImageDescription")
        document = json.loads(tag.value) if tag is not None else {}
        if not isinstance(document, dict) or METADATA_KEY not in document:
            raise ValueError(f"{Path(path).name} holds no svcode metadata to add to")
        document[METADATA_KEY].update(fields)
        tag.overwrite(json.dumps(document))


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
