"""One exposure for the learned methods: every frame is brought to the level they were
trained at, and the reconstruction is scaled back.

A frame read with another gain or exposure time carries the same image at another scale,
but a network is not scale-equivariant: the bundled model lost up to 6 dB on a frame at
5 % of its training level. The learned reconstructors therefore multiply each frame by
``REFERENCE_LEVEL / exposure_level(frame)`` before the network and divide its output by
the same gain, so ``reconstruct(s · frame) == s · reconstruct(frame)`` for every ``s > 0``
(up to rounding). What is left is the noise: a frame with fewer photons stays noisier.

:func:`exposure_level` is the largest 3 × 3 mean of the frame after every pixel is clipped
to its brightest neighbour: an isolated hot pixel does not count, a spot of a few pixels (a
bead's image) does, and the level scales with the frame.
"""

from __future__ import annotations

import numpy as np

__all__ = ["REFERENCE_LEVEL", "exposure_gain", "exposure_level"]

REFERENCE_LEVEL = 0.58
"""The level frames are brought to: the median :func:`exposure_level` of the bundled
``cm2-mini`` model's training frames (0.576 over 32 of them, noisy, through their own
instruments; the middle 80 % lie within 0.30–1.25)."""


def exposure_level(frame: np.ndarray) -> float:
    """A frame's brightness, robust to hot pixels; ``exposure_level(s · x) == s ·
    exposure_level(x)`` for ``s > 0``.

    Parameters
    ----------
    frame : numpy.ndarray
        ``(H, W)``, or ``(N, H, W)`` images measured in every 2-D slice; non-negative.

    Examples
    --------
    >>> frame = np.zeros((16, 16)); frame[4:7, 4:7] = 1.0
    >>> frame[12, 12] = 50.0  # a hot pixel
    >>> exposure_level(frame), exposure_level(0.25 * frame)
    (1.0, 0.25)
    """
    values = np.asarray(frame, dtype=np.float32)
    rows, cols = values.shape[-2:]
    padded = np.pad(values, [(0, 0)] * (values.ndim - 2) + [(1, 1), (1, 1)])  # zeros outside
    brightest = np.zeros_like(values)
    for dr, dc in ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)):
        np.maximum(brightest, padded[..., 1 + dr : 1 + dr + rows, 1 + dc : 1 + dc + cols],
                   out=brightest)  # fmt: skip
    padded[..., 1:-1, 1:-1] = np.minimum(values, brightest)  # despiked, zeros outside
    across = (padded[..., :-2] + padded[..., 1:-1] + padded[..., 2:]) / np.float32(3)
    box = (across[..., :-2, :] + across[..., 1:-1, :] + across[..., 2:, :]) / np.float32(3)
    return float(box.max())


def exposure_gain(frame: np.ndarray, reference: float = REFERENCE_LEVEL) -> float:
    """The factor that brings ``frame`` to ``reference`` (1 for a frame with no light)."""
    level = exposure_level(frame)
    return reference / level if level > 0 else 1.0
