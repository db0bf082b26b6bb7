"""Coordinates, sub-view extraction and placement, sensor truncation.

Every map here is linear and comes with its exact adjoint, so that model-based solvers
can compose them with the low-rank blur (see :mod:`svcode_core.physics.cm2`). Conventions are
those of :mod:`svcode_core.config`: ``(row, col)`` order, normalised coordinates in
``[-1, 1]`` from the first to the last pixel centre, lenses row-major.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..config import N_LENSES, SystemConfig

__all__ = [
    "CONTEXT_SHIFTS",
    "assemble_frame",
    "assemble_window",
    "context_corners",
    "context_shifts",
    "context_views",
    "crop_to_sensor",
    "crops_at",
    "extract_sub_views",
    "field_radius",
    "lens_pitch",
    "normalized_coordinates",
    "pad_sensor_frame",
    "place_sub_views",
    "sensor_coverage",
    "sub_view_origins",
]

CONTEXT_SHIFTS = ((0, 0), (-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
"""Shifts of a lens's crop in lens pitches for :func:`context_views` at reach 1: itself
first, then its eight neighbours' places, row-major."""


def context_shifts(reach: int = 1) -> tuple[tuple[int, int], ...]:
    """Shifts in lens pitches of the crops :func:`context_views` cuts per lens.

    Reach 1 is :data:`CONTEXT_SHIFTS`; each further step of reach adds the crops that many
    pitches to the left and to the right, not up or down: in the presets the sensor's
    rows end within two pitches of every lens row's sub-view, so such crops would lie
    off the sensor where the edge strips need them.

    Examples
    --------
    >>> context_shifts(2)[9:]
    ((0, -2), (0, 2))
    """
    if not isinstance(reach, int) or isinstance(reach, bool) or reach < 1:
        raise ValueError(f"reach must be an integer >= 1, got {reach!r}")
    return CONTEXT_SHIFTS + tuple((0, sign * k) for k in range(2, reach + 1) for sign in (-1, 1))


def normalized_coordinates(
    size: int,
    start: int = 0,
    length: int | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Normalised coordinates of pixels ``start .. start + length - 1`` of a ``size`` grid.

    Pixel ``i`` of a grid of ``size`` pixels sits at ``2 i / (size - 1) - 1``, so the first
    and last pixel centres are exactly ``-1`` and ``1``. Pixels outside ``[0, size)``
    (for example the padding of a tile) continue the same line beyond ``[-1, 1]``.
    Computed in float64 and cast, so every value is the correctly rounded one.

    Parameters
    ----------
    size : int
        Number of pixels of the full grid (the sub-view size ``S``), at least 2.
    start : int
        Index of the first pixel wanted (may be negative).
    length : int, optional
        Number of pixels wanted; defaults to ``size - start``.
    dtype, device
        Of the returned tensor.

    Returns
    -------
    torch.Tensor
        Shape ``(length,)``.

    Examples
    --------
    >>> normalized_coordinates(5).tolist()
    [-1.0, -0.5, 0.0, 0.5, 1.0]
    """
    if size < 2:
        raise ValueError(f"size must be at least 2, got {size}")
    if length is None:
        length = size - start
    index = torch.arange(start, start + length, dtype=torch.float64, device=device)
    return (2.0 * index / (size - 1) - 1.0).to(dtype)


def field_radius(size: int) -> np.ndarray:
    """Normalised field radius ``(size, size)`` of every pixel of the object field: the
    distance from its centre in :func:`normalized_coordinates` (1 at the middle of each
    edge, √2 in the corners), float64.

    Examples
    --------
    >>> field_radius(3).round(3).tolist()
    [[1.414, 1.0, 1.414], [1.0, 0.0, 1.0], [1.414, 1.0, 1.414]]
    """
    axis = normalized_coordinates(size, dtype=torch.float64).numpy()
    return np.hypot(axis[:, None], axis[None, :])


def sub_view_origins(config: SystemConfig) -> np.ndarray:
    """Top-left padded-frame pixel of each sub-view, shape ``(9, 2)`` integer ``(row, col)``."""
    half = config.sub_view_size // 2
    return np.asarray(config.chief_rays, dtype=np.int64) - half


def _check_frame(frame: torch.Tensor, shape: tuple[int, int], what: str) -> None:
    if not isinstance(frame, torch.Tensor):
        raise TypeError(f"{what} must be a torch.Tensor, got {type(frame).__name__}")
    if frame.ndim < 2 or tuple(frame.shape[-2:]) != tuple(shape):
        raise ValueError(
            f"{what} must have shape (..., {shape[0]}, {shape[1]}), got {tuple(frame.shape)}"
        )


def _overlap(origin: int, size: int, extent: int) -> tuple[int, int, int, int]:
    """Intersection of ``[origin, origin + size)`` with ``[0, extent)``.

    Returns ``(frame_start, frame_stop, crop_start, crop_stop)``.
    """
    lo = max(origin, 0)
    hi = min(origin + size, extent)
    if hi <= lo:
        return 0, 0, 0, 0
    return lo, hi, lo - origin, hi - origin


def extract_sub_views(frame: torch.Tensor, config: SystemConfig, margin: int = 0) -> torch.Tensor:
    """Cut the nine ``S × S`` sub-views out of a padded sensor frame.

    Parts of a crop that fall outside the padded frame are zero.

    Parameters
    ----------
    frame : torch.Tensor
        Padded sensor frame(s), shape ``(..., H_pad, W_pad)``.
    config : SystemConfig
    margin : int
        Extra pixels on every side of each crop: the crops are ``(S + 2·margin)`` square
        and still centred on the chief rays.

    Returns
    -------
    torch.Tensor
        Shape ``(..., 9, S + 2·margin, S + 2·margin)``; view ``ℓ`` is centred on ``c_ℓ``.
    """
    _check_frame(frame, config.padded_shape, "padded sensor frame")
    return crops_at(frame, sub_view_origins(config) - margin, config.sub_view_size + 2 * margin)


def crops_at(frame: torch.Tensor, corners: np.ndarray, size: int) -> torch.Tensor:
    """``size``-square crops of a frame ``(..., H, W)`` at the top-left ``corners``
    ``(n, 2)``, zero where they leave the frame; shape ``(..., n, size, size)``."""
    rows, cols = frame.shape[-2:]
    crops = frame.new_empty(*frame.shape[:-2], len(corners), size, size)
    for index, (r0, c0) in enumerate(corners):
        fr0, fr1, vr0, vr1 = _overlap(int(r0), size, rows)
        fc0, fc1, vc0, vc1 = _overlap(int(c0), size, cols)
        crop = crops[..., index, :, :]
        if (vr0, vr1, vc0, vc1) != (0, size, 0, size):  # partly off the frame
            crop.zero_()
        crop[..., vr0:vr1, vc0:vc1] = frame[..., fr0:fr1, fc0:fc1]
    return crops


def lens_pitch(config: SystemConfig) -> tuple[int, int]:
    """Spacing of the lenses' chief rays along rows and columns, in sensor pixels (the
    mean over the 3 × 3 grid, rounded).

    Examples
    --------
    >>> lens_pitch(SystemConfig.preset("cm2-mini"))
    (144, 144)
    """
    rays = np.asarray(config.chief_rays, dtype=np.float64).reshape(3, 3, 2)
    rows = (rays[2, :, 0] - rays[0, :, 0]).mean() / 2
    cols = (rays[:, 2, 1] - rays[:, 0, 1]).mean() / 2
    return round(rows), round(cols)


def context_views(
    frame: torch.Tensor, config: SystemConfig, origin: tuple[int, int] = (0, 0),
    size: int | None = None, reach: int = 1,
) -> torch.Tensor:
    """Each lens's crop of a padded frame and the same crop moved by one lens pitch
    towards each of its eight neighbours (:data:`CONTEXT_SHIFTS`), and with ``reach`` 2 or
    more also by two or more pitches left and right (:func:`context_shifts`).

    The readings a pitch away carry what one position of the nine sub-views leaves open
    where some lenses' images fall off the sensor: at the field's left edge the lenses'
    sums at column ``u`` mix ``O(u)``, ``O(u + pitch)`` and ``O(u + 2·pitch)``, and the
    right lenses' reading at ``u + pitch`` is the third equation. That equation mixes two
    more unknowns, though; the one reading of the chain that a single lens column sees
    alone lies two pitches beyond the right lenses' own crop, which reach 2 adds (and
    symmetrically at the right edge). The first crop of lens ``ℓ`` (channel ``kℓ`` for
    ``k`` crops per lens) is its sub-view, as from :func:`extract_sub_views`.

    Parameters
    ----------
    frame : torch.Tensor
        Padded sensor frame(s), shape ``(..., H_pad, W_pad)``.
    config : SystemConfig
    origin : (int, int)
        Top-left corner of the crops in sub-view pixels (a tile's origin).
    size : int, optional
        Side of the crops; default the sub-view ``S``.
    reach : int
        How many pitches left and right the crops go (:func:`context_shifts`).

    Returns
    -------
    torch.Tensor
        Shape ``(..., 9 k, size, size)`` with ``k = len(context_shifts(reach))`` (81 at
        reach 1), lens-major: channel ``k ℓ + j`` is lens ``ℓ`` shifted by
        ``context_shifts(reach)[j]`` pitches; zero outside the padded frame.
    """
    _check_frame(frame, config.padded_shape, "padded sensor frame")
    corners = context_corners(config, origin, reach)
    return crops_at(frame, corners, config.sub_view_size if size is None else size)


def context_corners(
    config: SystemConfig, origin: tuple[int, int] = (0, 0), reach: int = 1
) -> np.ndarray:
    """Top-left padded-frame pixels ``(9 k, 2)`` of the crops :func:`context_views` cuts,
    in its channel order (``k = len(context_shifts(reach))``).

    Examples
    --------
    >>> corners = context_corners(SystemConfig.preset("cm2-mini"), (10, 20))
    >>> corners[0].tolist(), corners[5].tolist()  # lens 0 itself, and moved one pitch right
    ([10, 20], [10, 164])
    """
    shifts = np.asarray(context_shifts(reach)) * np.asarray(lens_pitch(config))
    return (sub_view_origins(config)[:, None] + np.asarray(origin) + shifts).reshape(-1, 2)


def place_sub_views(views: torch.Tensor, config: SystemConfig, margin: int = 0) -> torch.Tensor:
    """Adjoint of :func:`extract_sub_views`: add each view back at its place in the frame.

    Parameters
    ----------
    views : torch.Tensor
        Shape ``(..., 9, S + 2·margin, S + 2·margin)``.
    config : SystemConfig
    margin : int
        As in :func:`extract_sub_views`.

    Returns
    -------
    torch.Tensor
        Padded frame(s) ``(..., H_pad, W_pad)``: the sum of the placed views (overlaps add);
        parts falling outside the frame are dropped.
    """
    size = config.sub_view_size + 2 * margin
    if views.ndim < 3 or tuple(views.shape[-3:]) != (N_LENSES, size, size):
        raise ValueError(
            f"views must have shape (..., {N_LENSES}, {size}, {size}), got {tuple(views.shape)}"
        )
    rows, cols = config.padded_shape
    frame = views.new_zeros(*views.shape[:-3], rows, cols)
    for lens, (r0, c0) in enumerate(sub_view_origins(config) - margin):
        fr0, fr1, vr0, vr1 = _overlap(int(r0), size, rows)
        fc0, fc1, vc0, vc1 = _overlap(int(c0), size, cols)
        frame[..., fr0:fr1, fc0:fc1] += views[..., lens, vr0:vr1, vc0:vc1]
    return frame


def assemble_frame(views: torch.Tensor, config: SystemConfig) -> torch.Tensor:
    """The padded frame that the nine sub-views were cut from.

    Every padded-frame pixel that some sub-view covers gets its value back (the views
    that overlap there hold the same reading, averaged, so up to float rounding); pixels
    no view covers are zero. In the presets the nine views tile the padded frame, so
    this inverts :func:`extract_sub_views`.

    Parameters
    ----------
    views : torch.Tensor
        Shape ``(..., 9, S, S)``, as returned by :func:`extract_sub_views`.
    config : SystemConfig

    Returns
    -------
    torch.Tensor
        Padded frame(s) ``(..., H_pad, W_pad)``.
    """
    size = config.sub_view_size
    coverage = place_sub_views(views.new_ones(N_LENSES, size, size), config)
    return place_sub_views(views, config) / coverage.clamp(min=1)


def assemble_window(
    views: Any, config: SystemConfig, top: int, left: int, height: int, width: int
) -> torch.Tensor:
    """``assemble_frame(views, config)[top : top + height, left : left + width]`` for one
    frame's views ``(9, S, S)``, reading only the views' pixels in that window (zero
    outside the padded frame). ``views`` may be a memory-mapped array of any float type;
    the result is float32, the same sums in the same order as :func:`assemble_frame`.

    Examples
    --------
    >>> tiny = SystemConfig.tiny()
    >>> views = torch.rand(N_LENSES, tiny.sub_view_size, tiny.sub_view_size)
    >>> window = assemble_window(views, tiny, 10, -3, 20, 30)
    >>> torch.equal(window[:, 3:], assemble_frame(views, tiny)[10:30, :27])
    True
    """
    out = torch.zeros(height, width)
    rows, cols = config.padded_shape
    row0, row1 = max(top, 0), min(top + height, rows)  # the window's part inside the frame
    col0, col1 = max(left, 0), min(left + width, cols)
    if row0 >= row1 or col0 >= col1:
        return out
    total = torch.zeros(row1 - row0, col1 - col0)
    count = torch.zeros(row1 - row0, col1 - col0)
    size = config.sub_view_size
    for lens, (r0, c0) in enumerate(sub_view_origins(config)):
        wr0, wr1, vr0, vr1 = _overlap(int(r0) - row0, size, row1 - row0)
        wc0, wc1, vc0, vc1 = _overlap(int(c0) - col0, size, col1 - col0)
        if wr0 < wr1 and wc0 < wc1:
            part = views[lens, vr0:vr1, vc0:vc1]
            if not isinstance(part, torch.Tensor):  # a copy: stored views are read-only
                part = torch.tensor(np.asarray(part))
            total[wr0:wr1, wc0:wc1] += part.float()
            count[wr0:wr1, wc0:wc1] += 1
    out[row0 - top : row1 - top, col0 - left : col1 - left] = total / count.clamp(min=1)
    return out


def crop_to_sensor(frame: torch.Tensor, config: SystemConfig) -> torch.Tensor:
    """Raw sensor reading from a padded frame: the sensor window, shape ``(..., *sensor)``."""
    _check_frame(frame, config.padded_shape, "padded sensor frame")
    rows, cols = config.sensor_window
    return frame[..., rows, cols]


def pad_sensor_frame(sensor: torch.Tensor, config: SystemConfig) -> torch.Tensor:
    """Adjoint of :func:`crop_to_sensor`: zero-pad a raw frame to the padded shape."""
    _check_frame(sensor, config.sensor_shape, "raw sensor frame")
    pad_r, pad_c = config.padding
    return torch.nn.functional.pad(sensor, (pad_c, pad_c, pad_r, pad_r))


def sensor_coverage(
    config: SystemConfig,
    dtype: torch.dtype = torch.float32,
    device: torch.device | None = None,
    margin: int = 0,
) -> torch.Tensor:
    """Which pixels of each sub-view the sensor reads: 1 on the sensor, 0 in the padding
    (and, with ``margin``, beyond the padded frame).

    Returns
    -------
    torch.Tensor
        Shape ``(9, S + 2·margin, S + 2·margin)``: each sub-view enlarged by ``margin`` on
        every side, as :func:`extract_sub_views` cuts it.

    Examples
    --------
    >>> config = SystemConfig.preset("cm2-mini")
    >>> coverage = sensor_coverage(config)
    >>> coverage[4].mean().item(), coverage[0, :, :16].max().item()  # centre lens; a corner's
    (1.0, 0.0)
    >>> tuple(sensor_coverage(config, margin=16).shape)
    (9, 416, 416)
    """
    sensor = torch.ones(config.sensor_shape, dtype=dtype, device=device)
    return extract_sub_views(pad_sensor_frame(sensor, config), config, margin)
