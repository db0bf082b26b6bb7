"""Sizes of the learned baselines: the filter bank and the refinement U-Net."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...config import ConfigError, check_int
from ...network.config import BlockConfig

__all__ = ["FourierNetConfig", "MultiWienerConfig"]


@dataclass(frozen=True)
class _BaselineConfig(BlockConfig):
    """Fields shared by both learned baselines.

    Attributes
    ----------
    balance : float
        Initial Wiener regularisation relative to the filter's peak ``|H|²``.
    width : int
        Channels of the first level of the refinement U-Net (a plain NAFNet U-Net).
    enc_blocks, dec_blocks : tuple of int
        NAF blocks per encoder / decoder level (same length: the down-sampling steps).
    middle_blocks : int
        NAF blocks at the bottom of the U-Net.
    """

    balance: float = 1e-2
    width: int = 16
    enc_blocks: tuple[int, ...] = (1, 1, 1)
    middle_blocks: int = 1
    dec_blocks: tuple[int, ...] = (1, 1, 1)

    block_lists = ("enc_blocks", "dec_blocks")

    @property
    def levels(self) -> int:
        """Down-sampling steps of the U-Net."""
        return len(self.enc_blocks)

    def validate(self) -> _BaselineConfig:
        """Check every field; raise :class:`~svcode_core.config.ConfigError` naming it."""
        if not (
            isinstance(self.balance, (int, float))
            and math.isfinite(self.balance)
            and self.balance > 0
        ):
            raise ConfigError(f"balance: must be a finite number > 0, got {self.balance!r}")
        check_int("width", self.width, 1)
        check_int("middle_blocks", self.middle_blocks, 0)
        for name in self.block_lists:
            value = getattr(self, name)
            if not isinstance(value, tuple) or not value:
                raise ConfigError(f"{name}: must be a non-empty list of integers, got {value!r}")
            for item in value:
                check_int(name, item, 0)
        if len(self.enc_blocks) != len(self.dec_blocks):
            raise ConfigError(
                f"dec_blocks: needs as many levels as enc_blocks "
                f"({len(self.enc_blocks)}), got {len(self.dec_blocks)}"
            )
        return self


@dataclass(frozen=True)
class MultiWienerConfig(_BaselineConfig):
    """MultiWienerNet: ``rank`` learnable Wiener filters over the padded frame, then a U-Net.

    Attributes
    ----------
    rank : int
        ``K``, the number of Wiener filters: the leading basis PSFs of the frame PSF's
        low-rank model (:func:`~.filters.frame_psf_basis`).
    """

    rank: int = 4

    def validate(self) -> MultiWienerConfig:
        check_int("rank", self.rank, 1)
        return super().validate()


@dataclass(frozen=True)
class FourierNetConfig(_BaselineConfig):
    """SV-FourierNet: one learnable Fourier filter per view over the padded frame, then a
    U-Net (the fields of the shared base)."""
