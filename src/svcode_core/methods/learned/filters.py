"""Frame-sized linear filters of the learned baselines and their physics initialisation.

Both learned baselines filter the whole zero-padded sensor frame in the Fourier domain
(circular convolution over the padded frame) and cut the object window out of each
result. Conventions:

* The **reference point** ``o`` is the centre pixel ``(H_pad // 2, W_pad // 2)`` of the
  padded frame, and the **object window** is the ``S × S`` crop whose pixel ``S // 2``
  sits at ``o``.
* A frame-sized kernel is stored with ``o`` moved to index ``(0, 0)``. Lens ``ℓ`` images
  object pixel ``S // 2 + r`` around ``c_ℓ + r`` (:mod:`svcode_core.physics.cm2`), so a lens kernel
  placed at offset ``c_ℓ − o`` (:func:`lens_offsets`) maps the object, embedded at the
  object window, onto that lens's image: deconvolving with it brings the lens image back
  to the object window.

The operators here are ``H_pad × W_pad`` per filter: their memory grows with the field of
view, which is the cost the patch-wise SV-CoDe avoids (design.md §4).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ...config import N_LENSES, SystemConfig
from ...physics.cm2 import CM2Operator
from ...physics.lowrank import decompose_psfs

__all__ = [
    "FourierFilterBank",
    "WienerBank",
    "crop_object_window",
    "frame_psf_basis",
    "initial_regularisation",
    "lens_offsets",
    "place_kernel",
    "wiener_gain",
]


def lens_offsets(system: SystemConfig) -> np.ndarray:
    """Offsets ``c_ℓ − o`` of the nine chief rays from the reference point, ``(9, 2)``."""
    rows, cols = system.padded_shape
    return np.asarray(system.chief_rays, dtype=np.int64) - np.array([rows // 2, cols // 2])


def place_kernel(
    kernel: torch.Tensor, offset: tuple[int, int], shape: tuple[int, int]
) -> torch.Tensor:
    """A frame-sized kernel: ``kernel`` (odd sizes) centred at ``offset`` from index (0, 0),
    wrapping around the edges, shape ``shape``."""
    height, width = kernel.shape[-2:]
    if height > shape[0] or width > shape[1]:
        raise ValueError(f"kernel {height}x{width} does not fit a {shape} frame")
    frame = kernel.new_zeros(*kernel.shape[:-2], *shape)
    frame[..., :height, :width] = kernel
    shift = (int(offset[0]) - height // 2, int(offset[1]) - width // 2)
    return torch.roll(frame, shifts=shift, dims=(-2, -1))


def crop_object_window(frames: torch.Tensor, system: SystemConfig) -> torch.Tensor:
    """The ``S × S`` object window of frame-sized images ``(..., H_pad, W_pad)``."""
    rows, cols = system.padded_shape
    size = system.sub_view_size
    r0, c0 = rows // 2 - size // 2, cols // 2 - size // 2
    return frames[..., r0 : r0 + size, c0 : c0 + size]


def frame_psf_basis(operator: CM2Operator, rank: int) -> torch.Tensor:
    """The ``rank`` leading basis PSFs of the whole frame, placed on the padded frame.

    The PSF of an object point on the sensor is the nine lens spots together. Each lens's
    PSF grid is rebuilt from the operator's low-rank model (``Σ_k W_{ℓ,k}[g] h_{ℓ,k}``), the
    nine grids are stacked spot by spot and decomposed jointly
    (:func:`~svcode_core.physics.lowrank.decompose_psfs`), and basis PSF ``k`` is the sum of its
    nine lens parts placed at the lens offsets (:func:`lens_offsets`).

    Parameters
    ----------
    operator : CM2Operator
        Built from a PSF grid (it must carry its decompositions).
    rank : int
        ``K``, at most the number of PSF grid nodes.

    Returns
    -------
    torch.Tensor
        ``(K, H_pad, W_pad)`` in the operator's dtype, reference point at index (0, 0).
    """
    if len(operator.decompositions) != N_LENSES:
        raise ValueError(
            "the operator carries no PSF decompositions; build it with "
            "CM2Operator.from_psfs or from_system"
        )
    grids = np.stack(
        [np.einsum("kab,kij->abij", d.grid_weights, d.kernels) for d in operator.decompositions]
    )  # (9, G, G, h, w)
    _, side, _, height, width = grids.shape
    if not 1 <= rank <= side * side:
        raise ValueError(f"rank must lie in [1, {side * side}] (the PSF grid nodes), got {rank}")
    joint = grids.reshape(N_LENSES, side * side, height, width).transpose(1, 0, 2, 3)
    basis = decompose_psfs(joint.reshape(side * side, N_LENSES * height, width), rank)
    kernels = torch.as_tensor(
        basis.kernels.reshape(rank, N_LENSES, height, width), dtype=operator.lenses.dtype
    )
    shape = operator.system.padded_shape
    return sum(
        place_kernel(kernels[:, lens], offset, shape)
        for lens, offset in enumerate(lens_offsets(operator.system))
    )


def initial_regularisation(psfs: torch.Tensor, balance: float) -> torch.Tensor:
    """``λ = balance · max |H|²`` for each frame-sized PSF ``(..., H, W)``: the same
    relative regularisation whatever the PSF's scale (floored at ``1e-12 · balance``)."""
    peak = torch.fft.rfft2(psfs).abs().flatten(-2).amax(-1) ** 2
    return balance * peak.clamp(min=1e-12)


def wiener_gain(psfs: torch.Tensor, regularisation: torch.Tensor) -> torch.Tensor:
    """Wiener filters ``conj(H) / (|H|² + λ)`` of frame-sized PSFs ``(..., H, W)`` with one
    ``λ`` per PSF (shape ``psfs.shape[:-2]``); half-spectrum of the real FFT."""
    transfer = torch.fft.rfft2(psfs)
    return transfer.conj() / (transfer.abs() ** 2 + regularisation[..., None, None])


def _filter_frames(frames: torch.Tensor, gains: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` frames through ``(N, H, W//2+1)`` gains → ``(B, N, H, W)``, in float32
    at least (also under autocast: torch has no half-precision FFT on the CPU)."""
    shape = tuple(frames.shape[-2:])
    with torch.autocast(frames.device.type, enabled=False):
        dtype = torch.promote_types(frames.dtype, torch.float32)
        spectrum = torch.fft.rfft2(frames.to(dtype))[:, None]
        return torch.fft.irfft2(spectrum * gains, s=shape)


class WienerBank(nn.Module):
    """``K`` Wiener deconvolutions of the padded frame with learnable PSFs and ``λ``.

    Parameters
    ----------
    psfs : torch.Tensor
        Initial frame-sized PSFs ``(K, H_pad, W_pad)``, reference point at index (0, 0).
    balance : float
        Initial ``λ_k = balance · max |H_k|²``.

    Attributes
    ----------
    psfs : nn.Parameter
        ``(K, H_pad, W_pad)``.
    log_regularisation : nn.Parameter
        ``log λ_k``, shape ``(K,)`` (the log keeps ``λ`` positive).
    """

    def __init__(self, psfs: torch.Tensor, balance: float) -> None:
        super().__init__()
        psfs = psfs.detach().float()
        self.psfs = nn.Parameter(psfs.clone())
        self.log_regularisation = nn.Parameter(initial_regularisation(psfs, balance).log())

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """Deconvolved frames ``(B, K, H_pad, W_pad)`` of ``(B, H_pad, W_pad)`` frames."""
        with torch.autocast(frames.device.type, enabled=False):
            gains = wiener_gain(self.psfs.float(), self.log_regularisation.float().exp())
        return _filter_frames(frames, gains)


class FourierFilterBank(nn.Module):
    """``N`` free complex filters over the padded frame's real-FFT half spectrum.

    Parameters
    ----------
    gains : torch.Tensor
        Initial complex filters ``(N, H_pad, W_pad // 2 + 1)``.

    Attributes
    ----------
    spectra : nn.Parameter
        The filters as real and imaginary parts, ``(N, H_pad, W_pad // 2 + 1, 2)``.
    """

    def __init__(self, gains: torch.Tensor) -> None:
        super().__init__()
        self.spectra = nn.Parameter(torch.view_as_real(gains.detach().to(torch.complex64)).clone())

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """Filtered frames ``(B, N, H_pad, W_pad)`` of ``(B, H_pad, W_pad)`` frames."""
        return _filter_frames(frames, torch.view_as_complex(self.spectra.float()))
