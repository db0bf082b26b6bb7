"""The exact (slow) spatially varying convolution and the low-rank error table.

:func:`sv_convolve_reference` scatters every nonzero object pixel with its own PSF,
interpolated from the PSF grid with the same basis as the low-rank model
(:func:`svcode_core.physics.lowrank.interpolation_basis`). The low-rank operator at full rank
reproduces it to float precision, so :func:`lowrank_error` measures the truncation
error of each rank ``K`` alone. Conventions are those of :mod:`svcode_core.physics.lowrank`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch

from .lowrank import LowRankSVOperator, decompose_psfs, interpolation_basis

__all__ = ["LowRankError", "lowrank_error", "sv_convolve_reference"]


def sv_convolve_reference(
    x: np.ndarray,
    grid_psfs: np.ndarray,
    basis_rows: np.ndarray,
    basis_cols: np.ndarray,
    chunk_elements: int = 1 << 22,
) -> np.ndarray:
    """Exact SV convolution: every object pixel blurred by its own interpolated PSF.

    ``y = Σ_r x(r) · PSF(r)`` placed with its centre at ``r``, where
    ``PSF(i, j) = Σ_{a,b} basis_rows[a, i] · basis_cols[b, j] · grid_psfs[a·G_c + b]``;
    zero boundary, output the size of ``x``. Only nonzero pixels cost time (processed in
    chunks of about ``chunk_elements`` PSF samples).

    Parameters
    ----------
    x : array_like
        Object, shape ``(H, W)``.
    grid_psfs : array_like
        PSFs on the grid, shape ``(G_r·G_c, h, w)`` with odd ``h, w``, row-node-major.
    basis_rows, basis_cols : array_like
        Interpolation basis along rows ``(G_r, H)`` and columns ``(G_c, W)``.
    chunk_elements : int
        Working-memory bound: number of PSF samples built per chunk.

    Returns
    -------
    numpy.ndarray
        Float64 image, shape ``(H, W)``.
    """
    x = np.asarray(x, dtype=np.float64)
    grid_psfs = np.asarray(grid_psfs, dtype=np.float64)
    basis_rows = np.asarray(basis_rows, dtype=np.float64)
    basis_cols = np.asarray(basis_cols, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must be a 2-D image, got shape {x.shape}")
    rows, cols = x.shape
    n_grid_rows, n_grid_cols = basis_rows.shape[0], basis_cols.shape[0]
    if basis_rows.shape != (n_grid_rows, rows) or basis_cols.shape != (n_grid_cols, cols):
        raise ValueError(
            f"basis_rows {basis_rows.shape} and basis_cols {basis_cols.shape} must be "
            f"(G_r, {rows}) and (G_c, {cols})"
        )
    if grid_psfs.ndim != 3 or grid_psfs.shape[0] != n_grid_rows * n_grid_cols:
        raise ValueError(
            f"grid_psfs must have shape ({n_grid_rows * n_grid_cols}, h, w), got {grid_psfs.shape}"
        )
    height, width = grid_psfs.shape[1:]
    if height % 2 == 0 or width % 2 == 0:
        raise ValueError(f"PSF sizes must be odd, got {height}x{width}")
    for array, name in ((x, "x"), (grid_psfs, "grid_psfs")):
        if not np.isfinite(array).all():
            raise ValueError(f"{name} contains NaN or Inf values")

    full_cols = cols + width - 1
    full = np.zeros((rows + height - 1) * full_cols)
    psf_matrix = grid_psfs.reshape(-1, height * width)
    offsets = (np.arange(height)[:, None] * full_cols + np.arange(width)[None, :]).ravel()
    pixel_rows, pixel_cols = np.nonzero(x)
    chunk = max(1, chunk_elements // (height * width))
    for start in range(0, pixel_rows.size, chunk):
        r = pixel_rows[start : start + chunk]
        c = pixel_cols[start : start + chunk]
        phi = basis_rows[:, None, r] * basis_cols[None, :, c]  # (G_r, G_c, n)
        phi = phi.reshape(-1, r.size) * x[r, c]
        psfs = phi.T @ psf_matrix  # (n, h*w): each pixel's PSF times its value
        index = (r * full_cols + c)[:, None] + offsets[None, :]
        full += np.bincount(index.ravel(), weights=psfs.ravel(), minlength=full.size)
    full = full.reshape(rows + height - 1, full_cols)
    return full[height // 2 : height // 2 + rows, width // 2 : width // 2 + cols]


@dataclass(frozen=True)
class LowRankError:
    """Accuracy and cost of the rank-``K`` operator against the exact SV convolution.

    Attributes
    ----------
    rank : int
        ``K``.
    captured_energy : float
        Fraction of the PSF-grid energy captured by ``K`` components.
    relative_error : float
        ``‖A_K x − A_ref x‖ / ‖A_ref x‖``.
    lowrank_seconds : float
        Time of one forward application of the rank-``K`` operator (construction excluded).
    reference_seconds : float
        Time of the exact reference (the same for every row).
    """

    rank: int
    captured_energy: float
    relative_error: float
    lowrank_seconds: float
    reference_seconds: float


def lowrank_error(
    x: np.ndarray,
    psfs: np.ndarray,
    ranks: Iterable[int],
    margin: int = 0,
    order: int = 3,
    dtype: torch.dtype = torch.float64,
) -> list[LowRankError]:
    """Low-rank error and timing table for one object and one lens's PSF grid.

    Parameters
    ----------
    x : array_like
        Object on the padded grid, shape ``(S_r + 2·margin, S_c + 2·margin)``.
    psfs : array_like
        PSF grid ``(G·G, h, w)`` (see :func:`svcode_core.physics.lowrank.decompose_psfs`).
    ranks : iterable of int
        The ``K`` to evaluate.
    margin, order
        As in :func:`svcode_core.physics.lowrank.coefficient_maps`.
    dtype : torch.dtype
        Precision of the low-rank operator (float64 isolates the truncation error).

    Returns
    -------
    list of LowRankError
        One row per rank, in the order given.

    Raises
    ------
    ValueError
        If the reference image is zero (no relative error can be formed).
    """
    x = np.asarray(x, dtype=np.float64)
    psfs = np.asarray(psfs, dtype=np.float64)
    if x.ndim != 2 or min(x.shape) - 2 * margin < 2:
        raise ValueError(f"x must be a 2-D image larger than twice the margin, got {x.shape}")
    size = (x.shape[0] - 2 * margin, x.shape[1] - 2 * margin)
    n_grid = int(round(np.sqrt(psfs.shape[0])))
    basis_rows = interpolation_basis(n_grid, size[0], margin, order)
    basis_cols = interpolation_basis(n_grid, size[1], margin, order)
    start = time.perf_counter()
    reference = sv_convolve_reference(x, psfs, basis_rows, basis_cols)
    reference_seconds = time.perf_counter() - start
    reference_norm = np.linalg.norm(reference)
    if reference_norm == 0.0:
        raise ValueError("the reference image is zero: no relative error can be formed")
    x_tensor = torch.as_tensor(x, dtype=dtype)
    rows = []
    for rank in ranks:
        decomposition = decompose_psfs(psfs, rank=rank)
        operator = LowRankSVOperator.from_decomposition(
            decomposition, size, margin=margin, order=order, dtype=dtype
        )
        operator.forward(x_tensor)  # warm-up: first-call FFT planning is not the steady cost
        start = time.perf_counter()
        image = operator.forward(x_tensor).double().numpy()
        seconds = time.perf_counter() - start
        rows.append(
            LowRankError(
                rank=decomposition.rank,
                captured_energy=decomposition.energy_fraction,
                relative_error=float(np.linalg.norm(image - reference) / reference_norm),
                lowrank_seconds=seconds,
                reference_seconds=reference_seconds,
            )
        )
    return rows
