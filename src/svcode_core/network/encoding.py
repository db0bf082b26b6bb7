"""Positional encoding γ of normalised coordinates, and the coordinates of U-Net levels."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..physics.geometry import normalized_coordinates
from .config import PE_SCHEMES

__all__ = ["encoding_size", "frequencies", "level_coordinates", "positional_encoding"]


def frequencies(bands: int, scheme: str) -> list[float]:
    """Band frequencies ``f_k`` in units of π: the encoding uses ``sin(f_k π t)``.

    ``"paper"``: ``f_k = 2^k``; ``"code"``: ``f_k = 0.5 (k + 1)``, for k = 0..bands-1.
    """
    if scheme not in PE_SCHEMES:
        raise ValueError(f"scheme must be one of {PE_SCHEMES}, got {scheme!r}")
    if scheme == "paper":
        return [float(2**k) for k in range(bands)]
    return [0.5 * (k + 1) for k in range(bands)]


def encoding_size(bands: int, enabled: bool = True) -> int:
    """Features per axis: ``2 · bands`` (sin and cos) or 1 for the raw coordinate."""
    return 2 * bands if enabled else 1


def positional_encoding(
    coords: torch.Tensor,
    bands: int,
    scheme: str,
    enabled: bool = True,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """γ of one coordinate axis: ``[sin(f_0 π t), cos(f_0 π t), sin(f_1 π t), ...]``.

    The phase is reduced modulo 2 in float64 before the sine, so integer multiples of π
    (for example the largest band at the edge of the field, ``t = ±1``) give exact zeros
    and ones, then the result is cast to ``dtype``.

    Parameters
    ----------
    coords : torch.Tensor
        Normalised coordinates, any shape ``(...)``; promoted to float64.
    bands : int
        Number of frequency bands ``L``.
    scheme : {"paper", "code"}
        See :func:`frequencies`.
    enabled : bool
        ``False`` returns the raw coordinate as a single feature (the ablation).
    dtype : torch.dtype
        Of the result.

    Returns
    -------
    torch.Tensor
        Shape ``(..., 2·bands)`` (or ``(..., 1)`` when disabled).
    """
    t = coords.to(torch.float64)
    if not enabled:
        return t.unsqueeze(-1).to(dtype)
    if not torch.isfinite(t).all():
        raise ValueError("coordinates must be finite")
    freq = torch.tensor(frequencies(bands, scheme), dtype=torch.float64, device=t.device)
    phase = t.unsqueeze(-1) * freq  # in units of π
    phase = phase - 2.0 * torch.round(phase / 2.0)  # exact for the magnitudes used here
    angle = math.pi * phase
    features = torch.stack((torch.sin(angle), torch.cos(angle)), dim=-1)
    return features.flatten(-2).to(dtype)


def level_coordinates(
    origins: torch.Tensor, length: int, size: int, levels: int
) -> list[torch.Tensor]:
    """Normalised coordinates of one axis at every U-Net level, in float64.

    Level 0 holds pixels ``origin .. origin + length - 1`` of the ``size`` grid (see
    :func:`~svcode_core.physics.geometry.normalized_coordinates`); level ``k`` is the 2-average
    pooling of level ``k - 1``: the coordinates of the down-sampled grid.

    Parameters
    ----------
    origins : torch.Tensor
        Shape ``(B,)`` integer first-pixel indices (may be negative or beyond ``size``).
    length : int
        Pixels at level 0; divisible by ``2**levels``.
    size : int
        The sub-view size ``S``.
    levels : int
        Number of down-sampling steps.

    Returns
    -------
    list of torch.Tensor
        ``levels + 1`` tensors of shape ``(B, length / 2^k)``, float64.
    """
    level0 = torch.stack(
        [
            normalized_coordinates(size, int(o), length, dtype=torch.float64, device=origins.device)
            for o in origins.tolist()
        ]
    )
    out = [level0]
    for _ in range(levels):
        out.append(F.avg_pool1d(out[-1].unsqueeze(1), 2).squeeze(1))
    return out
