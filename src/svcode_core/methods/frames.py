"""Raw frames as the reconstructors take them: shape, type, scale and range checks.

Every reconstructor (the network, the model-based and the learned baselines) and the
streaming command line pass their input through :func:`as_frame_stack` (the stack as a
whole) and :func:`finite_frame` (one frame), so the rules below hold everywhere.

Units
    Frames are sensor readings normalised so that the sensor's full scale is ``1.0`` (the
    saturation level of the presets' noise model, and the range the bundled model was
    trained on).

Integer frames (the rule)
    The system configuration records no ADC bit depth, so an integer frame is converted by
    its type: 8- and 16-bit integers are divided by the largest value of their type (255,
    65535; 127 and 32767 when signed), so the type's full scale becomes ``1.0``. Wider
    integers (32 and 64 bit) have no such meaning and are refused unless a scale is given.
    An explicit ``scale`` (``svcode reconstruct --input-scale COUNTS``) replaces the rule
    and divides every frame, integer or float, by ``COUNTS``, e.g. 4095 for a 12-bit sensor
    stored in 16-bit words. A 16-bit frame that uses at most 12 bits gets a warning saying
    so. Boolean frames are refused.

Range
    NaN or Inf, a frame with no positive value (all negative: a sign or dark-frame error;
    after the usual clipping at 0 nothing would be left) and a frame reaching more than
    :data:`FAR_ABOVE` (10× the full scale: raw counts or another unit) are refused with a
    :class:`ValueError` naming the frame and the fix, and so is a frame whose brightest value
    is positive but below :data:`FAR_BELOW` (one count of a 32-bit sensor: no sensor
    reading is that small in normalised units, and single-precision sums of squares of
    such values underflow). Frames between :data:`WARN_ABOVE` (2×) and :data:`FAR_ABOVE`
    are reconstructed as they are, with a warning (a scale off by a few bits?).
    Noiseless simulated frames can exceed the full scale a little where views overlap (the
    sensor model clips real readings), so up to 2× passes silently. An all-zero frame (a
    closed shutter, a dropped frame) is reconstructed as zero with a warning, so a long
    recording with a blank frame in it runs to its end.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

__all__ = [
    "FAR_ABOVE",
    "FAR_BELOW",
    "FULL_SCALE",
    "WARN_ABOVE",
    "as_frame_stack",
    "finite_frame",
    "few_bits_scale",
    "few_bits_warning",
    "frame_warnings",
    "require_frames",
]

FULL_SCALE = 1.0
"""Normalised value of the sensor's full scale."""
FAR_ABOVE = 10.0 * FULL_SCALE
"""Frames reaching beyond this are refused: they are not in normalised units."""
FAR_BELOW = 2.0**-32 * FULL_SCALE
"""Frames whose brightest value is positive but below this are refused: not normalised."""
WARN_ABOVE = 2.0 * FULL_SCALE
"""Frames reaching beyond this (up to :data:`FAR_ABOVE`) are reconstructed with a warning."""
_SCALE_HINT = (
    "divide by the sensor's full-scale count (svcode reconstruct --input-scale COUNTS, "
    "e.g. 4095 for a 12-bit sensor), or convert the frames to float32 with full scale 1.0"
)


def require_frames(count: int, name: str = "the frame stack") -> None:
    """Raise :class:`ValueError` if ``name`` holds no frames (``count == 0``)."""
    if count == 0:
        raise ValueError(f"{name} is empty (0 frames): nothing to reconstruct")


def as_frame_stack(frames: Any) -> np.ndarray:
    """A raw frame ``(H, W)`` or a stack ``(T, H, W)`` as a ``(T, H, W)`` array (a view
    where possible).

    Raises
    ------
    ValueError
        For values that are not real numbers (booleans included), other ranks, an empty
        stack.
    """
    array = np.asarray(frames)
    if array.dtype.kind == "b":
        raise ValueError("frames hold booleans (a mask?), not sensor readings")
    if array.dtype.kind not in "iuf":
        raise ValueError(f"frames must hold real numbers, got dtype {array.dtype}")
    if array.ndim not in (2, 3):
        raise ValueError(
            "expected a raw sensor frame (H×W) or a stack (T×H×W), "
            f"got an array of shape {array.shape}"
        )
    stack = array[None] if array.ndim == 2 else array
    require_frames(stack.shape[0])
    return stack


def _integer_scale(dtype: np.dtype, index: int) -> float:
    """The full-scale count of integer ``dtype`` by the module's rule."""
    if dtype.itemsize > 2:
        raise ValueError(
            f"frame {index} holds {dtype} integers, whose full scale is not known: "
            + _SCALE_HINT
        )
    return float(np.iinfo(dtype).max)


# What the checks warn about, as (problem, what to do): warnings.warn joins the two with
# ": "; a front end can show them apart (frame_warnings).
def few_bits_warning(dtype: np.dtype) -> tuple[str, str]:
    """The warning about frames of integer ``dtype`` that use at most 12 bits (one of
    :func:`frame_warnings`' pairs), for a front end to recognise."""
    return (f"{dtype} frames that use at most 12 bits are divided by "
            f"{np.iinfo(dtype).max}, their type's full scale",
            "if the sensor has fewer bits, pass its full-scale count instead "
            "(--input-scale 4095 for 12 bits)")


_ABOVE = (f"frames reach more than {WARN_ABOVE / FULL_SCALE:g}× the sensor's full scale "
          f"{FULL_SCALE:g} (refused beyond {FAR_ABOVE:g}); they are reconstructed as they "
          "are, but a real sensor clips at its full scale", "check the input scale")
_BLANK = ("blank frames (every value 0: a closed shutter or a dropped frame?) are "
          "reconstructed as 0", "check the recording if no frame should be dark")


def _warn(message: tuple[str, str]) -> None:
    warnings.warn(": ".join(message), UserWarning, stacklevel=3)


def few_bits_scale(raw: Any) -> float | None:
    """The full-scale count of 16-bit integer frames whose values all fit in 12 bits
    (4095: a 12-bit sensor's counts stored as uint16), else ``None``.

    Examples
    --------
    >>> few_bits_scale(np.full((4, 4), 4000, np.uint16)), few_bits_scale(np.ones(4))
    (4095.0, None)
    """
    raw = np.asarray(raw)
    few = raw.dtype.kind in "iu" and raw.dtype.itemsize == 2 and raw.size > 0 and (
        0 < int(raw.max()) < 1 << 12)
    return float((1 << 12) - 1) if few else None


def frame_warnings(frames: Any, scale: float | None = None) -> list[tuple[str, str]]:
    """What reconstructing ``frames`` would warn about, found without reconstructing
    them: ``(problem, what to do)`` pairs, for a front end to show before a run.

    Examples
    --------
    >>> frames = np.zeros((2, 4, 4), np.uint16)
    >>> frames[0] = 4000  # 12-bit counts; frame 1 is blank
    >>> for problem, _ in frame_warnings(frames):
    ...     print(problem.split(",")[0].split(" (")[0])
    uint16 frames that use at most 12 bits are divided by 65535
    blank frames
    """
    stack = as_frame_stack(frames)
    found = []
    if scale is None and few_bits_scale(stack) is not None:
        found.append(few_bits_warning(stack.dtype))
    top = float(stack.max()) if stack.size else 0.0
    full = scale if scale is not None else (
        float(np.iinfo(stack.dtype).max) if stack.dtype.kind in "iu" else 1.0)
    if top / full > WARN_ABOVE:
        found.append(_ABOVE)
    if not stack.reshape(len(stack), -1).any(axis=1).all():
        found.append(_BLANK)
    return found


def _check_range(values: np.ndarray, index: int) -> None:
    if not values.size:
        return
    top, bottom = float(values.max()), float(values.min())
    if top > FAR_ABOVE:
        raise ValueError(
            f"frame {index} reaches {top:.4g}, far above the sensor's full scale "
            f"{FULL_SCALE:g} (refused beyond {FAR_ABOVE:g}): it is not in normalised units; "
            + _SCALE_HINT
        )
    if 0 < top < FAR_BELOW:
        raise ValueError(
            f"frame {index} reaches only {top:.4g}, below one count of a 32-bit sensor "
            f"({FAR_BELOW:.3g} of the full scale {FULL_SCALE:g}): it is not in normalised "
            "units; pass the full scale in these units (svcode reconstruct --input-scale "
            "VALUE) or rescale the frames to full scale 1.0"
        )
    if top == 0 == bottom:
        _warn(_BLANK)
    if top <= 0 < -bottom:
        raise ValueError(
            f"frame {index} has no positive value (it lies in [{bottom:.4g}, {top + 0.0:.4g}]); "
            "negative readings are clipped at 0, so nothing would be left: check the sign "
            "and any dark-frame subtraction"
        )
    if top > WARN_ABOVE:
        _warn(_ABOVE)


def finite_frame(
    frame: Any, index: int, dtype: type = np.float32, scale: float | None = None
) -> np.ndarray:
    """One raw frame as a ``dtype`` array in normalised units, checked.

    Parameters
    ----------
    frame : array_like
        A sensor reading, float (normalised) or integer (converted by the module's rule).
    index : int
        Its position in the stack, for the messages.
    dtype : type
        Floating-point type of the result.
    scale : float, optional
        Full-scale value: every frame is divided by it (replaces the integer rule).

    Returns
    -------
    numpy.ndarray
        The frame in normalised units.

    Raises
    ------
    ValueError
        For NaN or Inf (naming the count), booleans or other non-real values, integers
        wider than 16 bits without a ``scale``, a frame with no positive value, or one far
        above the full scale.
    """
    raw = np.asarray(frame)
    if raw.dtype.kind == "b":
        raise ValueError(f"frame {index} holds booleans (a mask?), not sensor readings")
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"frame {index} must hold real numbers, got dtype {raw.dtype}")
    if scale is not None:
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"input scale must be a finite number > 0, got {scale!r}")
        values = (np.asarray(raw, dtype=np.float64) / scale).astype(dtype, copy=False)
    elif raw.dtype.kind in "iu":
        full_scale = _integer_scale(raw.dtype, index)
        if few_bits_scale(raw) is not None:
            _warn(few_bits_warning(raw.dtype))
        values = (np.asarray(raw, dtype=np.float64) / full_scale).astype(dtype, copy=False)
    else:
        values = np.asarray(raw, dtype=dtype)
    bad = values.size - int(np.isfinite(values).sum())
    if bad:
        raise ValueError(f"frame {index} holds {bad} NaN or Inf values")
    _check_range(values, index)
    return values
