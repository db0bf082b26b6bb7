"""A bar target at several field positions: the finest line pair resolved at each.

The seed paper shows a uniform field by imaging a resolution target at the centre and at
the edge and reading off the finest line pair resolved at both. Here one target holds, at
each field position of :data:`POSITIONS`, a group of three vertical bars and a group of
three horizontal bars of one period (one line pair: a bar and a gap of half a period each,
rendered with exact pixel coverage, each group starting on a whole pixel). A group is
*resolved* when the reconstruction's profile across its bars dips between neighbouring
bars by at least :data:`RAYLEIGH_DIP` of the bars' level (the dip between two points at
the Rayleigh distance), in both orientations. :func:`finest_resolved` gives, per
position, the smallest period resolved, with every coarser one resolved too.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

__all__ = [
    "GROUP_GAP",
    "PERIODS",
    "PERIODS_AIRY_RADIUS",
    "POSITIONS",
    "RAYLEIGH_DIP",
    "BarGroup",
    "bar_dip",
    "bar_target",
    "finest_resolved",
    "periods_for",
]

#: field positions: the target's centre in normalised field coordinates ``(row, col)``
#: (``-1..1`` from edge to edge; the benchmark's outer ring starts at radius 0.8)
POSITIONS: dict[str, tuple[float, float]] = {
    "centre": (0.0, 0.0),
    "mid-field": (0.0, 0.5),
    "ring": (0.0, 0.8),
    "corner": (0.75, 0.75),
}
#: line-pair periods in object pixels, finest first, for a PSF whose Airy radius is
#: :data:`PERIODS_AIRY_RADIUS` sensor pixels (cm2-mini's; :func:`periods_for` scales them)
PERIODS: tuple[float, ...] = (2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)
PERIODS_AIRY_RADIUS = 2.0
#: pixels between a position's vertical and horizontal groups at that Airy radius
GROUP_GAP = 4.0
#: relative dip between two equal points at the Rayleigh distance (of an Airy pattern)
RAYLEIGH_DIP = 0.264
_BARS = 3


@dataclass(frozen=True)
class BarGroup:
    """Three bars of one period: where they lie and which way they run.

    Attributes
    ----------
    top, left : float
        Corner of the group's first bar, object pixels (pixel ``i`` covers ``[i, i + 1)``).
    period : float
        Line-pair period, pixels.
    length : float
        Length of the bars, pixels.
    vertical : bool
        Bars run along the rows (the profile goes across the columns).
    """

    top: float
    left: float
    period: float
    length: float
    vertical: bool

    @property
    def extent(self) -> tuple[float, float]:
        """``(height, width)`` in pixels."""
        across = (_BARS - 0.5) * self.period
        return (self.length, across) if self.vertical else (across, self.length)


def periods_for(airy_radius: float) -> tuple[float, ...]:
    """:data:`PERIODS` scaled to a PSF whose Airy radius is ``airy_radius`` sensor pixels
    (the object and sensor pixels of every preset keep the same ratio).

    >>> periods_for(8.0)
    (8.0, 10.0, 12.0, 16.0, 20.0, 24.0, 32.0)
    """
    return tuple(period * airy_radius / PERIODS_AIRY_RADIUS for period in PERIODS)


def _coverage(size: int, start: float, stop: float) -> np.ndarray:
    """Fraction of each of ``size`` pixels that ``[start, stop)`` covers."""
    edges = np.arange(size + 1, dtype=np.float64)
    return np.clip(np.minimum(edges[1:], stop) - np.maximum(edges[:-1], start), 0, 1)


def _render(group: BarGroup, size: int) -> np.ndarray:
    along = _coverage(size, group.top if group.vertical else group.left,
                      (group.top if group.vertical else group.left) + group.length)
    first = group.left if group.vertical else group.top
    across = sum(_coverage(size, first + k * group.period, first + (k + 0.5) * group.period)
                 for k in range(_BARS))
    image = along[:, None] * across[None, :]
    return image if group.vertical else image.T


def bar_target(size: int, period: float,
               positions: Mapping[str, tuple[float, float]] = POSITIONS, gap: float = GROUP_GAP,
               ) -> tuple[np.ndarray, dict[str, tuple[BarGroup, BarGroup]]]:  # fmt: skip
    """An ``(size, size)`` object of brightness 1 holding, at each position, a vertical and
    a horizontal bar group of ``period``, side by side, ``gap`` pixels apart.

    Returns
    -------
    (object, groups)
        float32 image; per position its ``(vertical, horizontal)`` groups.

    Examples
    --------
    >>> image, groups = bar_target(64, 4.0, {"centre": (0.0, 0.0)})
    >>> float(image.max()), round(float(image.sum()), 6)
    (1.0, 120.0)
    """
    length = max(10.0, 2.5 * period)
    across = (_BARS - 0.5) * period
    image = np.zeros((size, size), np.float64)
    groups = {}
    for name, (row, col) in positions.items():
        centre_row, centre_col = (size / 2) * (1 + row), (size / 2) * (1 + col)
        # groups start on whole pixels, so the finest bars (one pixel wide) are not
        # smeared over two by the grid
        width = np.ceil(across) + gap + length
        left = round(centre_col - width / 2)
        vertical = BarGroup(round(centre_row - length / 2), left, period, length, True)
        horizontal = BarGroup(round(centre_row - across / 2), left + np.ceil(across) + gap,
                              period, length, False)
        for group in (vertical, horizontal):
            height, extent = group.extent
            if (group.top < 0 or group.left < 0 or group.top + height > size
                    or group.left + extent > size):
                raise ValueError(f"the {period:g}-px bars at {name} do not fit a "
                                 f"{size}-px field")
            image += _render(group, size)
        groups[name] = (vertical, horizontal)
    return image.astype(np.float32), groups


def bar_dip(image: np.ndarray, group: BarGroup) -> float:
    """The smaller relative dip between neighbouring bars of ``group`` in ``image``:
    ``1 − gap / mean of the two bars``, each read by linear interpolation of the profile
    averaged along the bars' middle half (1 for perfectly resolved bars, 0 or below for
    bars blurred into one).

    Examples
    --------
    >>> image, groups = bar_target(64, 8.0, {"centre": (0.0, 0.0)})
    >>> vertical, horizontal = groups["centre"]
    >>> bar_dip(image, vertical), bar_dip(image, horizontal)
    (1.0, 1.0)
    """
    values = np.asarray(image, dtype=np.float64)
    if not group.vertical:
        values = values.T
        group = BarGroup(group.left, group.top, group.period, group.length, True)
    rows = slice(int(np.floor(group.top + group.length / 4)),
                 int(np.ceil(group.top + 3 * group.length / 4)))
    profile = values[rows].mean(axis=0)
    pixels = np.arange(profile.size) + 0.5  # pixel centres
    bars = [group.left + (k + 0.25) * group.period for k in range(_BARS)]
    read = np.interp(bars + [(a + b) / 2 for a, b in zip(bars, bars[1:], strict=False)],
                     pixels, profile)
    peaks, gaps = read[:_BARS], read[_BARS:]
    dips = [1 - gap / ((peaks[k] + peaks[k + 1]) / 2) if peaks[k] + peaks[k + 1] > 0
            else 0.0 for k, gap in enumerate(gaps)]
    return float(min(dips))


def finest_resolved(dips: Mapping[float, float], threshold: float = RAYLEIGH_DIP,
                    ) -> float | None:  # fmt: skip
    """The smallest period whose dip, and that of every coarser period, reaches
    ``threshold``; ``None`` when the coarsest is not resolved.

    Examples
    --------
    >>> finest_resolved({2.0: 0.1, 3.0: 0.3, 4.0: 0.2, 5.0: 0.6})
    5.0
    >>> finest_resolved({2.0: 0.5, 3.0: 0.6}) , finest_resolved({2.0: 0.1})
    (2.0, None)
    """
    finest = None
    for period in sorted(dips, reverse=True):
        if dips[period] < threshold:
            break
        finest = period
    return finest
