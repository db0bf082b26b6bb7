"""Sizes of the learned baselines: the filter bank and the refinement U-Net."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

from ..config import ConfigError

__all__ = ["FourierNetConfig", "MultiWienerConfig"]

_BLOCK_LISTS = ("enc_blocks", "dec_blocks")


@dataclass(frozen=True)
class _BaselineConfig:
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

    def __post_init__(self) -> None:
        for name in _BLOCK_LISTS:  # JSON gives lists; keep the dataclass hashable
            value = getattr(self, name)
            if isinstance(value, list):
                object.__setattr__(self, name, tuple(value))

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
        _check_int("width", self.width, 1)
        _check_int("middle_blocks", self.middle_blocks, 0)
        for name in _BLOCK_LISTS:
            value = getattr(self, name)
            if not isinstance(value, tuple) or not value:
                raise ConfigError(f"{name}: must be a non-empty list of integers, got {value!r}")
            for item in value:
                _check_int(name, item, 0)
        if len(self.enc_blocks) != len(self.dec_blocks):
            raise ConfigError(
                f"dec_blocks: needs as many levels as enc_blocks "
                f"({len(self.enc_blocks)}), got {len(self.dec_blocks)}"
            )
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of every field."""
        data = dataclasses.asdict(self)
        for name in _BLOCK_LISTS:
            data[name] = list(data[name])
        return data

    def to_json(self) -> str:
        """The configuration as an indented JSON string."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> _BaselineConfig:
        """Parse and validate; unknown fields and bad values name the field."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigError(f"model: not valid JSON ({err})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"model: expected a JSON object, got {type(data).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"model.{unknown[0]}: unknown field (known: {sorted(names)})")
        return cls(**data).validate()


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
        _check_int("rank", self.rank, 1)
        return super().validate()


@dataclass(frozen=True)
class FourierNetConfig(_BaselineConfig):
    """SV-FourierNet: one learnable Fourier filter per view over the padded frame, then a
    U-Net (the fields of the shared base)."""


def _check_int(name: str, value: Any, minimum: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ConfigError(f"{name}: must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{name}: must be >= {minimum}, got {value}")
