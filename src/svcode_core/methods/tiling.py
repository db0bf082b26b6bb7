"""Patch-wise inference over the ``S × S`` sub-views: tile grid, blending, skipping.

The nine sub-views of one frame are cut into overlapping ``P × P`` tiles on a regular grid
of stride ``s`` whose last row and column of tiles sit flush with the field edge, so every
pixel is covered. The tiles run through the model in batches; each output tile is
weighted by a smooth separable window and added into preallocated accumulators, and the
sum is divided by the summed weights. Peak working memory therefore depends on ``P`` and
the batch size, not on ``S``, and the result does not depend on the batch size (tiles are
always accumulated in the same order).

Blending window
    ``w(i) = sin²(π (i + ½) / P)`` along each axis (a Hann window sampled at pixel
    centres), outer product over rows and columns. It is smooth, falls towards the tile
    border so seams do not show, and is strictly positive everywhere, so the pixels at the
    edge of the field, which only one tile covers, keep their value exactly.

Scene-adaptive skipping
    A tile whose nine input patches hold no signal is not run. "No signal" means that the
    maximum over the tile (all nine views) of the input smoothed by a 3 × 3 box filter is
    at most ``dark_offset + k · noise_floor`` (default ``k = 5``): the box filter lowers the
    noise by 3×, so pure read noise stays below the threshold over ~10⁵ pixels with
    overwhelming probability, while a single emitter does not. A skipped tile contributes
    neither output nor weight: a pixel also covered by a tile that ran takes that tile's
    output, and a pixel covered only by skipped tiles is **background, 0** (the network's
    targets are non-negative objects on a zero background). Skipping therefore changes the
    result only inside skipped tiles, where the input holds no signal.

The model is given as ``run_batch(tiles, origins) -> (demixed or None, reconstruction)``
on NumPy arrays, so this module is independent of the deep-learning framework; see
:class:`svcode_core.methods.svcode.Reconstructor` for the PyTorch side.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from ..config import N_LENSES

__all__ = [
    "DEFAULT_SKIP_FACTOR",
    "BatchRunner",
    "Cancelled",
    "TileGrid",
    "TileProgress",
    "TiledOutput",
    "blend_window",
    "box_mean_3x3",
    "exhaust",
    "iter_tiled",
    "tile_starts",
    "tiles_with_signal",
]

DEFAULT_SKIP_FACTOR = 5.0

#: ``run_batch(tiles (B, 9, P, P), origins (B, 2)) -> (demixed (B, 9, P, P) or None,
#: reconstruction (B, 1, P, P))``, all float32 NumPy arrays, origins int64 ``(row, col)``.
BatchRunner = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray | None, np.ndarray]]

T = TypeVar("T")


class Cancelled(RuntimeError):
    """The caller's cancel flag was set; the work stopped after the current batch."""


def tile_starts(size: int, patch: int, stride: int) -> np.ndarray:
    """First pixel of every tile along one axis.

    Starts are ``0, s, 2s, ...`` and the last tile is moved flush with the edge, so the
    tiles cover ``[0, size)`` with every overlap at least ``patch - stride``.

    Parameters
    ----------
    size : int
        Length of the axis (the sub-view size ``S``).
    patch : int
        Tile length ``P``, ``1 <= P <= size``.
    stride : int
        Step between tiles, ``1 <= stride <= patch``.

    Returns
    -------
    numpy.ndarray
        Increasing int64 starts; the last is ``size - patch``.

    Examples
    --------
    >>> tile_starts(10, 4, 3).tolist()
    [0, 3, 6]
    >>> tile_starts(10, 4, 4).tolist()
    [0, 4, 6]
    """
    for name, value in (("size", size), ("patch", patch), ("stride", stride)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if patch > size:
        raise ValueError(f"tile size {patch} exceeds the sub-view size {size}")
    if stride > patch:
        raise ValueError(f"stride {stride} exceeds the tile size {patch}: pixels would be missed")
    starts = np.arange(0, size - patch + 1, stride, dtype=np.int64)
    if starts[-1] != size - patch:
        starts = np.append(starts, size - patch)
    return starts


@dataclass(frozen=True)
class TileGrid:
    """Overlapping ``patch × patch`` tiles covering an ``size × size`` field.

    Attributes
    ----------
    size : int
        Field side ``S``.
    patch : int
        Tile side ``P``.
    stride : int
        Step between tiles (the last tile of each axis is flush with the edge).
    """

    size: int
    patch: int
    stride: int

    def __post_init__(self) -> None:
        tile_starts(self.size, self.patch, self.stride)  # validates

    @property
    def origins(self) -> np.ndarray:
        """Top-left ``(row, col)`` of every tile, shape ``(N, 2)`` int64, row-major order."""
        starts = tile_starts(self.size, self.patch, self.stride)
        rows, cols = np.meshgrid(starts, starts, indexing="ij")
        return np.stack([rows.ravel(), cols.ravel()], axis=1)

    def __len__(self) -> int:
        return len(tile_starts(self.size, self.patch, self.stride)) ** 2


def blend_window(patch: int) -> np.ndarray:
    """Separable blending window ``w(i) w(j)`` with ``w(i) = sin²(π (i + ½) / P)``.

    Parameters
    ----------
    patch : int
        Tile side ``P``.

    Returns
    -------
    numpy.ndarray
        ``(P, P)`` float32, strictly positive, maximal at the centre.
    """
    if patch < 1:
        raise ValueError(f"patch must be >= 1, got {patch}")
    ramp = np.sin(np.pi * (np.arange(patch) + 0.5) / patch) ** 2
    return np.outer(ramp, ramp).astype(np.float32)


def box_mean_3x3(image: np.ndarray) -> np.ndarray:
    """Mean over each pixel's 3 × 3 neighbourhood, the edge pixels repeated outside.

    Examples
    --------
    >>> box_mean_3x3(np.array([[0.0, 0.0, 9.0]])).tolist()
    [[0.0, 3.0, 6.0]]
    """
    padded = np.pad(image, 1, mode="edge")
    rows = padded[:-2] + padded[1:-1] + padded[2:]
    return (rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:]) / np.asarray(9, image.dtype)


def tiles_with_signal(views: np.ndarray, grid: TileGrid, threshold: float) -> np.ndarray:
    """Which tiles hold signal: max of the 3×3-box-smoothed input over the tile > threshold.

    Parameters
    ----------
    views : numpy.ndarray
        The nine sub-views of one frame, ``(9, S, S)``, or ``(9 · k, S, S)`` lens-major
        with context crops (only each lens's own crop is looked at).
    grid : TileGrid
    threshold : float
        Level above which a smoothed pixel counts as signal (see the module docstring).

    Returns
    -------
    numpy.ndarray
        Boolean ``(N,)`` in the order of :attr:`TileGrid.origins`.
    """
    _check_views(views, grid)
    peak = np.full(views.shape[-2:], -np.inf, dtype=np.float32)
    for view in views[:: len(views) // N_LENSES]:  # one at a time: two S × S arrays, not nine
        np.maximum(peak, box_mean_3x3(view), out=peak)
    p = grid.patch
    return np.array([peak[r : r + p, c : c + p].max() > threshold for r, c in grid.origins])


@dataclass(frozen=True)
class TileProgress:
    """Progress after one batch: ``done`` of ``total`` tiles to run (skipped ones excluded)."""

    done: int
    total: int


@dataclass
class TiledOutput:
    """Blended outputs of one frame.

    Attributes
    ----------
    reconstruction : numpy.ndarray
        ``(S, S)`` float32.
    views : numpy.ndarray or None
        ``(9, S, S)`` float32 demixed views when requested.
    tiles_run, tiles_skipped : int
    model_seconds : float
        Time spent inside ``run_batch``.
    """

    reconstruction: np.ndarray
    views: np.ndarray | None
    tiles_run: int
    tiles_skipped: int
    model_seconds: float


def _check_views(views: np.ndarray, grid: TileGrid) -> None:
    """``(9 · k, S, S)``: the nine sub-views (``k = 1``) or, lens-major, each with its
    context crops (``k = 9`` or more, :func:`~svcode_core.physics.geometry.context_views`)."""
    shape = getattr(views, "shape", type(views).__name__)
    if (not isinstance(views, np.ndarray) or views.ndim != 3 or views.shape[0] % N_LENSES
            or not views.shape[0] or views.shape[1:] != (grid.size, grid.size)):
        raise ValueError(f"sub-views must be a NumPy array of shape ({N_LENSES}, {grid.size}, "
                         f"{grid.size}) (or 9·k channels, lens-major), got {shape}")


def iter_tiled(
    run_batch: BatchRunner,
    views: np.ndarray,
    grid: TileGrid,
    batch_size: int = 8,
    active: np.ndarray | None = None,
    return_views: bool = False,
    cancel: threading.Event | None = None,
) -> Generator[TileProgress, None, TiledOutput]:
    """Run the model over the tiles of one frame, yielding progress after every batch.

    Parameters
    ----------
    run_batch : callable
        ``(tiles (B, 9 · k, P, P), origins (B, 2)) -> (demixed or None, reconstruction)``.
    views : numpy.ndarray
        ``(9, S, S)`` float32 sub-views (or ``(9 · k, S, S)``, see :func:`tiles_with_signal`).
    grid : TileGrid
    batch_size : int
        Tiles per call of ``run_batch``.
    active : numpy.ndarray, optional
        Boolean ``(N,)``: tiles to run (others are skipped, see the module docstring).
        Default: all.
    return_views : bool
        Also blend the demixed views (``run_batch`` must then return them).
    cancel : threading.Event, optional
        Checked after every batch; when set, :class:`Cancelled` is raised. Closing the
        generator (``.close()``) stops it at the same points.

    Yields
    ------
    TileProgress
        After every batch.

    Returns
    -------
    TiledOutput
        As the generator's return value (``StopIteration.value``; see :func:`exhaust`).
    """
    _check_views(views, grid)
    if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    origins = grid.origins
    if active is None:
        active = np.ones(len(origins), dtype=bool)
    active = np.asarray(active, dtype=bool)
    if active.shape != (len(origins),):
        raise ValueError(f"active must have shape ({len(origins)},), got {active.shape}")
    todo = origins[active]

    p, size = grid.patch, grid.size
    window = blend_window(p)
    weight = np.zeros((size, size), dtype=np.float32)
    recon = np.zeros((size, size), dtype=np.float32)
    demixed = np.zeros((N_LENSES, size, size), dtype=np.float32) if return_views else None
    tiles = np.empty((min(batch_size, max(len(todo), 1)), len(views), p, p), dtype=np.float32)
    model_seconds = 0.0

    for first in range(0, len(todo), batch_size):
        batch = todo[first : first + batch_size]
        for k, (r, c) in enumerate(batch):
            tiles[k] = views[:, r : r + p, c : c + p]
        start = time.perf_counter()
        out_views, out_recon = run_batch(tiles[: len(batch)], batch)
        model_seconds += time.perf_counter() - start
        _check_output(out_recon, (len(batch), 1, p, p), "reconstruction")
        if return_views:
            _check_output(out_views, (len(batch), N_LENSES, p, p), "demixed views")
        for k, (r, c) in enumerate(batch):
            weight[r : r + p, c : c + p] += window
            recon[r : r + p, c : c + p] += window * out_recon[k, 0]
            if demixed is not None:
                demixed[:, r : r + p, c : c + p] += window * out_views[k]
        yield TileProgress(done=first + len(batch), total=len(todo))
        if cancel is not None and cancel.is_set():
            raise Cancelled("reconstruction cancelled")

    covered = weight > 0
    np.divide(recon, weight, out=recon, where=covered)
    if demixed is not None:
        np.divide(demixed, weight, out=demixed, where=covered)
    return TiledOutput(
        reconstruction=recon,
        views=demixed,
        tiles_run=len(todo),
        tiles_skipped=len(origins) - len(todo),
        model_seconds=model_seconds,
    )


def _check_output(array: Any, expected: tuple[int, ...], what: str) -> None:
    shape = getattr(array, "shape", None)
    if shape is None or tuple(shape) != expected:
        raise ValueError(f"model returned {what} of shape {shape}, expected {expected}")
    if not np.isfinite(array).all():
        raise ValueError(f"model returned NaN or Inf in its {what}")


def exhaust(generator: Generator[Any, None, T]) -> T:
    """Run a progress generator to the end and return its return value."""
    while True:
        try:
            next(generator)
        except StopIteration as stop:
            return stop.value
