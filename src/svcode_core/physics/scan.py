"""Simulated point-source scans: what a lab records to calibrate a CM² instrument.

A scan is one raw frame per source position (a point source on the object grid, on a pixel
or between pixels) and a dark frame, simulated through any
:class:`~svcode_core.physics.simulate.Simulator` (so through a departed instrument when it
has :class:`~svcode_core.physics.departures.Departures`). It is the input of
:func:`svcode_core.physics.calibration.calibrate` and of ``svcode calibrate``.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np

from ..config import SystemConfig
from .simulate import Simulator

__all__ = ["bead_object", "scan_grid", "simulate_scan", "with_dark_offset", "write_positions"]


def scan_grid(system: SystemConfig, steps: int) -> np.ndarray:
    """A ``steps × steps`` raster of whole-pixel positions over the object grid, row-major.

    Parameters
    ----------
    system : SystemConfig
    steps : int
        Positions per axis, at least ``optics.psf_grid`` (to determine the PSF grid).

    Returns
    -------
    numpy.ndarray
        ``(steps², 2)`` int64 ``(row, col)``, from pixel 0 to ``S - 1`` along each axis.
    """
    if steps < 2:
        raise ValueError(f"steps must be >= 2, got {steps}")
    axis = np.rint(np.linspace(0, system.sub_view_size - 1, steps)).astype(np.int64)
    rows, cols = np.meshgrid(axis, axis, indexing="ij")
    return np.stack([rows.ravel(), cols.ravel()], axis=1)


def with_dark_offset(system: SystemConfig, offset: float) -> SystemConfig:
    """``system`` whose camera adds ``offset`` before clipping (a camera's black level).

    A black level several read-noise deviations above zero keeps the noise of dark
    pixels from being clipped at zero, so a dark frame subtracts it without bias.
    """
    return system.replace(noise=dataclasses.replace(system.noise, dark_offset=float(offset)))


def simulate_scan(
    simulator: Simulator,
    positions: np.ndarray,
    brightness: float = 1.0,
    seed: int = 0,
    noise: bool = True,
    dark_frames: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw frames of a point source at each position, and a dark-frame stack.

    Parameters
    ----------
    simulator : Simulator
        The instrument scanned (nominal or departed).
    positions : numpy.ndarray
        ``(N, 2)`` ``(row, col)`` positions in object pixels, fractions allowed
        (:func:`bead_object`).
    brightness : float
        Total object value of the source (the value of its pixel when it sits on one).
    seed : int
        Seed of the noise; frame ``n`` uses ``seed + n``, dark frames follow.
    noise : bool
        Read through the camera model (else the expected readings).
    dark_frames : int
        Frames with no source, returned as the dark stack.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        Frames ``(N, H, W)`` and dark frames ``(dark_frames, H, W)``, float32.
    """
    size = simulator.system.sub_view_size
    frames = []
    for n, position in enumerate(np.asarray(positions, dtype=np.float64).reshape(-1, 2)):
        obj = bead_object(size, position) * np.float32(brightness)
        frames.append(simulator.simulate(obj, seed=seed + n, noise=noise).measurement)
    empty = np.zeros((size, size), np.float32)
    dark = simulator.simulate(empty, seed=seed + len(frames), noise=noise, frames=dark_frames)
    return np.stack(frames), dark.measurement.reshape(-1, *simulator.system.sensor_shape)


def bead_object(size: int, position: np.ndarray) -> np.ndarray:
    """A unit point source at ``position`` ``(row, col)`` on the ``size × size`` object grid.

    On a whole pixel, that pixel alone. Between pixels, the point as the grid samples it:
    ``sinc(i - row) · sinc(j - col)``, whose image is the image of a whole-pixel point
    moved by the fraction through a Fourier shift (within 3 % of the pupil model's own
    sub-pixel image on ``cm2-mini``; the tails are cut at the grid's edges).

    Examples
    --------
    >>> bead_object(4, (1, 2))[1].tolist()
    [0.0, 0.0, 1.0, 0.0]
    >>> bead_object(4, (1, 1.5))[1].astype(float).round(3).tolist()
    [-0.212, 0.637, 0.637, -0.212]
    """
    axis = np.arange(size, dtype=np.float64)
    row, col = (_samples(axis, float(value)) for value in position)
    return np.outer(row, col).astype(np.float32)


def _samples(axis: np.ndarray, x: float) -> np.ndarray:
    """``sinc(axis - x)``, exactly 1 and 0 when ``x`` is a whole pixel."""
    return (axis == x).astype(np.float64) if x == round(x) else np.sinc(axis - x)


def write_positions(path: str | Path, positions: np.ndarray) -> Path:
    """Write positions as the CSV ``svcode calibrate`` reads: header ``row,col``, then one
    line per frame in object pixels (whole numbers as such, fractions to 1e-6 px)."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["row", "col"])
        for position in np.asarray(positions, dtype=np.float64).reshape(-1, 2):
            writer.writerow([_decimal(value) for value in position])
    return path


def _decimal(value: float) -> str:
    """``value`` to 1e-6 without trailing zeros: ``40``, ``12.5``."""
    return f"{value:.6f}".rstrip("0").rstrip(".")
