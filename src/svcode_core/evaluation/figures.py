"""Matplotlib figures of simulations and reconstructions, drawn off-screen (Agg).

Matplotlib is imported only when a figure is drawn, and pyplot not at all: importing this
module (the plugin does, for :func:`psf_montage`) changes no backend and loads no
matplotlib.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..config import SystemConfig
from ..physics.geometry import pad_sensor_frame, sub_view_origins

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["calibration_figure", "montage", "overview_figure", "psf_montage"]


def montage(views: np.ndarray) -> np.ndarray:
    """Arrange nine ``(9, S, S)`` views as one ``(3S, 3S)`` image, lens 0 top left."""
    views = np.asarray(views)
    size = views.shape[-1]
    return views.reshape(3, 3, size, size).transpose(0, 2, 1, 3).reshape(3 * size, 3 * size)


def _figure(**options) -> Figure:
    """A new figure on an Agg canvas (no pyplot: no global backend, nothing to close)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**options)
    FigureCanvasAgg(fig)
    return fig


def _tab10(count: int) -> np.ndarray:
    """``count`` colours of the ``tab10`` colour map, repeating after ten."""
    import matplotlib

    return matplotlib.colormaps["tab10"](np.arange(count) % 10)


def _save(fig: Figure, path: str | Path, dpi: int) -> Path:
    """Lay out ``fig`` and write it to ``path`` (creating its folder)."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def psf_montage(psfs: np.ndarray) -> np.ndarray:
    """Arrange a PSF grid ``(9, G·G, k, k)`` as one image, lens-major.

    Lens 0's ``G × G`` field points (``k × k`` each) fill the top-left ``G·k`` square,
    lens 1's the next one to the right, and so on.

    Examples
    --------
    >>> psfs = np.zeros((9, 4, 5, 5))
    >>> psfs[1, 2, 2, 2] = 1.0  # lens 1, field point (1, 0)
    >>> image = psf_montage(psfs)
    >>> image.shape, tuple(int(i) for i in np.argwhere(image)[0])
    ((30, 30), (7, 12))
    """
    psfs = np.asarray(psfs)
    grid = int(round(np.sqrt(psfs.shape[1])))
    if psfs.ndim != 4 or psfs.shape[0] != 9 or grid * grid != psfs.shape[1]:
        raise ValueError(f"psfs must be (9, G·G, k, k), got {psfs.shape}")
    k = psfs.shape[-1]
    tiles = psfs.reshape(3, 3, grid, grid, k, k).transpose(0, 2, 4, 1, 3, 5)
    return tiles.reshape(3 * grid * k, 3 * grid * k)


def overview_figure(
    path: str | Path,
    system: SystemConfig,
    measurement: np.ndarray,
    panels: dict[str, np.ndarray],
    title: str = "",
) -> Path:
    """Save the raw frame with its sub-view boxes beside further image panels.

    Parameters
    ----------
    path : str or Path
        PNG to write.
    system : SystemConfig
        Gives the sensor window and the sub-view boxes.
    measurement : numpy.ndarray
        Raw sensor frame ``(H, W)``.
    panels : dict of str to numpy.ndarray
        Title → 2-D image (a ``(9, S, S)`` stack is shown as a 3×3 montage).
    title : str
        Figure title.
    """
    from matplotlib.patches import Rectangle

    count = 1 + len(panels)
    fig = _figure(figsize=(3.6 * count, 4.0))
    axes = fig.subplots(1, count, squeeze=False)[0]
    padded = pad_sensor_frame(torch.as_tensor(measurement, dtype=torch.float32), system)
    axes[0].imshow(padded.numpy(), cmap="gray")
    rows, cols = system.sensor_window
    axes[0].add_patch(Rectangle((cols.start - 0.5, rows.start - 0.5), cols.stop - cols.start,
                                rows.stop - rows.start, fill=False, ec="white", ls="--", lw=0.8))
    size = system.sub_view_size
    colours = _tab10(9)
    for lens, (r0, c0) in enumerate(sub_view_origins(system)):
        axes[0].add_patch(Rectangle((c0 - 0.5, r0 - 0.5), size, size, fill=False,
                                    ec=colours[lens], lw=0.8))
        r, c = system.chief_rays[lens]
        axes[0].plot(c, r, "+", color=colours[lens], ms=5)
    axes[0].set_title("raw frame, sub-views")
    for ax, (name, image) in zip(axes[1:], panels.items(), strict=True):
        image = np.asarray(image)
        shown = montage(image) if image.ndim == 3 else image
        cmap = "magma" if "error" in name else "gray"
        handle = ax.imshow(shown, cmap=cmap)
        if "error" in name:
            fig.colorbar(handle, ax=ax, fraction=0.046, pad=0.02)
        ax.set_title(name)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi=110)


def calibration_figure(path: str | Path, calibration, frames: np.ndarray) -> Path:
    """Save the fitted spots, their residuals and the PSF grid of a calibration.

    Parameters
    ----------
    path : str or Path
        PNG to write.
    calibration : svcode_core.physics.calibration.Calibration
    frames : numpy.ndarray
        The scan ``(N, H, W)``; its maximum over frames is the background of panel 1.
    """
    cal = calibration
    fig = _figure(figsize=(13.0, 4.4))
    axes = fig.subplots(1, 3)
    axes[0].imshow(np.asarray(frames).max(axis=0), cmap="gray")
    measured = cal.centroids.reshape(-1, 2)
    predicted = cal.predicted.reshape(-1, 2)
    axes[0].plot(measured[:, 1], measured[:, 0], "o", mfc="none", mec="cyan", ms=4,
                 label="measured spot")
    axes[0].plot(predicted[:, 1], predicted[:, 0], "+", color="red", ms=4, label="fitted")
    axes[0].legend(loc="lower right", fontsize=7)
    axes[0].set_title("scan (max over frames), spots")
    colours = _tab10(9)
    residual = cal.centroids - cal.predicted
    for lens in range(9):
        axes[1].plot(residual[:, lens, 1], residual[:, lens, 0], ".", color=colours[lens],
                     label=f"lens {lens}")
    axes[1].axhline(0, color="grey", lw=0.5)
    axes[1].axvline(0, color="grey", lw=0.5)
    axes[1].set_aspect("equal")
    axes[1].invert_yaxis()
    axes[1].set_xlabel("col residual (px)")
    axes[1].set_ylabel("row residual (px)")
    axes[1].legend(fontsize=6, ncol=3)
    axes[1].set_title("centroid residuals")
    psfs = np.asarray(cal.psfs)
    grid, k = int(round(np.sqrt(psfs.shape[1]))), psfs.shape[-1]
    axes[2].imshow(np.sqrt(psf_montage(psfs)), cmap="magma")
    for line in range(1, 3):
        axes[2].axhline(line * grid * k - 0.5, color="white", lw=0.8)
        axes[2].axvline(line * grid * k - 0.5, color="white", lw=0.8)
    axes[2].set_xticks([])
    axes[2].set_yticks([])
    axes[2].set_title(f"PSF grid, lens-major (sqrt), K = {max(cal.ranks)}")
    return _save(fig, path, dpi=100)
