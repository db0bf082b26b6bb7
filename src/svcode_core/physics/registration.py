"""Chief-ray self-registration: lens-array drift estimated from a raw frame itself.

Every lens forms an image of the same object. Given an estimate ``x̂`` of that object (a
reconstruction with the believed system), the forward model predicts each lens's share of
the sensor frame; a lens whose image moved by ``d_ℓ`` contributes its share displaced by
``d_ℓ``. All nine displacements are fitted at once, with a gain and an offset, by least
squares over every sensor pixel (:func:`scipy.optimize.least_squares`, cubic-spline
shifts): the sub-views overlap on the sensor, so no one of them can be registered alone.
A reconstruction made with misregistered lenses is a compromise between them, so one fit
finds only part of the drift; :func:`~svcode_core.methods.baselines.self_registration.self_register`
repeats reconstruct → register → rebuild the operator a few rounds, adding up the moves.

Only offsets *between* lenses are observable: moving every lens image by the same amount
is the same frame as moving the object, so offsets are relative to the reference lens
(its own is 0). A least-squares fit splits them into an array translation, a rotation
about the lattice centre and per-lens residuals. Measured accuracy is in
``bench/results/calibration.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from scipy.optimize import least_squares

from ..config import N_LENSES, SystemConfig
from .calibration import fit_array
from .cm2 import CM2Operator
from .geometry import crop_to_sensor, place_sub_views
from .optics import system_psfs
from .psf_io import model_psfs

__all__ = ["Registration", "register_views", "registered_system"]


@dataclass(frozen=True)
class Registration:
    """Lens offsets estimated from one frame, relative to the reference lens.

    Attributes
    ----------
    offsets : numpy.ndarray
        ``(9, 2)`` displacement ``(row, col)`` in pixels of each lens's image relative to
        the reference lens's (0 for the reference).
    shift : numpy.ndarray
        ``(2,)`` least-squares array translation (relative to the reference lens).
    rotation_deg : float
        Least-squares array rotation about the lattice centre, degrees.
    residuals : numpy.ndarray
        ``(9, 2)`` offsets left after translation and rotation.
    reference : int
        The reference lens.
    """

    offsets: np.ndarray
    shift: np.ndarray
    rotation_deg: float
    residuals: np.ndarray
    reference: int

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON record (for output metadata)."""
        return {
            "reference_lens": self.reference,
            "lens_offsets_px": np.round(self.offsets, 4).tolist(),
            "array_shift_px": np.round(self.shift, 4).tolist(),
            "array_rotation_deg": round(self.rotation_deg, 5),
        }


def _lens_frames(operator: CM2Operator, estimate: np.ndarray) -> np.ndarray:
    """``(9, H, W)``: each lens's share of the noiseless sensor frame of ``estimate``."""
    system = operator.system
    x = torch.as_tensor(np.clip(estimate, 0.0, None), dtype=operator.lenses.dtype)
    with torch.no_grad():
        blur = operator.lens_blur(x)  # (9, S', S')
        alone = blur * torch.eye(N_LENSES, dtype=blur.dtype)[:, :, None, None]  # lens ℓ only
        frames = crop_to_sensor(place_sub_views(alone, system, operator.margin), system)
    return frames.double().numpy()


def _fit_moves(frame: np.ndarray, lens_frames: np.ndarray, limit: float) -> np.ndarray:
    """``(9, 2)`` moves ``d`` with ``frame ≈ a · Σ_ℓ shift(lens_frames[ℓ], d_ℓ) + b``.

    Bounded least squares (:func:`scipy.optimize.least_squares`, ``|d| ≤ limit`` per
    axis) over every sensor pixel, the derivative of a shifted image being minus its
    gradient.
    """

    last: dict[bytes, np.ndarray] = {}  # the shifted images at the last point asked

    def shifted(p: np.ndarray) -> np.ndarray:
        key = p[2:].tobytes()
        if key not in last:  # the residual and the Jacobian come at the same point
            moves = p[2:].reshape(N_LENSES, 2)
            last.clear()
            last[key] = np.stack([ndimage.shift(image, move, order=3, mode="nearest")
                                  for image, move in zip(lens_frames, moves, strict=True)])
        return last[key]

    def residual(p: np.ndarray) -> np.ndarray:
        return (p[0] * shifted(p).sum(axis=0) + p[1] - frame).ravel()

    def jacobian(p: np.ndarray) -> np.ndarray:
        images = shifted(p)
        columns = [images.sum(axis=0).ravel(), np.ones(frame.size)]
        for image in images:
            rows, cols = np.gradient(image)
            columns += [-p[0] * rows.ravel(), -p[0] * cols.ravel()]
        return np.stack(columns, axis=1)

    total = lens_frames.sum(axis=0)
    gain = float((frame * total).sum() / max((total * total).sum(), 1e-30))
    start = np.concatenate([[gain, 0.0], np.zeros(2 * N_LENSES)])
    bound = np.full(2 * N_LENSES, float(limit))
    fit = least_squares(residual, start, jac=jacobian, x_scale="jac",
                        bounds=(np.r_[-np.inf, -np.inf, -bound], np.r_[np.inf, np.inf, bound]))
    return fit.x[2:].reshape(N_LENSES, 2)


def register_views(
    frame: np.ndarray,
    system: SystemConfig,
    estimate: np.ndarray,
    operator: CM2Operator | None = None,
    reference: int = 4,
    limit: float = 1.0,
) -> Registration:
    """Lens offsets of ``frame`` against the frame ``operator`` predicts for ``estimate``.

    Each lens's share of the predicted frame is moved by its own sub-pixel offset, the
    sum (times a gain, plus an offset) fitted to ``frame`` by least squares: crosstalk
    between the overlapping sub-views is part of the model, not an error of it.

    Parameters
    ----------
    frame : numpy.ndarray
        Raw sensor frame ``system.sensor_shape``.
    system : SystemConfig
        The system the frame is believed to come from.
    estimate : numpy.ndarray
        ``(S, S)`` estimate of the object (a reconstruction of ``frame`` with ``operator``).
    operator : CM2Operator, optional
        Forward model of ``system`` (default :meth:`CM2Operator.from_system`).
    reference : int
        Lens whose offset is 0 (default the centre lens, which sees the whole field).
    limit : float
        Largest move of a lens image along each axis, pixels (a trust region: an estimate
        made with misregistered lenses holds ghosts that a free fit may lock onto).

    Returns
    -------
    Registration
        Offsets of each lens's image against where ``system`` puts it.
    """
    system = system.validate()
    frame = np.asarray(frame, dtype=np.float64)
    if frame.shape != tuple(system.sensor_shape):
        raise ValueError(f"frame is {frame.shape[0]}×{frame.shape[1]} px, the system's sensor "
                         f"{system.sensor_shape[0]}×{system.sensor_shape[1]}")  # fmt: skip
    size = system.sub_view_size
    estimate = np.asarray(estimate, dtype=np.float64)
    if estimate.shape != (size, size):
        raise ValueError(f"estimate must be {size}×{size}, got {estimate.shape}")
    if operator is None:
        operator = CM2Operator.from_system(system, dtype=torch.float64)
    moves = _fit_moves(frame, _lens_frames(operator, estimate), limit)
    offsets = moves - moves[reference]
    shift, rotation, residuals = fit_array(offsets, system)
    return Registration(offsets, shift, rotation, residuals, reference)


def registered_system(system: SystemConfig, offsets: np.ndarray) -> tuple[SystemConfig, np.ndarray]:
    """``system`` with each lens's image moved by ``offsets``, and the PSFs that go with it.

    The whole-pixel part of each offset moves the lens's chief ray; the sub-pixel rest is
    put into the lens's PSFs: the pupil model's computed at the moved image points, or a
    measured PSF model (``system.psf_model``) shifted by it (cubic spline).

    Parameters
    ----------
    system : SystemConfig
    offsets : numpy.ndarray
        ``(9, 2)`` displacement ``(row, col)`` in pixels of each lens's image.

    Returns
    -------
    (SystemConfig, numpy.ndarray)
        The moved system and its PSFs ``(9, G·G, k, k)``
        (:meth:`CM2Operator.from_psfs` builds the operator).
    """
    offsets = np.asarray(offsets, dtype=float)
    if offsets.shape != (N_LENSES, 2) or not np.all(np.isfinite(offsets)):
        raise ValueError(f"offsets must be finite, shape ({N_LENSES}, 2), got {offsets.shape}")
    whole = np.rint(offsets)
    rays = np.asarray(system.chief_rays) + whole.astype(np.int64)
    moved = system.replace(chief_rays=tuple((int(r), int(c)) for r, c in rays)).validate()
    rest = offsets - whole
    if system.psf_model is None:
        return moved, system_psfs(moved, offsets=rest)
    psfs = model_psfs(system)
    shifted = np.stack([[ndimage.shift(psf, rest[lens], order=3, mode="constant")
                         for psf in psfs[lens]] for lens in range(N_LENSES)])  # fmt: skip
    return moved, np.clip(shifted, 0.0, None)
