"""Calibrate a CM² instrument from a point-source scan.

A lab records a **point-source scan**: a bead or pinhole at ``N`` object positions
``p_n`` (whole pixels of the ``S × S`` object grid), one raw frame each. Lens ``ℓ`` images
the source to the padded-sensor point ``c_ℓ - S//2 + p_n`` blurred by its PSF at ``p_n``
(:mod:`svcode_core.config`). :func:`calibrate` turns the scan into a system:

1. **Spots**: per frame, the local maxima of the frame smoothed over an Airy core
   (:func:`skimage.feature.peak_local_max`) above a threshold derived from the noise
   (median absolute deviation of the frames) are assigned to the lens whose nominal
   image point lies within half a lens pitch.
2. **Chief rays**: each spot fully on the sensor gives the lens's offset from its nominal
   chief ray as its centroid minus the centroid of the nominal model's PSF at ``p_n``
   (which carries the distortion and coma shift); the offset of a lens is the least-squares
   (mean) value over its spots, then split, again by least squares, into an array
   translation, an array rotation about the lattice centre and per-lens residuals. The
   nominal PSF at ``p_n`` is the one the operator uses: the grid PSFs interpolated.
3. **PSFs**: the ``k × k`` window at ``round(c_ℓ) - S//2 + p_n`` of every frame is the
   registered PSF of lens ``ℓ`` at ``p_n`` (the sub-pixel part of the chief ray stays in
   it, as in :mod:`svcode_core.physics.instrument`). The PSFs on the ``G × G`` grid are fitted to
   them by least squares through the same cubic interpolation the low-rank operator uses
   (:func:`svcode_core.physics.lowrank.interpolation_basis`), pixel by pixel over the pixels that
   are on the sensor, with a weak prior towards the nominal model for grid nodes the scan
   does not reach.
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
from .lowrank import decompose_psfs, interpolation_basis
from .optics import system_psfs

__all__ = [
    "Calibration",
    "CalibrationError",
    "Progress",
    "calibrate",
    "fit_array",
    "read_positions",
    "report_text",
    "save_calibration",
]

#: Weight of the nominal-model prior on a grid PSF, as a fraction of the mean data weight
#: of a grid node: enough to fix nodes the scan does not reach, a 1 % pull elsewhere.
PRIOR_WEIGHT = 1e-2

#: ``progress(stage, fraction)``: what :func:`calibrate` is doing and the fraction done.
Progress = Callable[[str, float], None]


class CalibrationError(ValueError):
    """The scan, its positions or the system cannot give a calibration."""


# ------------------------------------------------------------------- inputs
def read_positions(path: str | Path) -> np.ndarray:
    """Read the source positions of a scan from a CSV file.

    Parameters
    ----------
    path : str or Path
        A header line ``row,col``, then one ``row,col`` line per frame: the source
        position in whole pixels of the ``S × S`` object grid.

    Returns
    -------
    numpy.ndarray
        ``(N, 2)`` int64 positions.

    Raises
    ------
    CalibrationError
        On a missing header, a line that is not two whole numbers (naming the line).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"positions file not found: {path}")
    lines = list(csv.reader(path.read_text(encoding="utf-8").splitlines()))
    header = [cell.strip().lower() for cell in lines[0]] if lines else []
    if header != ["row", "col"]:
        raise CalibrationError(f"{path.name} line 1: expected the header 'row,col', got "
                               f"{','.join(header)!r}")  # fmt: skip
    rows = []
    for number, cells in enumerate(lines[1:], start=2):
        if not any(cell.strip() for cell in cells):
            continue
        try:
            values = [float(cell) for cell in cells]
        except ValueError:
            values = []
        if len(values) != 2 or not all(math.isfinite(v) and v == round(v) for v in values):
            raise CalibrationError(f"{path.name} line {number} (frame {len(rows)}): expected "
                                   f"two whole pixel numbers row,col, got {','.join(cells)!r}")
        rows.append(values)
    return np.asarray(rows, dtype=np.int64).reshape(-1, 2)


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
    outside = np.flatnonzero(((positions < 0) | (positions >= size)).any(axis=1))
    if outside.size:
        n = int(outside[0])
        raise CalibrationError(f"frame {n}: position ({positions[n, 0]}, {positions[n, 1]}) "
                               f"lies outside the {size}×{size} object grid")
    bad = np.flatnonzero(~np.isfinite(frames).all(axis=(1, 2)))
    if bad.size:
        raise CalibrationError(f"frame {int(bad[0])}: contains NaN or Inf values")
    saturated = np.flatnonzero((frames >= saturation).any(axis=(1, 2)))
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
    centroids : numpy.ndarray
        ``(N, 9, 2)`` measured spot centroids in sensor pixels, NaN where not measured.
    predicted : numpy.ndarray
        ``(N, 9, 2)`` centroids predicted by the fitted chief rays and nominal optics.
    throughput : numpy.ndarray
        ``(9, G·G)`` sum of every grid PSF (vignetting), nominal on-axis total = 1.
    ranks : tuple of int
        Low-rank order ``K`` of every lens at ``system.rank_tolerance``.
    brightness : float
        Source brightness the frames were divided by.
    noise_sigma : float
        Estimated noise standard deviation of one frame's background.
    """

    system: SystemConfig
    psfs: np.ndarray
    chief_rays: np.ndarray
    offsets: np.ndarray
    offset_errors: np.ndarray
    array_shift: np.ndarray
    array_rotation_deg: float
    lens_residuals: np.ndarray
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


def _windows(frames: np.ndarray, corners: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``k × k`` crops at integer top-left ``corners`` ``(N, 9, 2)``; zero and masked off-sensor.

    Returns windows ``(N, 9, k, k)`` and the on-sensor mask of the same shape.
    """
    n, height, width = frames.shape
    rows = corners[..., 0, None] + np.arange(k)  # (N, 9, k)
    cols = corners[..., 1, None] + np.arange(k)
    inside = ((rows >= 0) & (rows < height))[..., :, None] & ((cols >= 0) & (cols < width))[
        ..., None, :]
    r = np.clip(rows, 0, height - 1)[..., :, None]
    c = np.clip(cols, 0, width - 1)[..., None, :]
    frame = np.arange(n)[:, None, None, None]
    return np.where(inside, frames[frame, r, c], 0.0), inside


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
                sigma: float, progress: Progress) -> np.ndarray:  # fmt: skip
    """``(N, 9, 2)`` integer peak of each lens's spot, ``-1`` where none is detected.

    ``progress`` hears of every frame, as the fractions 0.05 to 0.5 of the calibration.
    """
    radius = _lens_pitch(system) / 2.0
    smooth_sigma = max(system.optics.airy_radius / 2.0, 0.5)
    # Noise of the smoothed frame: white noise through a unit-sum Gaussian.
    smooth_noise = sigma / (2.0 * math.sqrt(math.pi) * smooth_sigma)
    # One false peak in the whole scan is expected at this many standard deviations.
    threshold = float(norm.isf(1.0 / frames.size)) * smooth_noise
    peaks = np.full(expected.shape, -1, dtype=np.int64)
    for n, frame in enumerate(frames):
        progress(f"finding spots: frame {n + 1} of {len(frames)}",
                 0.05 + 0.45 * n / len(frames))  # fmt: skip
        smooth = ndimage.gaussian_filter(frame, smooth_sigma)
        found = peak_local_max(smooth, min_distance=max(1, int(radius // 2)),
                               threshold_abs=threshold, exclude_border=False)  # fmt: skip
        if found.size == 0:
            raise CalibrationError(
                f"frame {n}: no spot above the detection threshold {threshold:.3g} "
                f"(noise {sigma:.3g}); is the source in the field and the exposure long enough?")
        distance = np.linalg.norm(found[None, :, :] - expected[n][:, None, :], axis=-1)
        for lens in range(N_LENSES):
            near = np.flatnonzero(distance[lens] < radius)
            if near.size:
                best = near[np.argmax(smooth[found[near, 0], found[near, 1]])]
                peaks[n, lens] = found[best]
        if (peaks[n] < 0).all():
            raise CalibrationError(f"frame {n}: spots found, but none within {radius:.0f} px of "
                                   "a lens's nominal image point: wrong positions or system?")
    return peaks


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
    """``(N, G·G)`` weights of the grid PSFs at each position (the operator's interpolation)."""
    basis = interpolation_basis(system.optics.psf_grid, system.sub_view_size)
    rows = basis[:, positions[:, 0]]  # (G, N)
    cols = basis[:, positions[:, 1]]
    return np.einsum("an,bn->nab", rows, cols).reshape(len(positions), -1)


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
        ``(N, 2)`` source positions ``(row, col)`` in whole pixels of the object grid.
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
    frames = frames.astype(np.float64)
    positions = np.asarray(positions, dtype=np.int64).reshape(-1, 2)
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
        frames = frames - dark
    else:
        frames = frames - np.median(frames, axis=(1, 2), keepdims=True)
    # Robust noise of the background: spots cover a small fraction of every frame.
    sigma = float(np.median(median_abs_deviation(frames, axis=(1, 2), scale="normal")))
    sigma = max(sigma, 1e-12)
    k = system.optics.kernel_size
    half = k // 2
    nominal_rays = np.asarray(system.chief_rays, float)
    expected = _image_points(system, nominal_rays, positions)
    peaks = _find_spots(frames, np.rint(expected).astype(np.int64), system, sigma, report)
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
    windows, inside = _windows(frames, centres - half, k)
    complete = found & inside.all(axis=(-2, -1))
    # The nominal model's image of each point: its grid PSFs interpolated as the operator does.
    design = _grid_design(positions, system)
    nominal = np.einsum("ng,lgij->nlij", design, system_psfs(system))
    shift = _centroid(windows) - _centroid(nominal)  # (N, 9, 2) sub-pixel moves
    offsets = np.zeros((N_LENSES, 2))
    errors = np.zeros((N_LENSES, 2))
    for lens in range(N_LENSES):
        use = complete[:, lens]
        if use.sum() < 2:
            raise CalibrationError(f"lens {lens}: {int(use.sum())} spot(s) wholly on the sensor, "
                                   "at least 2 are needed to fit its chief ray")  # fmt: skip
        values = shift[use, lens]
        offsets[lens] = whole[lens] + values.mean(axis=0)
        errors[lens] = values.std(axis=0, ddof=1) / math.sqrt(len(values))
    array_shift, rotation, residuals = fit_array(offsets, system)
    fitted = nominal_rays + offsets
    rays = np.rint(fitted).astype(np.int64)
    predicted = _image_points(system, fitted, positions) + _centroid(nominal)
    centroids = np.where(complete[..., None], centres + _centroid(windows), np.nan)
    system = system.replace(chief_rays=tuple((int(r), int(c)) for r, c in rays))

    # -- PSFs: windows at the calibrated integer image points, fitted to the grid
    windows, inside = _windows(frames, np.rint(_image_points(system, rays, positions)).astype(
        np.int64) - half, k)
    prior_psfs = system_psfs(system, offsets=fitted - rays)
    overlap = complete & inside.all(axis=(-2, -1))
    measured = windows[overlap].sum()
    predicted_sum = np.einsum("ng,lgij->nl", design, prior_psfs)[overlap].sum()
    brightness = float(measured / predicted_sum)
    if design.shape[0] < design.shape[1] or np.linalg.matrix_rank(design) < design.shape[1]:
        g = system.optics.psf_grid
        raise CalibrationError(
            f"the {len(positions)} positions do not determine the {g}×{g} PSF grid "
            f"(optics.psf_grid): scan at least {g} distinct rows and {g} distinct columns "
            "spread over the object grid")
    samples = windows / brightness
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
    return Calibration(
        system=system, psfs=psfs, chief_rays=fitted, offsets=offsets, offset_errors=errors,
        array_shift=array_shift, array_rotation_deg=rotation, lens_residuals=residuals,
        centroids=centroids, predicted=np.where(complete[..., None], predicted, np.nan),
        throughput=throughput, ranks=ranks, brightness=brightness, noise_sigma=sigma,
    )  # fmt: skip


def _silent(stage: str, fraction: float) -> None:
    """The :data:`Progress` of a caller that did not ask for one."""


# ------------------------------------------------------------------ output
def report_text(calibration: Calibration, nominal: SystemConfig) -> str:
    """A plain-text report of a calibration: chief rays, array motion, residuals, PSFs."""
    cal = calibration
    lines = [
        f"calibration of {nominal.name!r}: {len(cal.centroids)} frames, noise sigma "
        f"{cal.noise_sigma:.3g}, source brightness {cal.brightness:.4g}",
        f"lens array: shift ({cal.array_shift[0]:+.3f}, {cal.array_shift[1]:+.3f}) px, "
        f"rotation {cal.array_rotation_deg:+.4f} deg",
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
    return "\n".join(lines) + "\n"


def save_calibration(calibration: Calibration, out_dir: str | Path, nominal: SystemConfig,
                     frames: np.ndarray | None = None) -> dict[str, Path]:  # fmt: skip
    """Write the calibrated system and everything it refers to into ``out_dir``.

    Files: ``system.json`` (``psf_model`` = ``psfs.tif``, relative), ``psfs.tif`` and
    ``psfs.positions.json`` (:func:`svcode_core.physics.psf_io.save_psfs`), ``calibration.json``
    (fitted chief rays, offsets, array motion, throughput, ranks), ``report.txt`` and
    ``report.png`` (:func:`svcode_core.evaluation.figures.calibration_figure`; needs ``frames``).

    Returns
    -------
    dict of str to Path
        The files written, by kind.
    """
    from ..evaluation.figures import calibration_figure
    from ..io import write_json_atomic
    from .psf_io import save_psfs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cal = calibration
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
        "centroid_rms_px": cal.residual_rms.tolist(),
        "throughput": cal.throughput.tolist(),
        "ranks": list(cal.ranks),
        "brightness": cal.brightness,
        "noise_sigma": cal.noise_sigma,
    })
    text = report_text(cal, nominal)
    files["report"] = out / "report.txt"
    files["report"].write_text(text, encoding="utf-8")
    if frames is not None:
        files["figure"] = calibration_figure(out / "report.png", cal, np.asarray(frames))
    return files
