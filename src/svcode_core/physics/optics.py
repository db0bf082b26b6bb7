"""Field-dependent PSFs of the nine CM² microlenses from a Fourier-optics pupil model.

For an object point ``r`` imaged by lens ``ℓ`` the field vector is ``f = r - a_ℓ``
(``a_ℓ`` the lens axis, ``config.lens_axes``), the normalised field is
``h = |f| / optics.field_radius`` and ``φ̂ = f / |f|`` is the field direction. Over the unit
pupil ``p = (p_v, p_u)`` (``ρ = |p|``, ``ρ cos θ = p · φ̂``) the wavefront in waves is the
Seidel sum (design.md §1, :class:`~svcode_core.config.OpticsConfig`)

    W = W040 ρ⁴ + W131 h ρ³ cos θ + W222 h² ρ² cos² θ + W220 h² ρ².

The pupil is the unit disc intersected with a disc of the same radius shifted by
``pupil_clip · h`` along ``φ̂`` (asymmetric clipping); its edge is anti-aliased over one
pupil sample, so PSFs vary smoothly with the field. The amplitude on the sensor is the
Fourier transform of ``P e^{2πiW}``, evaluated by matrix DFTs straight onto the pixel
grid of the ``kernel_size`` window: the scale puts the first Airy zero at exactly
``airy_radius`` pixels, and a linear phase moves the image point by the distortion
``distortion · h³`` pixels along ``φ̂``, sub-pixel exact, without resampling.

Conventions
-----------
* A PSF is a ``(k, k)`` float64 array whose centre pixel ``(k // 2, k // 2)`` is the ideal
  (undistorted) image point ``c_ℓ + r``; pixel ``(i, j)`` is the sensor offset
  ``(i - k // 2, j - k // 2)`` in ``(row, col) = (v, u)`` order, the same orientation as
  the object (the kernel convention of :mod:`svcode_core.physics.lowrank`).
* A pixel holds the intensity at its centre. When ``airy_radius`` is too small for the
  intensity to be Nyquist-sampled by the pixels (below ``1.2197 px``), it holds the mean of
  ``q × q`` samples over the pixel instead, ``q`` the smallest integer that is, so that
  pixel sums still equal the integral.
* The full (untruncated) PSF sums to the transmission ``cos⁴ θ_field × clipped pupil area
  fraction`` (:func:`transmission`); light falling outside the window is lost, never
  renormalised away.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..config import N_LENSES, OpticsConfig, SystemConfig

__all__ = [
    "field_vectors",
    "lens_psf",
    "lens_psfs",
    "psf_grid_positions",
    "system_psfs",
    "transmission",
]

#: First zero of J1 (3.8317059702075125) divided by π: the Airy first zero lies at this
#: many λ/D (a literal: ``scipy.special.jn_zeros`` would cost every start 0.4 s of imports;
#: tests compare the two).
AIRY_ZERO = 1.2196698912665045

#: Upper bound of the working memory of one batch of PSFs, in complex128 elements.
_BATCH_ELEMENTS = 1 << 22


# ------------------------------------------------------------------ validation
def _check_lens(lens: int) -> int:
    if isinstance(lens, bool) or not isinstance(lens, (int, np.integer)):
        raise ValueError(f"lens must be an integer in 0..{N_LENSES - 1}, got {lens!r}")
    if not 0 <= lens < N_LENSES:
        raise ValueError(f"lens must be in 0..{N_LENSES - 1}, got {lens}")
    return int(lens)


def _as_positions(positions: np.ndarray | Sequence, name: str) -> np.ndarray:
    try:
        points = np.asarray(positions, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric (v, u) pairs, got {positions!r}") from None
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2) of (v, u) pairs, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} contains NaN or Inf values")
    return points


# -------------------------------------------------------------------- geometry
def psf_grid_positions(config: SystemConfig) -> np.ndarray:
    """Object positions of the PSF grid.

    Parameters
    ----------
    config : SystemConfig

    Returns
    -------
    numpy.ndarray
        Shape ``(G·G, 2)``: ``(v, u)`` of the regular ``G × G`` grid over ``[-1, 1]²``
        (``G = optics.psf_grid``, ``t = linspace(-1, 1, G)``), row-major with ``v`` outer.

    Examples
    --------
    >>> psf_grid_positions(SystemConfig.preset("cm2-mini"))[:2].tolist()
    [[-1.0, -1.0], [-1.0, -0.6666666666666667]]
    """
    t = np.linspace(-1.0, 1.0, config.optics.psf_grid)
    v, u = np.meshgrid(t, t, indexing="ij")
    return np.stack([v.ravel(), u.ravel()], axis=1)


def field_vectors(config: SystemConfig, lens: int, points: np.ndarray) -> np.ndarray:
    """Normalised field vectors ``h φ̂ = (r - a_ℓ) / field_radius`` ``(N, 2)`` of lens ``lens``
    at object points ``(v, u)`` ``(N, 2)``.

    Examples
    --------
    >>> config = SystemConfig.preset("cm2-mini")
    >>> axis = np.asarray([config.lens_axes[4]])
    >>> field_vectors(config, 4, axis)
    array([[0., 0.]])
    """
    offset = np.asarray(points, dtype=np.float64) - np.asarray(config.lens_axes[lens], np.float64)
    return offset / config.optics.field_radius


def _field(config: SystemConfig, lens: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised field ``h`` (N,) and unit field direction ``φ̂`` (N, 2); ``φ̂ = 0`` on axis."""
    vectors = field_vectors(config, lens, points)
    h = np.hypot(vectors[:, 0], vectors[:, 1])
    direction = np.divide(vectors, h[:, None], out=np.zeros_like(vectors), where=h[:, None] > 0)
    return h, direction


def _transmission(optics: OpticsConfig, h: np.ndarray) -> np.ndarray:
    """``cos⁴ θ_field`` times the area fraction of the clipped pupil (two unit discs)."""
    tan_field = h * math.tan(math.radians(optics.vignetting_angle))
    cos4 = 1.0 / (1.0 + tan_field**2) ** 2
    half_shift = np.minimum(0.5 * optics.pupil_clip * h, 1.0)
    lens_area = 2.0 * np.arccos(half_shift) - 2.0 * half_shift * np.sqrt(1.0 - half_shift**2)
    return cos4 * lens_area / np.pi


def transmission(config: SystemConfig, lens: int, positions: np.ndarray | Sequence) -> np.ndarray:
    """Fraction of the light from each object point that lens ``lens`` brings to the sensor.

    Parameters
    ----------
    config : SystemConfig
    lens : int
        Lens index ``0..8``.
    positions : array_like
        ``(N, 2)`` object points ``(v, u)`` in normalised coordinates.

    Returns
    -------
    numpy.ndarray
        ``(N,)``: ``cos⁴ θ_field`` (``tan θ_field = h · tan(vignetting_angle)``) times the
        area fraction of the unit pupil left by the clipping disc shifted by
        ``pupil_clip · h`` pupil radii. 1 on the lens axis, 0 once the discs no longer meet.
    """
    config.validate()
    lens = _check_lens(lens)
    points = _as_positions(positions, "positions")
    h, _ = _field(config, lens, points)
    return _transmission(config.optics, h)


# ----------------------------------------------------------------- PSF model
class _Sampling:
    """Pupil and pixel sampling of one optics configuration.

    Attributes
    ----------
    pupil : (M,) pupil-sample centres across the unit pupil's diameter, spacing ``dp``.
    scale : cycles per pupil unit per pixel: the DFT kernel is ``exp(-2πi·scale·x·p)``.
    period : the sampled-pupil field repeats every ``period = 1 / (scale·dp)`` pixels.
    oversample : sub-samples ``q`` per pixel and axis.
    offsets : (k·q,) sub-sample offsets from the window centre, in pixels.
    """

    def __init__(self, optics: OpticsConfig) -> None:
        m = optics.pupil_samples
        self.dp = 2.0 / m
        self.pupil = -1.0 + (np.arange(m) + 0.5) * self.dp
        # A unit-radius pupil has its first dark ring at AIRY_ZERO / 2 in these units.
        self.scale = AIRY_ZERO / (2.0 * optics.airy_radius)
        self.period = 1.0 / (self.scale * self.dp)
        # The intensity spectrum reaches 2 pupil units: Nyquist needs scale / q < 1 / 2.
        self.oversample = math.floor(2.0 * self.scale) + 1
        q = self.oversample
        k = optics.kernel_size
        self.offsets = (np.arange(k * q) - (k * q - 1) / 2.0) / q


def _pupil(
    optics: OpticsConfig,
    sampling: _Sampling,
    h: np.ndarray,
    direction: np.ndarray,
    w020: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Complex pupil functions ``(N, M, M)`` and the wavefront gradient reach in pixels.

    ``w020`` is a field-independent defocus term in waves (the object off the focal plane).
    """
    pv = sampling.pupil[None, :, None]
    pu = sampling.pupil[None, None, :]
    dv = direction[:, 0, None, None]
    du = direction[:, 1, None, None]
    hh = h[:, None, None]
    rho2 = pv**2 + pu**2
    along = pv * dv + pu * du  # ρ cos θ
    # Anti-aliased aperture: linear ramp of the signed distance over one pupil sample.
    shift = optics.pupil_clip * hh
    outside = np.maximum(np.sqrt(rho2) - 1.0, np.hypot(pv - shift * dv, pu - shift * du) - 1.0)
    amplitude = np.clip(0.5 - outside / sampling.dp, 0.0, 1.0)

    spherical = optics.spherical
    coma = optics.coma * hh
    astigmatism = optics.astigmatism * hh**2
    defocus = optics.field_curvature * hh**2 + w020
    wavefront = spherical * rho2**2 + coma * rho2 * along + astigmatism * along**2 + defocus * rho2
    # ∇W: where each ray lands, used to refuse fields whose light would wrap into the window.
    radial = 4.0 * spherical * rho2 + 2.0 * coma * along + 2.0 * defocus
    axial = coma * rho2 + 2.0 * astigmatism * along
    distortion = optics.distortion * hh**3
    reach_v = np.abs(distortion * dv + (radial * pv + axial * dv) / sampling.scale)
    reach_u = np.abs(distortion * du + (radial * pu + axial * du) / sampling.scale)
    lit = amplitude > 0
    reach = np.max(np.where(lit, np.maximum(reach_v, reach_u), 0.0), axis=(1, 2))
    return amplitude * np.exp(2j * np.pi * wavefront), reach


def _psf_batch(
    optics: OpticsConfig,
    sampling: _Sampling,
    h: np.ndarray,
    direction: np.ndarray,
    w020: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """PSFs ``(N, k, k)`` of field points given by ``h`` and ``direction``.

    ``w020`` adds defocus in waves; ``offset`` moves every image point by ``(row, col)``
    pixels (sub-pixel exact, through the same linear phase as the distortion).
    """
    pupil, reach = _pupil(optics, sampling, h, direction, w020)
    reach = reach + max(abs(offset[0]), abs(offset[1]))
    k = optics.kernel_size
    worst = int(np.argmax(reach))
    if reach[worst] + k // 2 >= sampling.period:
        raise ValueError(
            f"optics.pupil_samples={optics.pupil_samples} is too small for the aberrations at "
            f"field h={h[worst]:.3g}: rays land {reach[worst]:.1f} px from the image point, and "
            f"the sampled pupil repeats the PSF every {sampling.period:.1f} px, which wraps "
            f"light into the {k}-px window; raise pupil_samples or lower the aberrations"
        )
    shift = optics.distortion * h[:, None] ** 3 * direction + np.asarray(offset)  # (N, 2) px
    phase = -2j * np.pi * sampling.scale * sampling.pupil[None, None, :]
    rows = np.exp(phase * (sampling.offsets[None, :, None] - shift[:, 0, None, None]))
    cols = np.exp(phase * (sampling.offsets[None, :, None] - shift[:, 1, None, None]))
    field = rows @ pupil @ cols.transpose(0, 2, 1)  # (N, kq, kq)
    intensity = field.real**2 + field.imag**2
    q = sampling.oversample
    intensity = intensity.reshape(-1, k, q, k, q).sum(axis=(2, 4))
    # Discrete Parseval: one period of the field holds (period·q)² samples and the
    # energy Σ|pupil|²; dividing by both makes the full PSF sum to 1 before transmission.
    energy = np.sum(np.abs(pupil) ** 2, axis=(1, 2)) * (sampling.period * q) ** 2
    gain = np.divide(_transmission(optics, h), energy, out=np.zeros_like(energy), where=energy > 0)
    return intensity * gain[:, None, None]


def _psfs(
    config: SystemConfig,
    lens: int,
    points: np.ndarray,
    w020: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    optics = config.optics
    sampling = _Sampling(optics)
    h, direction = _field(config, lens, points)
    side = optics.kernel_size * sampling.oversample
    m = optics.pupil_samples
    per_psf = m * m + 2 * side * m + side * side
    batch = max(1, _BATCH_ELEMENTS // per_psf)
    out = np.empty((len(points), optics.kernel_size, optics.kernel_size))
    for start in range(0, len(points), batch):
        part = slice(start, start + batch)
        out[part] = _psf_batch(optics, sampling, h[part], direction[part], w020, offset)
    return out


def lens_psfs(
    config: SystemConfig,
    lens: int,
    positions: np.ndarray | Sequence | None = None,
    *,
    defocus: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """PSFs of one lens at many object points.

    Parameters
    ----------
    config : SystemConfig
    lens : int
        Lens index ``0..8``.
    positions : array_like, optional
        ``(N, 2)`` object points ``(v, u)``; default the PSF grid
        (:func:`psf_grid_positions`).
    defocus : float
        Field-independent defocus ``W020`` in waves at the pupil edge (the object off the
        focal plane); 0 for the in-focus system.
    offset : (float, float)
        Displacement ``(row, col)`` in pixels of every image point of this lens (a lens
        off its calibrated position), applied sub-pixel exactly by the pupil's linear phase.

    Returns
    -------
    numpy.ndarray
        ``(N, k, k)`` float64 PSFs, each centred on its ideal image point.

    Raises
    ------
    ValueError
        For a lens outside ``0..8``, non-finite positions, or aberrations too strong for
        ``optics.pupil_samples`` (the message names the field).
    """
    config.validate()
    lens = _check_lens(lens)
    if positions is None:
        points = psf_grid_positions(config)
    else:
        points = _as_positions(positions, "positions")
    for name, value in (("defocus", defocus), *zip(("offset", "offset"), offset, strict=True)):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value!r}")
    return _psfs(config, lens, points, float(defocus), (float(offset[0]), float(offset[1])))


def lens_psf(config: SystemConfig, lens: int, position: np.ndarray | Sequence) -> np.ndarray:
    """PSF of lens ``lens`` for the object point ``position = (v, u)``.

    Returns
    -------
    numpy.ndarray
        ``(k, k)`` float64, centre pixel at the ideal image point ``c_ℓ + r``; it sums to
        :func:`transmission` less the light falling outside the window.

    Examples
    --------
    >>> system = SystemConfig.preset("cm2-mini")
    >>> psf = lens_psf(system, 4, (0.0, 0.0))
    >>> psf.shape, bool(abs(psf.sum() - 1) < 0.02)
    ((33, 33), True)
    """
    try:
        shape = np.shape(position)
    except ValueError:
        shape = None
    if shape != (2,):
        raise ValueError(f"position must be one (v, u) pair, got {position!r}")
    return lens_psfs(config, lens, _as_positions([position], "position"))[0]


def system_psfs(
    config: SystemConfig,
    *,
    defocus: float = 0.0,
    offsets: np.ndarray | Sequence | None = None,
) -> np.ndarray:
    """PSFs of all nine lenses on the PSF grid.

    Parameters
    ----------
    config : SystemConfig
    defocus : float
        Defocus ``W020`` in waves for every lens (see :func:`lens_psfs`).
    offsets : array_like, optional
        ``(9, 2)`` displacement ``(row, col)`` in pixels of each lens's image points.

    Returns
    -------
    numpy.ndarray
        ``(9, G·G, k, k)`` float64, lens-major, grid order of :func:`psf_grid_positions`.
    """
    moves = np.zeros((N_LENSES, 2)) if offsets is None else np.asarray(offsets, dtype=float)
    if moves.shape != (N_LENSES, 2):
        raise ValueError(f"offsets must have shape ({N_LENSES}, 2), got {moves.shape}")
    return np.stack([
        lens_psfs(config, lens, defocus=defocus, offset=tuple(moves[lens]))
        for lens in range(N_LENSES)
    ])
