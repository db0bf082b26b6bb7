"""Image-quality metrics of a reconstruction against its ground truth.

PSNR and SSIM over the whole field, and PSNR in two zones of the field that tell the
centre (seen by all nine lenses, mildest aberrations) from the periphery (seen by fewer
lenses through strongly aberrated, vignetted and truncated PSFs):

* **centre**: normalised field radius ``ρ = sqrt(u² + v²) < 0.5``;
* **outer ring**: ``ρ > 0.8``, corners included (``ρ`` reaches ``√2`` there).

``u`` and ``v`` are the normalised object coordinates of :mod:`svcode_core.physics.geometry`
(pixel ``i`` at ``2 i / (S - 1) - 1``). Every metric takes an explicit ``data_range`` (the
span of intensities the truth may take; 1 for objects normalised to ``[0, 1]``) rather than
guessing it from the data, and compares in absolute units: a reconstruction with the
wrong brightness is penalised.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity

from ..physics.geometry import field_radius
from .zones import CENTRE_RADIUS, RING_RADIUS

__all__ = [
    "CENTRE_RADIUS",
    "RING_RADIUS",
    "edge_columns",
    "field_zones",
    "image_quality",
    "psnr",
    "ssim",
]


def _check_pair(truth: np.ndarray, estimate: np.ndarray, data_range: float) -> tuple:
    truth = np.asarray(truth, dtype=np.float64)
    estimate = np.asarray(estimate, dtype=np.float64)
    if truth.ndim != 2 or truth.shape != estimate.shape:
        raise ValueError(
            f"truth and estimate must be 2-D images of one shape, got {truth.shape} and "
            f"{estimate.shape}"
        )
    for name, image in (("truth", truth), ("estimate", estimate)):
        if not np.isfinite(image).all():
            raise ValueError(f"{name} contains NaN or Inf values")
    if not (isinstance(data_range, (int, float)) and math.isfinite(data_range)) or data_range <= 0:
        raise ValueError(f"data_range must be a finite number > 0, got {data_range!r}")
    return truth, estimate


def field_zones(size: int) -> dict[str, np.ndarray]:
    """Boolean masks ``(S, S)`` of the ``"centre"`` and ``"ring"`` zones (module docstring)."""
    radius = field_radius(size)
    return {"centre": radius < CENTRE_RADIUS, "ring": radius > RING_RADIUS}


def edge_columns(size: int, width: int) -> np.ndarray:
    """Boolean mask ``(S, S)`` of the field's left and right edge strips, ``width`` columns
    each: where the outer lenses' sub-views leave the sensor, so fewer than nine lenses see
    the object.

    Examples
    --------
    >>> edge_columns(6, 2).astype(int)[0].tolist()
    [1, 1, 0, 0, 1, 1]
    """
    if not 0 < width <= size // 2:
        raise ValueError(f"edge strips of {width} columns do not fit a field of {size}")
    strips = np.zeros((size, size), dtype=bool)
    strips[:, :width] = strips[:, size - width:] = True
    return strips


def psnr_from_mse(mse: float | torch.Tensor, data_range: float = 1.0) -> float | torch.Tensor:
    """PSNR in dB of a mean squared error: ``10 log10(data_range² / mse)``.

    The one definition of the PSNR: :func:`psnr` and the training metrics
    (:func:`svcode_core.training.loss.psnr_per_sample`, on tensors) use it.

    Examples
    --------
    >>> psnr_from_mse(1e-3)
    30.0
    >>> psnr_from_mse(torch.tensor([1e-2, 1e-4]))
    tensor([20., 40.])
    """
    if isinstance(mse, torch.Tensor):
        return 10.0 * torch.log10(data_range**2 / mse)
    return math.inf if mse == 0.0 else 10.0 * math.log10(data_range**2 / mse)


def psnr(
    truth: np.ndarray,
    estimate: np.ndarray,
    data_range: float,
    mask: np.ndarray | None = None,
) -> float:
    """Peak signal-to-noise ratio ``10 log10(data_range² / MSE)`` in dB.

    Parameters
    ----------
    truth, estimate : array_like
        Images of one 2-D shape.
    data_range : float
        Peak-to-peak span of the truth's intensities (1 for objects in ``[0, 1]``).
    mask : array_like of bool, optional
        Only these pixels count (at least one); default all. Without a mask the value is
        that of :func:`skimage.metrics.peak_signal_noise_ratio`.

    Returns
    -------
    float
        ``inf`` when the images are equal on the mask.
    """
    truth, estimate = _check_pair(truth, estimate, data_range)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != truth.shape or not mask.any():
            raise ValueError(f"mask must be a non-empty boolean image of shape {truth.shape}")
        truth, estimate = truth[mask], estimate[mask]
    return psnr_from_mse(float(np.mean((truth - estimate) ** 2)), data_range)


def ssim(truth: np.ndarray, estimate: np.ndarray, data_range: float) -> float:
    """Mean structural similarity (scikit-image defaults: 7 × 7 uniform window).

    The SSIM every report uses. Training uses a differentiable SSIM with a Gaussian window
    (:func:`svcode_core.training.loss.ssim_per_sample`), so its validation SSIM is close to
    this one but not equal.
    """
    truth, estimate = _check_pair(truth, estimate, data_range)
    return float(structural_similarity(truth, estimate, data_range=data_range))


def image_quality(truth: np.ndarray, estimate: np.ndarray, data_range: float) -> dict[str, float]:
    """PSNR, SSIM and the centre / outer-ring PSNR of one reconstruction.

    Returns
    -------
    dict
        ``{"psnr", "ssim", "psnr_centre", "psnr_ring"}`` (dB, dB; SSIM unitless).

    Examples
    --------
    >>> truth = np.zeros((32, 32)); truth[8:24, 8:24] = 1
    >>> quality = image_quality(truth, truth * 0.9, data_range=1.0)
    >>> round(quality["psnr_centre"], 6), quality["psnr_ring"]
    (20.0, inf)
    """
    truth, estimate = _check_pair(truth, estimate, data_range)
    if truth.shape[0] != truth.shape[1]:
        raise ValueError(f"field zones need a square image, got {truth.shape}")
    zones = field_zones(truth.shape[0])
    return {
        "psnr": psnr(truth, estimate, data_range),
        "ssim": ssim(truth, estimate, data_range),
        "psnr_centre": psnr(truth, estimate, data_range, zones["centre"]),
        "psnr_ring": psnr(truth, estimate, data_range, zones["ring"]),
    }
