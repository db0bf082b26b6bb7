"""Rough run times, said before a run starts (the plugin asks before long runs; ``svcode
demo`` says what it will cost). Rates of this project's CPUs, within a factor of about two
(``bench/results/recording.md``: 1 s a cm2-mini frame, 55-80 s a cm2-v2 frame on two
cores), and an assumed GPU speed-up."""

from __future__ import annotations

__all__ = ["GPU_SPEED_UP", "SECONDS_PER_ITERATION", "SECONDS_PER_TILE", "duration",
           "iteration_seconds", "tile_seconds"]

#: rough CPU seconds per SV-CoDe tile of 96 × 96 pixels (larger tiles scale with area)
SECONDS_PER_TILE = 0.15
#: rough CPU seconds per LSV-ADMM / RL iteration on a 384 × 384 object grid
SECONDS_PER_ITERATION = 1.0
#: a GPU is taken to be this much faster
GPU_SPEED_UP = 20.0


def _speed(device: str) -> float:
    return 1.0 if str(device).startswith("cpu") else GPU_SPEED_UP


def tile_seconds(tiles: int, tile_side: int, device: str = "cpu") -> float:
    """Rough seconds of ``tiles`` SV-CoDe tiles of side ``tile_side`` on ``device``.

    >>> round(tile_seconds(16, 650), 0)  # a cm2-v2 frame's tiles
    110.0
    """
    return tiles * SECONDS_PER_TILE * max(1.0, (tile_side / 96) ** 2) / _speed(device)


def iteration_seconds(sub_view_size: int, device: str = "cpu") -> float:
    """Rough seconds of one LSV-ADMM or Richardson-Lucy iteration on ``device``."""
    return SECONDS_PER_ITERATION * (sub_view_size / 384) ** 2 / _speed(device)


def duration(seconds: float) -> str:
    """``seconds`` for people: seconds, minutes or hours.

    >>> duration(12.3), duration(150), duration(7200)
    ('12 s', '3 min', '2.0 h')
    """
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{-(-seconds // 60):.0f} min"
    return f"{seconds / 3600:.1f} h"
