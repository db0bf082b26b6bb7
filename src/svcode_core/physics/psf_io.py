"""Import and export of PSF stacks, such as PSFs measured on a calibration grid.

A stack holds the PSFs of the nine lenses on the system's ``G × G`` PSF grid, each
``k × k`` and registered to its ideal image point (centre pixel ``(k // 2, k // 2)``),
lens-major: ``(9, G·G, k, k)`` or flattened ``(9·G·G, k, k)``. The object positions of the
grid nodes travel in a JSON file ``{"positions": [[v, u], ...]}`` (or a two-column CSV)
and must be those of :func:`svcode_core.physics.optics.psf_grid_positions`. Measured PSFs keep
their scale: the relative throughput across the field is part of the calibration.

A system whose ``psf_model`` names such a stack (as ``svcode calibrate`` writes) is built
from it everywhere: :func:`model_psfs` is what :meth:`CM2Operator.from_system
<svcode_core.physics.cm2.CM2Operator.from_system>` uses.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..config import N_LENSES, SystemConfig
from ..io import read_tiff, write_json_atomic, write_tiff
from .optics import psf_grid_positions, system_psfs

__all__ = ["load_measured_psfs", "model_psfs", "positions_path", "save_psfs"]

#: Largest distance (normalised units) between a listed position and its grid node.
POSITION_TOLERANCE = 1e-6
#: Negative values down to this fraction of the stack maximum (background subtraction
#: residue) are set to zero; anything more negative is an error.
NEGATIVE_TOLERANCE = 1e-3


def positions_path(stack_path: str | Path) -> Path:
    """The positions JSON written beside ``stack_path`` by :func:`save_psfs`."""
    stack_path = Path(stack_path)
    return stack_path.with_name(stack_path.stem + ".positions.json")


def _read_positions(positions: str | Path | np.ndarray | Sequence) -> np.ndarray:
    if not isinstance(positions, (str, Path)):
        try:
            return np.asarray(positions, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"positions must be numeric (v, u) pairs, got {positions!r}") from None
    path = Path(positions)
    if not path.is_file():
        raise FileNotFoundError(f"positions file not found: {path}")
    text = path.read_text(encoding="utf-8")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"positions file {path}: not valid JSON ({err})") from None
        if not isinstance(data, dict) or "positions" not in data:
            raise ValueError(f'positions file {path}: expected {{"positions": [[v, u], ...]}}')
        rows = data["positions"]
    else:
        rows = [row for row in csv.reader(text.splitlines()) if any(cell.strip() for cell in row)]
        if rows and not _is_number(rows[0][0]):
            rows = rows[1:]  # a header line
    try:
        return np.asarray(rows, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"positions file {path}: entries must be numeric (v, u) pairs") from None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_positions(points: np.ndarray, config: SystemConfig) -> None:
    grid = psf_grid_positions(config)
    if points.shape != grid.shape:
        raise ValueError(
            f"positions must list the {len(grid)} (v, u) nodes of the "
            f"{config.optics.psf_grid}×{config.optics.psf_grid} PSF grid (optics.psf_grid), "
            f"got shape {points.shape}"
        )
    if not np.isfinite(points).all():
        raise ValueError("positions contains NaN or Inf values")
    error = np.abs(points - grid).max(axis=1)
    bad = np.flatnonzero(error > POSITION_TOLERANCE)
    if bad.size:
        g = int(bad[0])
        raise ValueError(
            f"positions[{g}] = ({points[g, 0]:.9g}, {points[g, 1]:.9g}) is not the PSF grid node "
            f"({grid[g, 0]:.9g}, {grid[g, 1]:.9g}) (tolerance {POSITION_TOLERANCE:g}); the "
            "positions must form the regular grid linspace(-1, 1, G)², v-major"
        )


def _check_stack(stack: np.ndarray, config: SystemConfig) -> np.ndarray:
    n_grid = config.optics.psf_grid**2
    k = config.optics.kernel_size
    if stack.ndim == 3 and stack.shape[0] == N_LENSES * n_grid:
        stack = stack.reshape(N_LENSES, n_grid, *stack.shape[1:])
    if stack.ndim != 4 or stack.shape[:2] != (N_LENSES, n_grid):
        raise ValueError(
            f"PSF stack must have shape ({N_LENSES}, {n_grid}, k, k) or "
            f"({N_LENSES * n_grid}, k, k) for {N_LENSES} lenses on the {n_grid}-node grid, "
            f"got {stack.shape}"
        )
    height, width = stack.shape[2:]
    if height != width or height % 2 == 0:
        raise ValueError(f"PSF kernels must be square with an odd side, got {height}×{width}")
    if height != k:
        raise ValueError(
            f"PSF kernel side {height} does not match optics.kernel_size={k} of system "
            f"{config.name!r}"
        )
    stack = stack.astype(np.float64)
    if not np.isfinite(stack).all():
        raise ValueError("PSF stack contains NaN or Inf values")
    floor = -NEGATIVE_TOLERANCE * max(float(stack.max()), 0.0)
    if stack.min() < floor:
        index = np.unravel_index(int(np.argmin(stack)), stack.shape)
        raise ValueError(
            f"PSF stack has a negative value {stack[index]:.3g} at (lens, node, row, col) = "
            f"{tuple(int(i) for i in index)}, below -{NEGATIVE_TOLERANCE:g} × the stack maximum; "
            "subtract the background so that PSFs are non-negative"
        )
    return np.maximum(stack, 0.0)


def load_measured_psfs(
    stack_path: str | Path,
    positions: str | Path | np.ndarray | Sequence,
    config: SystemConfig,
) -> np.ndarray:
    """Read a stack of measured PSFs and check it against the system.

    Parameters
    ----------
    stack_path : str or Path
        TIFF holding ``(9, G·G, k, k)`` or ``(9·G·G, k, k)`` PSFs, lens-major, each centred on
        its ideal image point.
    positions : str, Path or array_like
        The object positions ``(v, u)`` of the grid nodes, ``(G·G, 2)``: a JSON file
        ``{"positions": [[v, u], ...]}``, a two-column CSV (optional header line), or an
        array. They must be :func:`~svcode_core.physics.optics.psf_grid_positions` of ``config``
        within ``1e-6``.
    config : SystemConfig
        Fixes ``G`` (``optics.psf_grid``) and ``k`` (``optics.kernel_size``).

    Returns
    -------
    numpy.ndarray
        ``(9, G·G, k, k)`` float64, non-negative; all-zero PSFs (no energy in the window) are
        kept as they are.

    Raises
    ------
    ValueError
        On a wrong shape, a kernel side other than ``optics.kernel_size``, positions off the
        grid (the message names the first such node), NaN/Inf values, or negative values
        below ``-1e-3`` times the stack maximum (smaller ones are set to zero).
    """
    config.validate()
    _check_positions(_read_positions(positions), config)
    stack, _, _ = read_tiff(stack_path)
    return _check_stack(np.asarray(stack), config)


def save_psfs(path: str | Path, psfs: np.ndarray, config: SystemConfig) -> tuple[Path, Path]:
    """Write a PSF stack as a float32 TIFF with its grid positions in a JSON file beside it.

    Parameters
    ----------
    path : str or Path
        Destination ``.tif``; the positions go to :func:`positions_path` of it.
    psfs : numpy.ndarray
        ``(9, G·G, k, k)`` PSFs of ``config``'s grid and kernel size.
    config : SystemConfig
        Recorded in the TIFF's metadata.

    Returns
    -------
    (Path, Path)
        The TIFF and the positions JSON, ready for :func:`load_measured_psfs`.
    """
    config.validate()
    stack = _check_stack(np.asarray(psfs), config)
    grid = config.optics.psf_grid
    tiff = write_tiff(path, stack, config, kind="psfs", extra={"psf_grid": grid})
    positions = write_json_atomic(
        positions_path(path),
        {"positions": psf_grid_positions(config).tolist(), "psf_grid": grid, "lenses": N_LENSES},
    )
    return tiff, positions


def model_psfs(config: SystemConfig) -> np.ndarray:
    """The PSFs ``(9, G·G, k, k)`` of a system: its measured stack, else its pupil model.

    Parameters
    ----------
    config : SystemConfig
        With ``psf_model`` set, the stack it names is read with its positions JSON
        (:func:`positions_path`) and checked by :func:`load_measured_psfs`; otherwise
        :func:`~svcode_core.physics.optics.system_psfs`.

    Raises
    ------
    FileNotFoundError
        If the measured stack or its positions file is missing (the message names it).
    """
    if config.psf_model is None:
        return system_psfs(config)
    stack = Path(config.psf_model)
    if not stack.is_file():
        raise FileNotFoundError(f"psf_model: measured PSF stack not found: {stack}")
    return load_measured_psfs(stack, positions_path(stack), config)
