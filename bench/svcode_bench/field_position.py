"""The same content at the centre and in the outer ring: the field's own deficit.

The benchmark's zone PSNRs (:func:`~svcode_core.evaluation.metrics.field_zones`) compare
different content: a scene's centre and its outer ring hold different structures (one
bright cell in the middle of a dark field, vessels that thin out towards the edge), so
the gap between them mixes what the instrument and the method do at the periphery with
how the scene happens to be laid out. Here every scene is imaged a second, third and
fourth time moved by half the field (wrapping round, :func:`numpy.roll`) along the
rows, the columns and both. Content that sat in the centre then lies in the outer ring,
and content from the ring lies in the centre; :func:`same_content_zones` compares the
errors on those very pixels of content at the two places.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import _check_pair, field_zones, psnr_from_mse

__all__ = [
    "SameContentZones",
    "edge_strip_width",
    "half_field_shifts",
    "moved_scene",
    "same_content_zones",
]

Shift = tuple[int, int]


def edge_strip_width(system: SystemConfig) -> int:
    """Width of the field's left and right edge strips in object pixels: the sub-view
    columns that the outer lens columns lose off the sensor (the padding of its columns),
    so that only six of the nine lenses see them.

    >>> edge_strip_width(SystemConfig.preset("cm2-mini"))
    16
    >>> edge_strip_width(SystemConfig.preset("cm2-v2"))
    100
    """
    return system.padding[1]


def half_field_shifts(size: int) -> tuple[Shift, Shift, Shift]:
    """The three moves by half the field: along rows, along columns, along both.

    Examples
    --------
    >>> half_field_shifts(384)
    ((192, 0), (0, 192), (192, 192))
    """
    half = size // 2
    return (half, 0), (0, half), (half, half)


def moved_scene(image: np.ndarray, shift: Shift) -> np.ndarray:
    """``image`` moved by ``shift`` pixels (rows, columns), wrapping round the field.

    Content pixel ``p`` of ``image`` lands at ``p + shift`` (modulo the size).

    Examples
    --------
    >>> moved_scene(np.arange(4).reshape(2, 2), (1, 0))
    array([[2, 3],
           [0, 1]])
    """
    return np.roll(image, shift, axis=(0, 1))


@dataclass(frozen=True)
class SameContentZones:
    """PSNR of one set of content pixels where it sits in the centre and in the ring.

    Attributes
    ----------
    centre, ring : float
        PSNR (dB) over the compared content pixels, imaged at their centre-zone position
        and at their outer-ring position.
    pixels : int
        Number of content pixels compared (each counted once per move that takes it from
        one zone into the other).
    """

    centre: float
    ring: float
    pixels: int

    @property
    def gap(self) -> float:
        """``centre - ring`` in dB: what the outer ring loses on the same content."""
        return self.centre - self.ring


def same_content_zones(
    truth: np.ndarray,
    estimate: np.ndarray,
    moved_estimates: Mapping[Shift, np.ndarray],
    data_range: float = 1.0,
    ring: np.ndarray | None = None,
) -> SameContentZones:
    """Compare the errors on the same content at the centre and in the outer ring.

    Parameters
    ----------
    truth : array_like
        The scene ``(S, S)`` as imaged in place.
    estimate : array_like
        Its reconstruction.
    moved_estimates : mapping
        For each shift (e.g. :func:`half_field_shifts`), the reconstruction of
        ``moved_scene(truth, shift)``, in the moved frame's own coordinates.
    data_range : float
        Span of the truth's intensities (1 for objects in ``[0, 1]``).
    ring : array_like of bool, optional
        Field positions ``(S, S)`` that count as the ring: a part of the outer ring (e.g.
        its edge strips) to compare with the centre alone. Default: the whole outer ring.

    Returns
    -------
    SameContentZones
        Over every content pixel that one of the moves takes from the centre zone into
        the outer ring or back, the squared errors where it sat in the centre against
        those where it sat in the ring (pooled over the moves, then as PSNR).

    Examples
    --------
    A method whose error is 0.01 in the centre and 0.03 in the ring, whatever it images:

    >>> truth = np.random.default_rng(0).random((64, 64))
    >>> zones = field_zones(64)
    >>> error = 0.01 * zones["centre"] + 0.03 * zones["ring"]
    >>> moved = {s: moved_scene(truth, s) + error for s in half_field_shifts(64)}
    >>> result = same_content_zones(truth, truth + error, moved)
    >>> round(result.centre, 3), round(result.ring, 3), round(result.gap, 3)
    (40.0, 30.458, 9.542)
    """
    truth, estimate = _check_pair(truth, estimate, data_range)
    if not moved_estimates:
        raise ValueError("moved_estimates: give the reconstruction of at least one moved scene")
    zones = field_zones(truth.shape[0])
    if ring is not None:
        ring = np.asarray(ring, dtype=bool)
        if ring.shape != truth.shape:
            raise ValueError(f"ring must be a boolean image of shape {truth.shape}, "
                             f"got {ring.shape}")
        zones["ring"] = zones["ring"] & ring
    in_place = (estimate - truth) ** 2
    at_centre, in_ring = [], []
    for shift, moved in moved_estimates.items():
        moved = np.asarray(moved, dtype=np.float64)
        _check_pair(moved_scene(truth, shift), moved, data_range)
        back = (moved_scene(moved, (-shift[0], -shift[1])) - truth) ** 2  # content coordinates
        # the zone each content pixel lies in once moved
        moved_centre = moved_scene(zones["centre"], (-shift[0], -shift[1]))
        moved_ring = moved_scene(zones["ring"], (-shift[0], -shift[1]))
        outward = zones["centre"] & moved_ring
        inward = zones["ring"] & moved_centre
        at_centre += [in_place[outward], back[inward]]
        in_ring += [back[outward], in_place[inward]]
    at_centre_errors, in_ring_errors = np.concatenate(at_centre), np.concatenate(in_ring)
    if at_centre_errors.size == 0:
        raise ValueError("no content pixel moves between the centre and the ring with these "
                         "shifts")
    return SameContentZones(
        centre=psnr_from_mse(float(at_centre_errors.mean()), data_range),
        ring=psnr_from_mse(float(in_ring_errors.mean()), data_range),
        pixels=int(at_centre_errors.size),
    )
