"""Simulated point-source scans: what a lab records to calibrate a CM² instrument.

A scan is one raw frame per source position (a bead at one object pixel) and a dark frame,
simulated through any :class:`~svcode_core.physics.simulate.Simulator` (so through a departed
instrument when it has :class:`~svcode_core.physics.departures.Departures`). It is the input of
:func:`svcode_core.physics.calibration.calibrate` and of ``svcode calibrate``.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np

from ..config import SystemConfig
from .simulate import Simulator

__all__ = ["scan_grid", "simulate_scan", "with_dark_offset", "write_positions"]


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
        ``(N, 2)`` whole-pixel ``(row, col)`` positions in the object grid.
    brightness : float
        Object value of the source pixel.
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
    for n, (row, col) in enumerate(np.asarray(positions, dtype=np.int64)):
        obj = np.zeros((size, size), np.float32)
        obj[row, col] = brightness
        frames.append(simulator.simulate(obj, seed=seed + n, noise=noise).measurement)
    empty = np.zeros((size, size), np.float32)
    dark = simulator.simulate(empty, seed=seed + len(frames), noise=noise, frames=dark_frames)
    return np.stack(frames), dark.measurement.reshape(-1, *simulator.system.sensor_shape)


def write_positions(path: str | Path, positions: np.ndarray) -> Path:
    """Write positions as the CSV ``svcode calibrate`` reads (header ``row,col``)."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["row", "col"])
        writer.writerows(np.asarray(positions, dtype=np.int64).tolist())
    return path
