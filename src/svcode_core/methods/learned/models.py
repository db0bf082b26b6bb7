"""The learned SV baselines of the paper: MultiWienerNet and SV-FourierNet.

Both map zero-padded sensor frames ``(B, H_pad, W_pad)`` (what
:func:`~svcode_core.physics.geometry.pad_sensor_frame` makes of raw frames) to reconstructions
``(B, 1, S, S)``: a bank of frame-sized filters (:mod:`.filters`), the object window of
every filtered frame, and a refinement U-Net of plain NAF blocks (the SV-CoDe U-Net
without coordinate gates) that fuses the channels into one image. Like SV-CoDe's
``"linear"`` output the last convolution is unbounded while training and clamped at zero
in evaluation mode.

* :class:`MultiWienerNet` (Yanny et al. 2022): ``K`` Wiener deconvolutions with learnable
  PSFs and regularisation, initialised from the ``K`` leading basis PSFs of the frame
  PSF (:func:`~.filters.frame_psf_basis`).
* :class:`SVFourierNet` (Yang et al. 2024): nine free complex Fourier filters, initialised
  as the Wiener filter of each lens's unit-sum centre PSF placed at its chief ray, so
  filter ``ℓ`` starts as the shift-invariant Wiener deconvolution of view ``ℓ``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ...config import N_LENSES, SystemConfig
from ...network import ModelConfig, UNet
from ...physics.cm2 import CM2Operator
from ..baselines.deconv import unit_centre_psfs
from .config import FourierNetConfig, MultiWienerConfig, _BaselineConfig
from .filters import (
    FourierFilterBank,
    WienerBank,
    crop_object_window,
    frame_psf_basis,
    initial_regularisation,
    lens_offsets,
    place_kernel,
    wiener_gain,
)

__all__ = ["LEARNED_MODELS", "MultiWienerNet", "RefinementNet", "SVFourierNet"]


class RefinementNet(nn.Module):
    """3×3 convolution to ``width`` channels, a plain NAFNet U-Net, 3×3 convolution to one.

    Inputs of any size are zero-padded at the bottom and right to a multiple of the
    U-Net stride and the output is cropped back.
    """

    def __init__(self, in_channels: int, config: _BaselineConfig) -> None:
        super().__init__()
        unet_config = ModelConfig(width=config.width, coord_gate=False).validate()
        self.intro = nn.Conv2d(in_channels, config.width, 3, padding=1)
        self.unet = UNet(unet_config, config.enc_blocks, config.middle_blocks, config.dec_blocks)
        self.ending = nn.Conv2d(config.width, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, in_channels, H, W)`` → ``(B, 1, H, W)``."""
        stride = 2**self.unet.levels
        h, w = x.shape[-2:]
        x = F.pad(x, (0, math.ceil(w / stride) * stride - w, 0, math.ceil(h / stride) * stride - h))
        out = self.ending(self.unet(self.intro(x)))
        out = out[..., :h, :w]
        return out if self.training else out.clamp_min(0)


class _FilterNet(nn.Module):
    """Filter bank over the padded frame, object window, refinement U-Net."""

    def __init__(
        self, config: _BaselineConfig, system: SystemConfig, bank: nn.Module, channels: int
    ) -> None:
        super().__init__()
        self.model_config = config.validate()
        self.system = system.validate()
        self.bank = bank
        self.refine = RefinementNet(channels, config)

    def filtered(self, frames: torch.Tensor) -> torch.Tensor:
        """The object windows of the filtered frames, ``(B, channels, S, S)``."""
        shape = self.system.padded_shape
        if (
            not isinstance(frames, torch.Tensor)
            or frames.ndim != 3
            or tuple(frames.shape[-2:]) != shape
        ):
            got = tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames)
            raise ValueError(
                f"frames must be padded sensor frames (B, {shape[0]}, {shape[1]}), got {got}"
            )
        return crop_object_window(self.bank(frames), self.system)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """Reconstructions ``(B, 1, S, S)`` of padded frames ``(B, H_pad, W_pad)``."""
        windows = self.filtered(frames)
        return self.refine(windows.to(self.refine.intro.weight.dtype))


class MultiWienerNet(_FilterNet):
    """MultiWienerNet: ``K`` learnable Wiener deconvolutions of the frame, then a U-Net.

    Parameters
    ----------
    config : MultiWienerConfig
    system : SystemConfig
        Fixes the padded frame and sub-view sizes.
    psfs : torch.Tensor, optional
        Initial frame-sized PSFs ``(K, H_pad, W_pad)``; zeros when omitted (to be
        overwritten by loaded weights). :meth:`from_operator` starts from the physics.
    """

    config_class = MultiWienerConfig

    def __init__(
        self, config: MultiWienerConfig, system: SystemConfig, psfs: torch.Tensor | None = None
    ) -> None:
        if psfs is None:
            psfs = torch.zeros(config.rank, *system.padded_shape)
        if tuple(psfs.shape) != (config.rank, *system.padded_shape):
            raise ValueError(
                f"psfs must have shape ({config.rank}, "
                f"{system.padded_shape}), got {tuple(psfs.shape)}"
            )
        super().__init__(config, system, WienerBank(psfs, config.balance), config.rank)

    @classmethod
    def from_operator(cls, operator: CM2Operator, config: MultiWienerConfig) -> MultiWienerNet:
        """Wiener filters from the ``config.rank`` basis PSFs of ``operator``'s frame PSF."""
        return cls(config, operator.system, frame_psf_basis(operator, config.rank).float())


class SVFourierNet(_FilterNet):
    """SV-FourierNet: one learnable complex Fourier filter per view, then a U-Net.

    Parameters
    ----------
    config : FourierNetConfig
    system : SystemConfig
    gains : torch.Tensor, optional
        Initial complex filters ``(9, H_pad, W_pad // 2 + 1)``; zeros when omitted.
        :meth:`from_operator` starts from the per-view Wiener filters.
    """

    config_class = FourierNetConfig

    def __init__(
        self, config: FourierNetConfig, system: SystemConfig, gains: torch.Tensor | None = None
    ) -> None:
        rows, cols = system.padded_shape
        shape = (N_LENSES, rows, cols // 2 + 1)
        if gains is None:
            gains = torch.zeros(shape, dtype=torch.complex64)
        if tuple(gains.shape) != shape:
            raise ValueError(f"gains must have shape {shape}, got {tuple(gains.shape)}")
        super().__init__(config, system, FourierFilterBank(gains), N_LENSES)

    @classmethod
    def from_operator(cls, operator: CM2Operator, config: FourierNetConfig) -> SVFourierNet:
        """Filters = Wiener filters (``λ = balance · max|H|²``) of each lens's unit-sum
        centre PSF placed at its chief-ray offset."""
        system = operator.system
        psfs = unit_centre_psfs(operator).float()
        placed = torch.stack(
            [
                place_kernel(psf, offset, system.padded_shape)
                for psf, offset in zip(psfs, lens_offsets(system), strict=True)
            ]
        )
        gains = wiener_gain(placed, initial_regularisation(placed, config.balance))
        return cls(config, system, gains)


#: the learned baselines' model classes by name (the ``architecture`` of their model files)
LEARNED_MODELS: dict[str, type[_FilterNet]] = {
    cls.__name__: cls for cls in (MultiWienerNet, SVFourierNet)
}
