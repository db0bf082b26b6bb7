"""Degenerate inputs of a simulation: objects with nothing to image, systems that image
nothing onto the sensor.

:func:`check_object` refuses an object that is zero everywhere (an image file that is
constant, e.g. 1×1, normalises to zero). :func:`check_system_geometry` refuses a system
none of whose nine chief rays falls on the sensor (nothing of the object's centre reaches
it), and warns about lenses whose chief ray is off the sensor or shared with another lens.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..config import SystemConfig

__all__ = ["check_object", "check_system_geometry", "lenses_off_sensor"]


def check_object(obj: np.ndarray, source: str) -> None:
    """Raise :class:`ValueError` if ``obj`` (made from ``source``) is zero everywhere."""
    if not np.any(obj):
        raise ValueError(
            f"the object made from {source} is zero everywhere: the image is constant (or "
            "1×1), and normalising it to [0, 1] leaves nothing to image; use an image with "
            "structure, or a phantom kind"
        )


def lenses_off_sensor(system: SystemConfig) -> list[int]:
    """The lenses whose chief ray lies outside the raw sensor (in the padding)."""
    rows, cols = system.sensor_window
    return [
        lens
        for lens, (r, c) in enumerate(system.chief_rays)
        if not (rows.start <= r < rows.stop and cols.start <= c < cols.stop)
    ]


def check_system_geometry(system: SystemConfig) -> None:
    """Refuse a system that images nothing onto its sensor; warn about odd lenses.

    Raises
    ------
    ValueError
        If every chief ray lies outside the sensor.
    """
    off = lenses_off_sensor(system)
    height, width = system.sensor_shape
    if len(off) == len(system.chief_rays):
        raise ValueError(
            f"system {system.name!r}: all nine chief rays lie outside the {height}×{width} "
            f"sensor (rows {system.sensor_window[0].start}–{system.sensor_window[0].stop - 1}, "
            f"cols {system.sensor_window[1].start}–{system.sensor_window[1].stop - 1} of the "
            "padded frame), so no lens images the object's centre onto it; check chief_rays "
            "and padding"
        )
    if off:
        warnings.warn(
            f"system {system.name!r}: the chief rays of lenses {off} lie outside the sensor; "
            "their views are partly or wholly lost",
            UserWarning,
            stacklevel=2,
        )
    seen: dict[tuple[int, int], int] = {}
    for lens, ray in enumerate(system.chief_rays):
        if tuple(ray) in seen:
            warnings.warn(
                f"system {system.name!r}: lenses {seen[tuple(ray)]} and {lens} share the "
                f"chief ray {tuple(ray)}, so their views coincide",
                UserWarning,
                stacklevel=2,
            )
        seen.setdefault(tuple(ray), lens)
