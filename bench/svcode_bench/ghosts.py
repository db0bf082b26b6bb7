"""Ghost probe: does a bright object alone in a dark field come back only where it is?

Every lens images the whole field, so an object's light lands on the sensor once per
lens, one lens pitch apart. Demixing must give each copy to its own lens; a copy it keeps
in the wrong lens's view comes out of the reconstruction as a *ghost*, a fainter copy of
the object one pitch away. The outer views are cut by the sensor edge, so some copies
have no partner that would tell them apart, and a method that looks at the frame only
patch by patch can take them for objects of their own.

:func:`ghost_probe` images one uniform disc at a field position through the nominal
instrument and reads the reconstruction at the disc and at the four positions one pitch
away, as fractions of the disc's level. A model-based solver that inverts the whole
forward model has no ghosts (its readings there stay at the noise level).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from svcode_core.config import SystemConfig
from svcode_core.physics.simulate import Simulator

__all__ = ["DIRECTIONS", "GhostReading", "ghost_probe", "lens_pitch"]

#: the four neighbours one lens pitch away, as (row, column) steps
DIRECTIONS = {"up": (-1, 0), "down": (1, 0), "left": (0, -1), "right": (0, 1)}


@dataclass(frozen=True)
class GhostReading:
    """The reconstruction of one disc, read at the disc and one pitch away.

    Attributes
    ----------
    own : float
        Mean of the reconstruction over the disc's inner half-radius square, divided by
        the disc's level (1: the right brightness).
    ghosts : dict[str, float]
        The same one pitch away in each direction of :data:`DIRECTIONS` whose square lies
        inside the field (0: no ghost).
    """

    own: float
    ghosts: dict[str, float]

    @property
    def worst(self) -> float:
        """The largest ghost (0 when none lies inside the field)."""
        return max(self.ghosts.values(), default=0.0)


def lens_pitch(system: SystemConfig) -> tuple[int, int]:
    """The smallest nonzero spacing of the chief rays along rows and along columns.

    Examples
    --------
    >>> lens_pitch(SystemConfig.preset("cm2-mini"))
    (144, 144)
    """
    rays = np.asarray(system.chief_rays)
    steps = []
    for axis in (0, 1):
        spacing = np.diff(np.unique(rays[:, axis]))
        steps.append(int(spacing.min()) if spacing.size else 0)
    return steps[0], steps[1]


def ghost_probe(
    reconstruct: Callable[[np.ndarray], np.ndarray],
    simulator: Simulator,
    centre: tuple[int, int],
    radius: int,
    level: float = 1.0,
    seed: int = 0,
) -> GhostReading:
    """Image a uniform disc alone in a dark field and read the reconstruction.

    Parameters
    ----------
    reconstruct : callable
        Raw frame ``(H, W)`` to the ``(S, S)`` object estimate.
    simulator : Simulator
        The instrument the frame comes from (noise included).
    centre : (int, int)
        The disc's centre in sub-view pixels.
    radius : int
        The disc's radius in pixels; the readings average a square of half-side
        ``max(radius // 2, 3)``.
    level : float
        The disc's brightness (the object scale: 1 is the brightest the presets expect).
    seed : int
        Noise seed of the frame.

    Returns
    -------
    GhostReading

    Examples
    --------
    >>> system = SystemConfig.preset("cm2-mini")
    >>> reading = ghost_probe(lambda raw: np.zeros((384, 384)), Simulator(system),
    ...                       (192, 192), 20)
    >>> reading.own, reading.worst
    (0.0, 0.0)
    """
    size = simulator.system.sub_view_size
    rows, cols = np.mgrid[:size, :size]
    disc = (rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 < radius**2
    estimate = np.asarray(reconstruct(simulator.simulate(disc * np.float32(level), seed=seed)
                                      .measurement), dtype=np.float64)
    half = max(radius // 2, 3)

    def read(row: int, col: int) -> float | None:
        if not (half <= row < size - half and half <= col < size - half):
            return None
        return float(estimate[row - half:row + half, col - half:col + half].mean()) / level

    pitch = lens_pitch(simulator.system)
    ghosts = {}
    for name, (down, right) in DIRECTIONS.items():
        value = read(centre[0] + down * pitch[0], centre[1] + right * pitch[1])
        if value is not None:
            ghosts[name] = value
    own = read(*centre)
    return GhostReading(own=0.0 if own is None else own, ghosts=ghosts)
