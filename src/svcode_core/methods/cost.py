"""Rough run times, said before a run starts (the plugin asks before long runs; ``svcode
demo`` says what it will cost). Rates of this project's CPUs on one thread, within a factor
of about two (``bench/results/recording.md``: about 0.8 s a cm2-mini frame, 35 s a cm2-v2
frame), and an assumed GPU speed-up."""

from __future__ import annotations

__all__ = ["DEFAULT_BYTES_PER_PIXEL", "GPU_SPEED_UP", "MIN_TILE_COST_SIDE", "SECONDS_PER_ITERATION",
           "SECONDS_PER_PIXEL_BYTE", "duration", "iteration_seconds", "tile_seconds"]

#: rough CPU seconds per tile pixel and per byte of the network's float32 working memory a
#: pixel (``SVCoDe.working_bytes_per_pixel``): its activations, a measure of its work that
#: follows a coarser grid (``pixel_unshuffle``) and narrower layers
SECONDS_PER_PIXEL_BYTE = 1.6e-9
#: float32 working bytes a pixel taken for a network not at hand (the bundled cm2-mini
#: model's)
DEFAULT_BYTES_PER_PIXEL = 3328
#: a tile costs at least as much as one of this side: the fixed cost of a network call
#: (about 10 ms for the bundled cm2-mini model's 16-px tiles)
MIN_TILE_COST_SIDE = 48
#: rough CPU seconds per LSV-ADMM / RL iteration on a 384 × 384 object grid
SECONDS_PER_ITERATION = 1.0
#: a GPU is taken to be this much faster
GPU_SPEED_UP = 20.0


def _speed(device: str) -> float:
    return 1.0 if str(device).startswith("cpu") else GPU_SPEED_UP


def tile_seconds(tiles: int, tile_side: int, bytes_per_pixel: float | None = None,
                 device: str = "cpu") -> float:
    """Rough seconds of ``tiles`` SV-CoDe tiles of side ``tile_side`` on ``device``, for a
    network of ``bytes_per_pixel`` float32 working memory a pixel (``None``:
    :data:`DEFAULT_BYTES_PER_PIXEL`).

    >>> round(tile_seconds(1, 384, 3328), 1)  # the bundled cm2-mini model: one tile a frame
    0.8
    >>> round(tile_seconds(9, 1280, 1272))  # the bundled cm2-v2 model: 9 tiles a frame
    30
    """
    pixels = max(tile_side, MIN_TILE_COST_SIDE) ** 2  # small tiles cost a call each
    bytes_per_pixel = DEFAULT_BYTES_PER_PIXEL if bytes_per_pixel is None else bytes_per_pixel
    return tiles * pixels * bytes_per_pixel * SECONDS_PER_PIXEL_BYTE / _speed(device)


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
