"""Calibrate a CM² instrument from a point-source scan.

A lab records a **point-source scan**: a bead or pinhole at ``N`` object positions
``p_n`` (pixels of the ``S × S`` object grid, fractions allowed: a stage does not stop on
pixel centres), one raw frame each, in any order; the frames of a position recorded more
than once are averaged first. Lens ``ℓ`` images the source to the padded-sensor point
``c_ℓ - S//2 + p_n`` blurred by its PSF at ``p_n`` (:mod:`svcode_core.config`).
The operator's PSFs are images of a source on a whole object pixel, so the frame of a
source a fraction ``f_n = p_n - q_n`` off its nearest pixel ``q_n`` is first moved back by
``-f_n`` (a Fourier shift, :func:`_subpixel_shift`): it is then the frame of a source on
``q_n`` with the PSFs of ``p_n``. :func:`calibrate` turns the scan into a system:

1. **Spots**: per position, the local maxima of the frame smoothed over an Airy core
   (:func:`skimage.feature.peak_local_max`) above a threshold derived from the noise
   (median absolute deviation of the frames) are assigned to the lens whose nominal
   image point lies within half a lens pitch.
2. **Chief rays**: each spot fully on the sensor gives its centroid minus the centroid of
   the nominal model's PSF at ``p_n`` (which carries the nominal distortion and coma
   shift; the nominal PSF at ``p_n`` is the one the operator uses, the grid PSFs
   interpolated). That difference is the lens's offset ``o_ℓ`` plus the instrument's
   departure from the nominal centroid shift, which all lenses share as a function of the
   field vector ``f`` from their axis: ``Σ_j b_j |f|^(j-1) f``, ``j`` in
   :data:`FIELD_POWERS` (coma moves a centroid about ``∝ h``, distortion ``∝ h³``). The
   offsets and ``b_j`` are fitted together by least squares: an outer lens sees only part
   of its field, so its mean difference alone would carry the departure at its spots as a
   bias, while the centre lens, which sees its field around its axis, pins ``b_j``. The
   offsets are then split, again by least squares, into an array translation, an array
   rotation about the lattice centre and per-lens residuals.
3. **PSFs**: the ``k × k`` window at ``round(c_ℓ) - S//2 + q_n`` of every moved frame is
   the registered PSF of lens ``ℓ`` at ``p_n`` (the sub-pixel part of the chief ray stays
   in it, as in :mod:`svcode_core.physics.instrument`). The PSFs on the ``G × G`` grid are
   fitted to them by least squares through the same cubic interpolation the low-rank
   operator uses (:func:`svcode_core.physics.lowrank.interpolation_basis`, here at
   ``p_n``), pixel by pixel over the pixels that are on the sensor, with a weak prior
   towards the nominal model for grid nodes the scan does not reach.
4. **Vignetting**: the throughput (sum) of every grid PSF, relative to the nominal
   model's total; the bead's brightness, unknown, is set so the measured stack's total
   equals the nominal one on the spots both see.
5. **Low-rank order**: the smallest ``K`` of every lens meeting the tolerance.

Errors on bad input name the frame (or the position line) at fault.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.stats import median_abs_deviation, norm
from skimage.feature import peak_local_max

from ..config import N_LENSES, SystemConfig
from .lowrank import decompose_psfs
from .optics import field_vectors, psf_grid_positions, system_psfs

__all__ = [
    "Calibration",
    "CalibrationError",
    "Progress",
    "calibrate",
    "fit_array",
    "psf_fwhm",
    "read_positions",
    "report_text",
    "save_calibration",
]

#: Weight of the nominal-model prior on a grid PSF, as a fraction of the mean data weight
#: of a grid node: enough to fix nodes the scan does not reach, a 1 % pull elsewhere.
PRIOR_WEIGHT = 1e-2

#: Rows and columns at each sensor edge left out of the PSF fit in a frame moved by a
#: sub-pixel shift: the interpolation there reaches past the sensor.
SHIFT_MARGIN = 2

#: Powers of the normalised field ``h`` in the centroid shift fitted beside the chief rays
#: (step 2 above): coma's shift is about linear in ``h``, distortion's cubic.
FIELD_POWERS = (1, 3)

#: ``progress(stage, fraction)``: what :func:`calibrate` is doing and the fraction done.
Progress = Callable[[str, float], None]


class CalibrationError(ValueError):
    """The scan, its positions or the system cannot give a calibration."""


# ------------------------------------------------------------------- inputs
#: Header names of a positions file: columns in object pixels, and in micrometres (``y``
#: along the rows, ``x`` along the columns); each name gives its axis, 0 row, 1 column.
PIXEL_COLUMNS = {"row": 0, "col": 1}
MICROMETRE_COLUMNS = {"y_um": 0, "x_um": 1}


def read_positions(path: str | Path, pixel_size: float | None = None, *,
                   size: int | None = None, frames: int | None = None) -> np.ndarray:  # fmt: skip
    """Read the source positions of a scan from a CSV file.

    One line per frame of the scan, in the scan's order (any order of positions; a
    position on several lines: its frames are averaged by :func:`calibrate`). A header
    line names the two columns:

    * ``row,col`` (or ``col,row``): object pixels of the ``S × S`` grid, fractions
      allowed (a bead is rarely centred on a pixel); a file without a header is read as
      ``row,col``;
    * ``x_um,y_um`` (or ``y_um,x_um``): stage micrometres from the centre of the object
      field, object pixel ``(S//2, S//2)``, the point each lens images on its chief ray;
      ``x`` runs along the columns, ``y`` along the rows. Needs ``pixel_size`` and ``size``.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    pixel_size : float, optional
        Object-space pixel size in micrometres (sensor pixel over magnification).
    size : int, optional
        ``S``: positions are checked to lie on the grid, pixels 0 to ``S - 1``.
    frames : int, optional
        Frames in the scan: the file must give exactly one position per frame.

    Returns
    -------
    numpy.ndarray
        ``(N, 2)`` float64 ``(row, col)`` positions in object pixels.

    Raises
    ------
    CalibrationError
        One line naming the file and the line at fault: an unknown header, a line that
        is not two numbers, micrometres without a pixel size, a position off the grid,
        fewer or more positions than frames.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "pos.csv"
    >>> _ = path.write_text("x_um,y_um\\n0,0\\n-3.5,8.75\\n")
    >>> read_positions(path, pixel_size=3.5, size=48)
    array([[24. , 24. ],
           [26.5, 23. ]])
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"positions file not found: {path}")
    name = path.name
    # utf-8-sig: a spreadsheet's CSV may start with a byte-order mark
    lines = [(number, [cell.strip() for cell in cells]) for number, cells in
             enumerate(csv.reader(path.read_text(encoding="utf-8-sig").splitlines()), start=1)
             if any(cell.strip() for cell in cells)]  # fmt: skip
    if not lines:
        raise CalibrationError(f"{name}: no positions (an empty file)")
    number, first = lines[0]
    if all(_number(cell) is None for cell in first):
        lines = lines[1:]
        names = [cell.lower() for cell in first]
        if sorted(names) == sorted(PIXEL_COLUMNS):
            axes, scale = [PIXEL_COLUMNS[n] for n in names], None
        elif sorted(names) == sorted(MICROMETRE_COLUMNS):
            axes = [MICROMETRE_COLUMNS[n] for n in names]
            if pixel_size is None:
                raise CalibrationError(
                    f"{name} line {number}: positions in micrometres ({','.join(first)}) need "
                    "the object-space pixel size in micrometres (svcode calibrate --pixel-size)")
            if not (math.isfinite(pixel_size) and pixel_size > 0):
                raise CalibrationError(f"the pixel size must be a positive number of "
                                       f"micrometres, got {pixel_size:g}")  # fmt: skip
            if size is None:
                raise ValueError("read_positions: micrometres need the object grid's size")
            scale = float(pixel_size)
        else:
            raise CalibrationError(
                f"{name} line {number}: unknown header {','.join(first)!r}: expected row,col "
                "(object pixels) or x_um,y_um (stage micrometres)")
    else:
        names, axes, scale = ["row", "col"], [0, 1], None
    if not lines:
        raise CalibrationError(f"{name}: no positions after the header line {number}")
    columns = ",".join(names)
    positions = np.empty((len(lines), 2))
    for index, (number, cells) in enumerate(lines):
        if len(cells) != 2:
            raise CalibrationError(f"{name} line {number}: expected 2 values {columns}, got "
                                   f"{len(cells)}: {','.join(cells)!r}")  # fmt: skip
        for cell, axis in zip(cells, axes, strict=True):
            value = _number(cell)
            if value is None:
                raise CalibrationError(f"{name} line {number}: {cell!r} is not a number "
                                       f"(expected {columns})")  # fmt: skip
            positions[index, axis] = value if scale is None else size // 2 + value / scale
        row, col = positions[index]
        if size is not None and not (0 <= row <= size - 1 and 0 <= col <= size - 1):
            where = "" if scale is None else f" ({columns} = {','.join(cells)})"
            raise CalibrationError(
                f"{name} line {number}: position ({row:g}, {col:g}){where} lies outside the "
                f"{size}×{size} object grid (pixels 0 to {size - 1})")
    if frames is not None and len(positions) < frames:
        raise CalibrationError(
            f"{name}: {len(positions)} positions for {frames} frames: frame {len(positions)} "
            f"has no position (the last is on line {lines[-1][0]})")
    if frames is not None and len(positions) > frames:
        raise CalibrationError(f"{name} line {lines[frames][0]}: more positions than the "
                               f"{frames} frames of the scan")  # fmt: skip
    return positions


def _number(cell: str) -> float | None:
    """The finite number a CSV cell holds, else ``None``."""
    try:
        value = float(cell)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _check_scan(frames: np.ndarray, positions: np.ndarray, system: SystemConfig,
                saturation: float) -> None:  # fmt: skip
    """Raise :class:`CalibrationError` naming the first frame at fault."""
    if frames.ndim != 3:
        raise CalibrationError(f"scan must be an N×H×W stack of frames, got shape {frames.shape}")
    if tuple(frames.shape[1:]) != tuple(system.sensor_shape):
        raise CalibrationError(
            f"frame 0 is {frames.shape[1]}×{frames.shape[2]} px but system {system.name!r} "
            f"has a {system.sensor_shape[0]}×{system.sensor_shape[1]} sensor: a scan of "
            "another sensor, or the wrong --preset/--system")
    if len(frames) != len(positions):
        raise CalibrationError(
            f"the scan has {len(frames)} frames but the positions list {len(positions)}: "
            f"frame {min(len(frames), len(positions))} has "
            + ("no position" if len(frames) > len(positions) else "no frame"))
    size = system.sub_view_size
    on_grid = np.isfinite(positions) & (positions >= 0) & (positions <= size - 1)
    outside = np.flatnonzero(~on_grid.all(axis=1))
    if outside.size:
        n = int(outside[0])
        raise CalibrationError(f"frame {n}: position ({positions[n, 0]:g}, {positions[n, 1]:g}) "
                               f"lies outside the {size}×{size} object grid")
    # one pass, a frame at a time: a paper-scale scan is gigabytes
    finite, saturated = [], []
    for frame in frames:
        finite.append(np.isfinite(frame).all())
        saturated.append((frame >= saturation).any())
    bad = np.flatnonzero(~np.array(finite, dtype=bool))
    if bad.size:
        raise CalibrationError(f"frame {int(bad[0])}: contains NaN or Inf values")
    saturated = np.flatnonzero(saturated)
    if saturated.size:
        n = int(saturated[0])
        r, c = np.unravel_index(int(np.argmax(frames[n])), frames.shape[1:])
        raise CalibrationError(
            f"frame {n}: saturated spot at sensor pixel ({r}, {c}) (reading >= {saturation:g}); "
            f"{saturated.size} frame(s) saturate: record them with a shorter exposure")


# ------------------------------------------------------------------- result
@dataclass
class Calibration:
    """A calibrated system and what was measured to make it.

    Attributes
    ----------
    system : SystemConfig
        The nominal system with the fitted (integer) chief rays, the tolerance and,
        once saved, ``psf_model`` naming the PSF stack.
    psfs : numpy.ndarray
        ``(9, G·G, k, k)`` fitted grid PSFs registered to ``system.chief_rays``.
    chief_rays : numpy.ndarray
        ``(9, 2)`` fitted chief rays (float, padded-frame pixels).
    offsets : numpy.ndarray
        ``(9, 2)`` fitted displacement of each chief ray from the nominal one, pixels.
    offset_errors : numpy.ndarray
        ``(9, 2)`` standard errors of ``offsets``.
    array_shift : numpy.ndarray
        ``(2,)`` least-squares translation of the lens array, pixels.
    array_rotation_deg : float
        Least-squares rotation of the lens array about the lattice centre, degrees.
    lens_residuals : numpy.ndarray
        ``(9, 2)`` offsets left after the translation and rotation (per-lens errors).
    field_shift : numpy.ndarray
        ``(len(FIELD_POWERS),)`` coefficients ``b_j`` (pixels) of the centroid shift's
        departure from the nominal optics along the field direction, ``Σ_j b_j h^j``; their
        sum is the departure at the edge of a lens's field (``h = 1``).
    centroids : numpy.ndarray
        ``(N, 9, 2)`` measured spot centroids in sensor pixels of every frame (of the mean
        frame of its position), NaN where not measured.
    predicted : numpy.ndarray
        ``(N, 9, 2)`` centroids predicted by the fitted chief rays and nominal optics.
    throughput : numpy.ndarray
        ``(9, G·G)`` sum of every grid PSF (vignetting), nominal on-axis total = 1.
    ranks : tuple of int
        Low-rank order ``K`` of every lens at ``system.rank_tolerance``.
    brightness : float
        Source brightness the frames were divided by.
    noise_sigma : float
        Estimated noise standard deviation of one (raw, not averaged) frame's background.
    """

    system: SystemConfig
    psfs: np.ndarray
    chief_rays: np.ndarray
    offsets: np.ndarray
    offset_errors: np.ndarray
    array_shift: np.ndarray
    array_rotation_deg: float
    lens_residuals: np.ndarray
    field_shift: np.ndarray
    centroids: np.ndarray
    predicted: np.ndarray
    throughput: np.ndarray
    ranks: tuple[int, ...]
    brightness: float
    noise_sigma: float

    @property
    def residual_rms(self) -> np.ndarray:
        """``(9,)`` RMS distance in pixels between measured and predicted centroids."""
        error = np.linalg.norm(self.centroids - self.predicted, axis=-1)
        return np.sqrt(np.nanmean(error**2, axis=0))


# ---------------------------------------------------------------- the steps
def _lens_pitch(system: SystemConfig) -> float:
    rays = np.asarray(system.chief_rays, float)
    distance = np.linalg.norm(rays[:, None] - rays[None], axis=-1)
    return float(distance[distance > 0].min())


def _image_points(system: SystemConfig, rays: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """``(N, 9, 2)`` sensor points ``c_ℓ - S//2 + p_n - padding``."""
    offset = np.asarray(rays, float) - system.sub_view_size // 2 - np.asarray(system.padding)
    return positions[:, None, :].astype(float) + offset[None]


def _windows(frames: np.ndarray, corners: np.ndarray, k: int,
             margin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``k × k`` crops at integer top-left ``corners`` ``(N, 9, 2)``; zero and masked off-sensor.

    ``margin`` ``(N, 2)``: rows and columns at each sensor edge of frame ``n`` that are
    masked too. Returns windows ``(N, 9, k, k)`` and the on-sensor mask of the same shape.
    """
    n, height, width = frames.shape
    margin = np.zeros((n, 2), np.int64) if margin is None else margin
    rows = corners[..., 0, None] + np.arange(k)  # (N, 9, k)
    cols = corners[..., 1, None] + np.arange(k)
    low_r, low_c = (margin[:, None, None, i] for i in range(2))
    inside = ((rows >= low_r) & (rows < height - low_r))[..., :, None] & (
        (cols >= low_c) & (cols < width - low_c))[..., None, :]
    r = np.clip(rows, 0, height - 1)[..., :, None]
    c = np.clip(cols, 0, width - 1)[..., None, :]
    frame = np.arange(n)[:, None, None, None]
    return np.where(inside, frames[frame, r, c].astype(np.float64), 0.0), inside


def _centroid(windows: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroid ``(..., 2)`` of ``(..., k, k)`` windows, from the centre."""
    k = windows.shape[-1]
    axis = np.arange(k) - k // 2
    total = windows.sum(axis=(-2, -1))[..., None]
    rows = (windows.sum(axis=-1) * axis).sum(axis=-1)
    cols = (windows.sum(axis=-2) * axis).sum(axis=-1)
    moments = np.stack([rows, cols], axis=-1)
    return np.divide(moments, total, out=np.full_like(moments, np.nan), where=total != 0)


def _find_spots(frames: np.ndarray, expected: np.ndarray, system: SystemConfig,
                sigma: float, progress: Progress, labels: list[str]) -> np.ndarray:  # fmt: skip
    """``(N, 9, 2)`` integer peak of each lens's spot, ``-1`` where none is detected.

    ``frames`` are the scan's positions (their mean frames), ``labels`` name their frames
    in errors; ``progress`` hears of every position, as the fractions 0.05 to 0.5.
    """
    radius = _lens_pitch(system) / 2.0
    smooth_sigma = max(system.optics.airy_radius / 2.0, 0.5)
    # Noise of the smoothed frame: white noise through a unit-sum Gaussian.
    smooth_noise = sigma / (2.0 * math.sqrt(math.pi) * smooth_sigma)
    # One false peak in the whole scan is expected at this many standard deviations.
    threshold = float(norm.isf(1.0 / frames.size)) * smooth_noise
    peaks = np.full(expected.shape, -1, dtype=np.int64)
    for n, frame in enumerate(frames):
        progress(f"finding spots: position {n + 1} of {len(frames)}",
                 0.05 + 0.45 * n / len(frames))  # fmt: skip
        smooth = ndimage.gaussian_filter(frame, smooth_sigma)
        found = peak_local_max(smooth, min_distance=max(1, int(radius // 2)),
                               threshold_abs=threshold, exclude_border=False)  # fmt: skip
        if found.size == 0:
            raise CalibrationError(
                f"{labels[n]}: no spot above the detection threshold {threshold:.3g} "
                f"(noise {sigma:.3g}); is the source in the field and the exposure long enough?")
        distance = np.linalg.norm(found[None, :, :] - expected[n][:, None, :], axis=-1)
        for lens in range(N_LENSES):
            near = np.flatnonzero(distance[lens] < radius)
            if near.size:
                best = near[np.argmax(smooth[found[near, 0], found[near, 1]])]
                peaks[n, lens] = found[best]
        if (peaks[n] < 0).all():
            raise CalibrationError(f"{labels[n]}: spots found, but none within {radius:.0f} px of "
                                   "a lens's nominal image point: wrong positions or system?")
    return peaks


def _field_vectors(positions: np.ndarray, system: SystemConfig) -> np.ndarray:
    """``(N, 9, 2)`` normalised field vectors of every lens at object positions ``(N, 2)``."""
    points = 2.0 * np.asarray(positions, np.float64) / (system.sub_view_size - 1) - 1.0
    return np.stack([field_vectors(system, lens, points) for lens in range(N_LENSES)], axis=1)


def _fit_offsets(shift: np.ndarray, use: np.ndarray, field: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Lens offsets and the shared centroid-shift departure by least squares (step 2).

    ``shift`` ``(N, 9, 2)``: measured minus nominal centroid; ``use`` ``(N, 9)``: the spots
    that count; ``field`` ``(N, 9, 2)``: normalised field vectors. Returns the offsets and
    their standard errors ``(9, 2)`` and ``b_j`` (:data:`FIELD_POWERS`); ``b_j`` are zero
    where the spots do not determine them (a scan that does not spread over the field).
    """
    spot, lens = np.nonzero(use)
    count = len(spot)
    f = field[spot, lens]
    h = np.hypot(f[:, 0], f[:, 1])
    design = np.zeros((count, 2, 2 * N_LENSES + len(FIELD_POWERS)))
    design[np.arange(count), 0, 2 * lens] = 1.0
    design[np.arange(count), 1, 2 * lens + 1] = 1.0
    for j, power in enumerate(FIELD_POWERS):
        design[:, :, 2 * N_LENSES + j] = f * h[:, None] ** (power - 1)
    design = design.reshape(2 * count, -1)
    if np.linalg.matrix_rank(design) < design.shape[1]:
        design = design[:, : 2 * N_LENSES]
    values = shift[spot, lens].ravel()
    solution, *_ = np.linalg.lstsq(design, values, rcond=None)
    residual = values - design @ solution
    variance = float(residual @ residual) / max(len(values) - design.shape[1], 1)
    covariance = variance * np.linalg.inv(design.T @ design)
    errors = np.sqrt(np.diag(covariance)[: 2 * N_LENSES]).reshape(N_LENSES, 2)
    field_shift = np.zeros(len(FIELD_POWERS))
    field_shift[: design.shape[1] - 2 * N_LENSES] = solution[2 * N_LENSES:]
    return solution[: 2 * N_LENSES].reshape(N_LENSES, 2), errors, field_shift


def _shared_shift(field: np.ndarray, field_shift: np.ndarray) -> np.ndarray:
    """``(..., 2)`` centroid-shift departure ``Σ_j b_j |f|^(j-1) f`` at field vectors ``field``."""
    h = np.hypot(field[..., 0], field[..., 1])[..., None]
    terms = zip(field_shift, FIELD_POWERS, strict=True)
    return sum(b * field * h ** (power - 1) for b, power in terms)


def fit_array(offsets: np.ndarray, system: SystemConfig) -> tuple[np.ndarray, float, np.ndarray]:
    """Split lens offsets into array translation, small rotation and per-lens residuals.

    Parameters
    ----------
    offsets : numpy.ndarray
        ``(9, 2)`` displacement ``(row, col)`` of each lens's image, pixels.
    system : SystemConfig
        Its chief rays fix the lattice centre the rotation turns about.

    Returns
    -------
    (numpy.ndarray, float, numpy.ndarray)
        Translation ``(2,)``, rotation in degrees, residuals ``(9, 2)`` (least squares).
    """
    rays = np.asarray(system.chief_rays, float)
    relative = rays - rays.mean(axis=0)
    design = np.zeros((2 * N_LENSES, 3))
    design[0::2, 0] = 1.0
    design[1::2, 1] = 1.0
    design[0::2, 2] = -relative[:, 1]  # a small rotation θ moves (r, c) by θ·(-c, r)
    design[1::2, 2] = relative[:, 0]
    solution, *_ = np.linalg.lstsq(design, offsets.ravel(), rcond=None)
    residual = (offsets.ravel() - design @ solution).reshape(N_LENSES, 2)
    return solution[:2], math.degrees(solution[2]), residual


def _grid_design(positions: np.ndarray, system: SystemConfig) -> np.ndarray:
    """``(N, G·G)`` weights of the grid PSFs at each position (the operator's interpolation).

    The cubic spline of :func:`svcode_core.physics.lowrank.interpolation_basis`, evaluated
    at positions that may fall between pixels.
    """
    grid, size = system.optics.psf_grid, system.sub_view_size
    if grid == 1:
        return np.ones((len(positions), 1))
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(np.linspace(-1.0, 1.0, grid), np.eye(grid), axis=0,
                         bc_type="not-a-knot")  # fmt: skip
    coords = np.clip(2.0 * np.asarray(positions, np.float64) / (size - 1) - 1.0, -1.0, 1.0)
    rows, cols = spline(coords[:, 0]), spline(coords[:, 1])  # (N, G)
    return np.einsum("na,nb->nab", rows, cols).reshape(len(positions), -1)


def _average_repeats(frames: np.ndarray, positions: np.ndarray, dark: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The mean frame of every distinct position, background removed: ``dark``, or else each
    frame's median.

    Returns the distinct positions ``(M, 2)`` (sorted, so the scan's order does not
    matter), their mean frames ``(M, H, W)`` in float32 (summed in float64 one frame at a
    time, so that a paper-scale scan costs one float32 copy), the number of frames of each
    ``(M,)`` and the index of every frame's position ``(N,)``.
    """
    distinct, which, counts = np.unique(positions, axis=0, return_inverse=True,
                                        return_counts=True)  # fmt: skip
    which = which.ravel()
    means = np.empty((len(distinct), *frames.shape[1:]), np.float32)
    for m in range(len(distinct)):
        total = np.zeros(frames.shape[1:])
        for n in np.flatnonzero(which == m):
            frame = np.asarray(frames[n], np.float64)
            total += frame - (np.median(frame) if dark is None else dark)
        means[m] = total / counts[m]
    return distinct, means, counts, which


def _subpixel_shift(frame: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``frame`` moved by a sub-pixel ``shift`` ``(row, col)``.

    A Fourier shift, exact for an image sampled finely enough for its optics; the frame
    is mirrored at its edges first, so that a spot the sensor cuts does not ring.
    """
    pad = 16
    padded = np.pad(frame, pad, mode="symmetric")
    spectrum = ndimage.fourier_shift(np.fft.rfft2(padded), shift, n=padded.shape[1])
    return np.fft.irfft2(spectrum, padded.shape)[pad:-pad, pad:-pad]


def _fit_grid(samples: np.ndarray, masks: np.ndarray, design: np.ndarray,
              prior: np.ndarray) -> np.ndarray:  # fmt: skip
    """Masked least-squares grid PSFs of one lens.

    ``samples, masks`` ``(N, k, k)``, ``design`` ``(N, G·G)``, ``prior`` ``(G·G, k, k)``.
    Each kernel pixel is fitted over the positions where it is on the sensor; pixels with
    the same set of positions share one factorisation.
    """
    n, k, _ = samples.shape
    nodes = design.shape[1]
    y = samples.reshape(n, -1)
    m = masks.reshape(n, -1)
    out = np.empty((nodes, k * k))
    weight = PRIOR_WEIGHT * float(np.mean(np.sum(design**2, axis=0)))
    patterns, which = np.unique(m.T, axis=0, return_inverse=True)
    for index, pattern in enumerate(patterns):
        pixels = np.flatnonzero(which.ravel() == index)
        a = design[pattern]
        normal = a.T @ a + weight * np.eye(nodes)
        rhs = a.T @ y[pattern][:, pixels] + weight * prior.reshape(nodes, -1)[:, pixels]
        out[:, pixels] = np.linalg.solve(normal, rhs)
    return out.reshape(nodes, k, k)


def _denoise(psfs: np.ndarray, sigma: float, count: int) -> np.ndarray:
    """Zero the grid-PSF pixels indistinguishable from noise, clip what is left at 0.

    ``sigma`` is the noise of a fitted pixel; the threshold leaves one noise pixel in the
    whole stack on average (``count`` pixels).
    """
    threshold = float(norm.isf(1.0 / count)) * sigma
    return np.where(psfs > threshold, psfs, 0.0)


# ------------------------------------------------------------------- driver
def calibrate(
    frames: np.ndarray,
    positions: np.ndarray,
    system: SystemConfig,
    dark: np.ndarray | None = None,
    tolerance: float | None = None,
    saturation: float | None = None,
    progress: Progress | None = None,
) -> Calibration:
    """Calibrate ``system`` from a point-source scan.

    Parameters
    ----------
    frames : numpy.ndarray
        ``(N, H, W)`` raw frames, ``H × W`` the system's sensor.
    positions : numpy.ndarray
        ``(N, 2)`` source positions ``(row, col)`` in pixels of the object grid, fractions
        allowed (:func:`read_positions`), in any order; the frames of a position are
        averaged (in the PSF fit, a position weighs as many frames as it has).
    system : SystemConfig
        The nominal system: sensor, object grid, PSF grid and kernel size, starting chief
        rays and the pupil model used for the centroid shifts and as a weak prior.
    dark : numpy.ndarray, optional
        Dark frame ``(H, W)`` or stack ``(M, H, W)`` (averaged), subtracted from every
        frame; without it each frame's median is taken as its background.
    tolerance : float, optional
        Low-rank tolerance; default ``system.rank_tolerance``.
    saturation : float, optional
        Reading at which a pixel is saturated; default the full scale of integer frames,
        else ``system.noise.saturation``.
    progress : callable, optional
        ``progress(stage, fraction)`` is called, in the calling thread, as every step
        starts (every frame while finding spots, every lens while fitting PSFs) with a
        short description and the fraction of the work done, from 0 to 1 (the last call).
        An exception it raises stops the calibration and propagates: a way to cancel.

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationError
        For mismatched counts, positions outside the grid, another sensor size, saturated
        or missing spots (naming the frame), or a scan that does not determine the PSF grid.
    """
    report = progress if progress is not None else _silent
    report("checking the scan", 0.0)
    system = system.validate()
    frames = np.asarray(frames)
    if saturation is None:  # integer camera data saturate at the type's full scale
        integer = np.issubdtype(frames.dtype, np.integer)
        saturation = float(np.iinfo(frames.dtype).max) if integer else system.noise.saturation
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    saturation = float(saturation)
    _check_scan(frames, positions, system, saturation)
    tolerance = system.rank_tolerance if tolerance is None else float(tolerance)
    system = system.replace(rank=None, rank_tolerance=tolerance, psf_model=None)
    if dark is not None:
        dark = np.asarray(dark, dtype=np.float64)
        dark = dark.mean(axis=0) if dark.ndim == 3 else dark
        if dark.shape != frames.shape[1:]:
            raise CalibrationError(f"dark frame is {dark.shape[0]}×{dark.shape[1]} px, the scan's "
                                   f"frames {frames.shape[1]}×{frames.shape[2]}")  # fmt: skip
    # From here on, one mean frame per distinct position (whatever the scan's order); in
    # the PSF fit and the brightness a position of c frames weighs c, as its frames would.
    positions, frames, counts, which = _average_repeats(frames, positions, dark)
    labels = [_frame_label(np.flatnonzero(which == m)) for m in range(len(positions))]
    # Robust noise of one frame's background: spots cover a small fraction of every frame.
    spread = np.array([median_abs_deviation(frame, axis=None, scale="normal")
                       for frame in frames])
    sigma = float(np.median(spread * np.sqrt(counts)))
    sigma = max(sigma, 1e-12)
    # A source a fraction f off its nearest whole pixel q: its frame moved back by -f is
    # the frame of a source on q, as the operator's PSFs are, with the PSF shapes of p.
    nearest = np.floor(positions + 0.5)
    fraction = positions - nearest
    frames = _registered(frames, fraction)
    margin = np.where(fraction != 0, SHIFT_MARGIN, 0)
    k = system.optics.kernel_size
    half = k // 2
    nominal_rays = np.asarray(system.chief_rays, float)
    expected = _image_points(system, nominal_rays, nearest)
    peaks = _find_spots(frames, np.rint(expected).astype(np.int64), system,
                        sigma / math.sqrt(counts.min()), report, labels)  # fmt: skip
    report("fitting the chief rays", 0.5)

    # -- chief rays: centroid of each whole spot against the nominal PSF's centroid
    found = (peaks >= 0).all(axis=-1)
    whole = np.zeros((N_LENSES, 2))
    for lens in range(N_LENSES):
        if not found[:, lens].any():
            raise CalibrationError(f"lens {lens}: no spot in any frame; the scan must reach "
                                   "every lens's field")  # fmt: skip
        whole[lens] = np.rint(np.median(peaks[found[:, lens], lens] - expected[found[:, lens],
                                                                              lens], axis=0))
    centres = np.rint(expected + whole[None]).astype(np.int64)
    windows, inside = _windows(frames, centres - half, k, margin)
    complete = found & inside.all(axis=(-2, -1))
    # The nominal model's image of each point: its grid PSFs interpolated as the operator
    # does, at the position p itself.
    design = _grid_design(positions, system)
    nominal = np.einsum("ng,lgij->nlij", design, system_psfs(system))
    shift = _centroid(windows) - _centroid(nominal)  # (N, 9, 2) sub-pixel moves
    for lens in range(N_LENSES):
        if complete[:, lens].sum() < 2:
            raise CalibrationError(f"lens {lens}: {int(complete[:, lens].sum())} spot(s) wholly "
                                   "on the sensor, at least 2 are needed to fit its chief ray")
    field = _field_vectors(positions, system)
    offsets, errors, field_shift = _fit_offsets(shift, complete, field)
    offsets += whole
    array_shift, rotation, residuals = fit_array(offsets, system)
    fitted = nominal_rays + offsets
    rays = np.rint(fitted).astype(np.int64)
    # in the recorded frames, where the source was
    predicted = (_image_points(system, fitted, positions) + _centroid(nominal)
                 + _shared_shift(field, field_shift))
    centroids = centres + _centroid(windows) + fraction[:, None]
    system = system.replace(chief_rays=tuple((int(r), int(c)) for r, c in rays))

    # -- PSFs: windows at the calibrated integer image points, fitted to the grid
    windows, inside = _windows(frames, _image_points(system, rays, nearest).astype(np.int64)
                               - half, k, margin)  # fmt: skip
    prior_psfs = system_psfs(system, offsets=fitted - rays)
    overlap = complete & inside.all(axis=(-2, -1))
    weight = np.broadcast_to(counts[:, None], overlap.shape)
    measured = (windows.sum(axis=(-2, -1)) * weight)[overlap].sum()
    predicted_sum = (np.einsum("ng,lgij->nl", design, prior_psfs) * weight)[overlap].sum()
    brightness = float(measured / predicted_sum)
    if design.shape[0] < design.shape[1] or np.linalg.matrix_rank(design) < design.shape[1]:
        g = system.optics.psf_grid
        raise CalibrationError(
            f"the {len(positions)} distinct positions do not determine the {g}×{g} PSF grid "
            f"(optics.psf_grid): scan at least {g} distinct rows and {g} distinct columns "
            "spread over the object grid")
    root = np.sqrt(counts)
    samples = windows / brightness * root[:, None, None, None]
    design = design * root[:, None]
    psfs = []
    for lens in range(N_LENSES):
        report(f"fitting the PSFs: lens {lens + 1} of {N_LENSES}", 0.55 + 0.4 * lens / N_LENSES)
        psfs.append(_fit_grid(samples[:, lens], inside[:, lens], design, prior_psfs[lens]))
    psfs = np.stack(psfs)
    # noise of a fitted pixel: one frame's noise over the number of frames fitting a node
    per_node = float(np.mean(np.sum(design**2, axis=0)))
    psfs = _denoise(psfs, sigma / brightness / math.sqrt(per_node), psfs.size)
    reference = float(system_psfs(system).sum(axis=(-2, -1)).max())
    throughput = psfs.sum(axis=(-2, -1)) / reference
    report("choosing the low-rank order", 0.95)
    ranks = tuple(decompose_psfs(lens_psfs_, None, tolerance).rank for lens_psfs_ in psfs)
    report("done", 1.0)
    spots = complete[which, :, None]  # per frame of the scan again
    return Calibration(
        system=system, psfs=psfs, chief_rays=fitted, offsets=offsets, offset_errors=errors,
        array_shift=array_shift, array_rotation_deg=rotation, lens_residuals=residuals,
        field_shift=field_shift,
        centroids=np.where(spots, centroids[which], np.nan),
        predicted=np.where(spots, predicted[which], np.nan),
        throughput=throughput, ranks=ranks, brightness=brightness, noise_sigma=sigma,
    )  # fmt: skip


def _frame_label(frames: np.ndarray) -> str:
    """How errors name the frames of one position: ``frame 7`` or ``frames 7, 56 (averaged)``."""
    if len(frames) == 1:
        return f"frame {int(frames[0])}"
    return f"frames {', '.join(str(int(n)) for n in frames)} (averaged)"


def _registered(frames: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """Each frame moved by ``-fraction`` ``(N, 2)``, in place: as if its source sat on a
    whole pixel."""
    for frame, move in zip(frames, fraction, strict=True):
        if move.any():
            frame[...] = _subpixel_shift(frame, -move)
    return frames


def _silent(stage: str, fraction: float) -> None:
    """The :data:`Progress` of a caller that did not ask for one."""


# ------------------------------------------------------------------ output
#: Finer sampling (per pixel and axis) on which :func:`psf_fwhm` measures the half-maximum area.
FWHM_UPSAMPLE = 4


def psf_fwhm(psfs: np.ndarray) -> np.ndarray:
    """Full width at half maximum of each PSF ``(..., k, k)``, in pixels.

    The diameter of the disc whose area is that of the region at or above half the peak
    that holds the peak (read on a :data:`FWHM_UPSAMPLE` times finer grid, cubic spline), so
    an aberrated, elongated PSF gets one width; NaN for a PSF without a positive peak.

    Examples
    --------
    >>> r = np.hypot(*np.mgrid[-8:9, -8:9])
    >>> gaussian = np.exp(-(r / 3.0) ** 2 * 4 * np.log(2))  # FWHM 3 px
    >>> round(float(psf_fwhm(gaussian)), 1)
    3.0
    """
    psfs = np.asarray(psfs, dtype=np.float64)
    flat = psfs.reshape(-1, *psfs.shape[-2:])
    out = np.full(len(flat), np.nan)
    up = FWHM_UPSAMPLE
    for index, psf in enumerate(flat):
        peak = psf.max()
        if not peak > 0:
            continue
        labels, _ = ndimage.label(psf >= peak / 2)
        top = np.unravel_index(np.argmax(psf), psf.shape)
        rows, cols = np.nonzero(labels == labels[top])
        # fine samples at the centres of 1/up-pixel cells over the core, one pixel around
        r = np.arange((rows.min() - 1) * up, (rows.max() + 2) * up) / up + (0.5 / up - 0.5)
        c = np.arange((cols.min() - 1) * up, (cols.max() + 2) * up) / up + (0.5 / up - 0.5)
        grid = np.meshgrid(r, c, indexing="ij")
        fine = ndimage.map_coordinates(psf, grid, order=3, mode="constant")
        labels, _ = ndimage.label(fine >= peak / 2)
        centre = np.unravel_index(np.argmax(fine), fine.shape)
        area = np.count_nonzero(labels == labels[centre]) / up**2
        out[index] = 2.0 * math.sqrt(area / math.pi)
    return out.reshape(psfs.shape[:-2])


def _fwhm_lines(calibration: Calibration) -> list[str]:
    """The FWHM of the fitted PSFs at each field point of the PSF grid, over the lenses,
    in pixels and (when the system knows its pixel size) object-space micrometres."""
    system = calibration.system
    fwhm = psf_fwhm(calibration.psfs)  # (9, G·G)
    pixel = system.object_pixel_um
    half = (system.sub_view_size - 1) / 2  # normalised field 1 is this many pixels out
    lines = [
        "PSF FWHM by field point, over the nine lenses "
        + (f"(object pixel {pixel:g} um)" if pixel is not None
           else "(pixel size unknown: give the system object_pixel_um for micrometres)"),
        "field (v, u)     from centre (y, x) um    FWHM px median [min-max]    "
        "FWHM um median [min-max]",
    ]
    for node, (v, u) in enumerate(psf_grid_positions(system)):
        values = fwhm[:, node][np.isfinite(fwhm[:, node])]
        if not len(values):
            continue
        stats = (np.median(values), values.min(), values.max())
        pixels = "{:6.2f} [{:.2f}-{:.2f}]".format(*stats)
        if pixel is None:
            where, microns = "-", "-"
        else:
            where = f"({v * half * pixel:+9.1f}, {u * half * pixel:+9.1f})"
            microns = "{:7.2f} [{:.2f}-{:.2f}]".format(*(value * pixel for value in stats))
        lines.append(f"({v:+.2f}, {u:+.2f})   {where:>22}    {pixels:>24}    {microns:>24}")
    return lines


def report_text(calibration: Calibration, nominal: SystemConfig) -> str:
    """A plain-text report of a calibration: chief rays, array motion, residuals, PSFs
    (their FWHM at each field point in pixels and micrometres)."""
    cal = calibration
    lines = [
        f"calibration of {nominal.name!r}: {len(cal.centroids)} frames, noise sigma "
        f"{cal.noise_sigma:.3g}, source brightness {cal.brightness:.4g}",
        f"lens array: shift ({cal.array_shift[0]:+.3f}, {cal.array_shift[1]:+.3f}) px, "
        f"rotation {cal.array_rotation_deg:+.4f} deg",
        "spot centroids off the nominal optics' along the field by "
        + " ".join(f"{b:+.3f} h^{power}"
                   for b, power in zip(cal.field_shift, FIELD_POWERS, strict=True))
        + f" px ({cal.field_shift.sum():+.3f} px at the edge of a lens's field, h = 1)",
        "lens  nominal ray   fitted ray            offset (+- s.e.) px            "
        "per-lens residual px  spots  centroid rms px  K  peak throughput",
    ]
    spots = np.isfinite(cal.centroids[..., 0]).sum(axis=0)
    for lens in range(N_LENSES):
        nr, nc = nominal.chief_rays[lens]
        fr, fc = cal.chief_rays[lens]
        (dr, dc), (er, ec) = cal.offsets[lens], cal.offset_errors[lens]
        jr, jc = cal.lens_residuals[lens]
        lines.append(
            f"{lens:4d}  ({nr:4d}, {nc:4d})  ({fr:8.3f}, {fc:8.3f})  ({dr:+.3f} +- {er:.3f}, "
            f"{dc:+.3f} +- {ec:.3f})  ({jr:+.3f}, {jc:+.3f})  {spots[lens]:5d}  "
            f"{cal.residual_rms[lens]:15.3f}  {cal.ranks[lens]}  "
            f"{cal.throughput[lens].max():.3f}")
    lines.append(f"low-rank order K = {max(cal.ranks)} at tolerance "
                 f"{cal.system.rank_tolerance:g} (per lens {list(cal.ranks)})")
    lines += ["", *_fwhm_lines(cal)]
    return "\n".join(lines) + "\n"


def save_calibration(calibration: Calibration, out_dir: str | Path,
                     nominal: SystemConfig) -> dict[str, Path]:  # fmt: skip
    """Write the calibrated system and everything it refers to into ``out_dir``.

    Files: ``system.json`` (``psf_model`` = ``psfs.tif``, relative), ``psfs.tif`` and
    ``psfs.positions.json`` (:func:`svcode_core.physics.psf_io.save_psfs`), ``calibration.json``
    (fitted chief rays, offsets, array motion, the centroid shift off the nominal optics,
    throughput, ranks, the PSF FWHM ``(9, G·G)`` in pixels and micrometres) and
    ``report.txt``. The report's figure, ``report.png``, is drawn above the physics
    (:func:`svcode_core.evaluation.figures.calibration_figure`, by ``svcode calibrate`` and
    the Calibration widget).

    Returns
    -------
    dict of str to Path
        The files written, by kind.
    """
    from ..io import write_json_atomic
    from .psf_io import save_psfs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cal = calibration
    fwhm, pixel = psf_fwhm(cal.psfs), cal.system.object_pixel_um
    psf_file, positions_file = save_psfs(out / "psfs.tif", cal.psfs, cal.system)
    system = cal.system.replace(psf_model=str(psf_file.resolve()))
    files = {"system": system.save(out / "system.json"), "psfs": psf_file,
             "positions": positions_file}  # fmt: skip
    files["calibration"] = write_json_atomic(out / "calibration.json", {
        "nominal": nominal.name,
        "chief_rays": cal.chief_rays.tolist(),
        "offsets_px": cal.offsets.tolist(),
        "offset_errors_px": cal.offset_errors.tolist(),
        "array_shift_px": cal.array_shift.tolist(),
        "array_rotation_deg": cal.array_rotation_deg,
        "lens_residuals_px": cal.lens_residuals.tolist(),
        "field_shift_px": dict(zip((f"h^{p}" for p in FIELD_POWERS), cal.field_shift.tolist(),
                                   strict=True)),
        "centroid_rms_px": cal.residual_rms.tolist(),
        "throughput": cal.throughput.tolist(),
        "ranks": list(cal.ranks),
        "brightness": cal.brightness,
        "noise_sigma": cal.noise_sigma,
        "object_pixel_um": cal.system.object_pixel_um,
        "psf_fwhm_px": _json_list(fwhm),
        "psf_fwhm_um": None if pixel is None else _json_list(fwhm * pixel),
    })
    text = report_text(cal, nominal)
    files["report"] = out / "report.txt"
    files["report"].write_text(text, encoding="utf-8")
    return files


def _json_list(values: np.ndarray) -> list:
    """``values`` as nested lists, NaN as ``null`` (JSON has no NaN)."""
    return np.where(np.isfinite(values), np.round(values, 4), None).tolist()
