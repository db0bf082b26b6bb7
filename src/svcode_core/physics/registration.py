"""Chief-ray self-registration: lens-array drift estimated from a raw frame itself.

Every sub-view is an image of the same object, so a lens whose image moved by ``d_ℓ``
shows the object displaced by ``d_ℓ`` against the other sub-views. Each sub-view is
registered to the reference lens's by weighted least squares over the sensor part both
see, tapered to its edge (a gain, an offset and a sub-pixel shift,
:func:`scipy.optimize.least_squares`); the same registration on the model's frame of the
reference view (taken as the object) is subtracted, as what the lenses' own blur,
distortion and crosstalk give. A least-squares fit splits the offsets into an array
translation, a rotation about the lattice centre and per-lens residuals.

Only offsets *between* lenses are observable: moving every lens image by the same amount
is the same frame as moving the object, so the offsets are relative to the reference lens
(its own is 0) and the translation is that of the array relative to it.

Accuracy (``bench/calibration.py``, ``cm2-mini``, ``calibration`` departures, the
held-out ``cell.png`` scene): the estimated offsets relative to the centre lens are off by
0.88 px on average (1.48 px at worst), where assuming no drift is off by 0.23 px; on the
tiny test system, 0.2–0.5 px for true offsets up to 0.6 px. The reference used (the
model's frame of the centre view) differs from the object by the centre lens's blur and
crosstalk, and that difference moves the registration by more than the drift itself.
This is therefore not an option of ``svcode reconstruct``.
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
from .geometry import crop_to_sensor, extract_sub_views, pad_sensor_frame

__all__ = ["Registration", "register_frame"]

#: Phase-correlation upsampling: offsets are resolved to 1 / UPSAMPLE px.
UPSAMPLE = 50


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


def _weights(valid: np.ndarray, taper: float) -> np.ndarray:
    """Weights ``(9, S, S)`` rising smoothly from 0 at the edge of each view's ``valid``
    region to 1 ``taper`` px inside."""
    distance = np.stack([ndimage.distance_transform_edt(v) for v in valid])
    return np.sin(0.5 * np.pi * np.clip(distance / taper, 0.0, 1.0)) ** 2


def _shift(model: np.ndarray, measured: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Displacement ``(2,)`` of ``measured``'s content against ``model``'s.

    Weighted least squares over ``weight`` of ``measured ≈ a · shift(model, d) + b``
    (gain ``a`` and offset ``b`` free; cubic-spline shift).
    """
    root = np.sqrt(weight)

    def residual(p: np.ndarray) -> np.ndarray:
        moved = ndimage.shift(model, p[2:], order=3, mode="nearest")
        return (root * (measured - p[0] * moved - p[1])).ravel()

    scale = float((weight * measured).sum() / max((weight * model).sum(), 1e-30))
    fit = least_squares(residual, np.array([scale, 0.0, 0.0, 0.0]), x_scale="jac")
    return fit.x[2:]


def _pairwise(views: np.ndarray, weight: np.ndarray, reference: int) -> np.ndarray:
    """``(9, 2)`` displacement of every view's content against the reference view's."""
    return np.stack([np.zeros(2) if lens == reference else
                     _shift(views[reference], views[lens], weight[lens])
                     for lens in range(N_LENSES)])  # fmt: skip


def register_frame(
    frame: np.ndarray,
    system: SystemConfig,
    operator: CM2Operator | None = None,
    reference: int = 4,
) -> Registration:
    """Estimate the lens offsets of ``system`` from a raw frame.

    Parameters
    ----------
    frame : numpy.ndarray
        Raw sensor frame ``system.sensor_shape``.
    system : SystemConfig
        The system the frame is believed to come from (its chief rays are the start).
    operator : CM2Operator, optional
        Its forward model (default :meth:`CM2Operator.from_system`), to subtract the
        displacements the lenses' own blur and distortion give.
    reference : int
        Lens whose offset is 0 (default the centre lens, which sees the whole field).

    Returns
    -------
    Registration
    """
    system = system.validate()
    frame = np.asarray(frame, dtype=np.float64)
    if frame.shape != tuple(system.sensor_shape):
        raise ValueError(f"frame is {frame.shape[0]}×{frame.shape[1]} px, the system's sensor "
                         f"{system.sensor_shape[0]}×{system.sensor_shape[1]}")  # fmt: skip
    if operator is None:
        operator = CM2Operator.from_system(system, dtype=torch.float64)
    dtype = operator.lenses.dtype
    window = torch.zeros(system.padded_shape, dtype=torch.float64)
    window[system.sensor_window] = 1.0
    valid = extract_sub_views(window, system).numpy() > 0
    views = extract_sub_views(pad_sensor_frame(torch.as_tensor(frame), system), system).numpy()
    weight = _weights(valid & valid[reference], float(system.optics.kernel_size))
    measured = _pairwise(views, weight, reference)
    # what the lenses' own blur, distortion and crosstalk give: the same on the model's
    # frame of the reference view, taken as the object
    proxy = torch.as_tensor(np.clip(views[reference], 0.0, None), dtype=dtype)
    with torch.no_grad():
        model_frame = crop_to_sensor(operator.forward(proxy), system).double()
    model_views = extract_sub_views(pad_sensor_frame(model_frame, system), system).numpy()
    offsets = measured - _pairwise(model_views, weight, reference)
    shift, rotation, residuals = fit_array(offsets, system)
    return Registration(offsets, shift, rotation, residuals, reference)
