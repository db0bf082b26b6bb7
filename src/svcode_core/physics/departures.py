"""How the real instrument departs from the nominal system the reconstructors are given.

A :class:`Departures` lists, as physical quantities, every way the true CM² differs from
its :class:`~svcode_core.config.SystemConfig`: where the microlens array sits, how wrong
the fitted aberrations are, how far the sample is from the focal plane, how finely the
true PSFs vary, how much out-of-focus haze reaches the sensor and what the camera adds
(shot noise at a photon level, read noise, hot pixels, fixed-pattern noise, ADC). All zero
(``Departures()``, the ``none`` set) is the nominal system: simulating with it is the
*inverse crime* of reconstructing with the very model that made the data.

Units are in the field names: ``_px`` sensor pixels of the system, ``_deg`` degrees,
``_waves`` wavefront waves at the pupil edge, ``_e`` photo-electrons, ``_percent`` percent.

Named sets (:data:`NAMED_SETS`, :meth:`Departures.named`) hold magnitudes typical after a
careful calibration; ``docs/regimes.md`` says where each one comes from. Pixel quantities
are given for an Airy radius of :data:`REFERENCE_AIRY_RADIUS_PX` pixels (``cm2-mini``) and
scaled with the system's ``optics.airy_radius``, so a set means the same fraction of a
resolution element on every system.

:meth:`Departures.sample` treats a set as ranges and draws one instrument from them
(domain randomisation of training data).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (
    N_LENSES,
    ConfigError,
    JsonFile,
    SystemConfig,
    _build,
    check_int,
    check_number,
    parse_json,
    read_text,
)

__all__ = [
    "NAMED_SETS",
    "OPTICAL_FIELDS",
    "REFERENCE_AIRY_RADIUS_PX",
    "Departures",
    "load_departures",
]

#: Airy radius (pixels) at which the named sets' pixel magnitudes are stated (cm2-mini).
REFERENCE_AIRY_RADIUS_PX = 2.0

#: Fields that change the PSFs or the lens positions: a new forward operator each.
OPTICAL_FIELDS = (
    "mla_shift_px", "mla_rotation_deg", "lens_jitter_px",
    "spherical_error_waves", "coma_error_waves", "astigmatism_error_waves",
    "field_curvature_error_waves", "distortion_error_px",
    "defocus_waves", "depth_spread_waves", "truth_psf_grid", "truth_rank_tolerance",
)  # fmt: skip

#: Signed fields: :meth:`Departures.sample` draws them uniformly in ``[-|m|, |m|]``.
_SIGNED = (
    "mla_rotation_deg", "spherical_error_waves", "coma_error_waves",
    "astigmatism_error_waves", "field_curvature_error_waves", "distortion_error_px",
    "defocus_waves",
)  # fmt: skip
#: Non-negative magnitudes: drawn uniformly in ``[0, m]``.
_MAGNITUDES = (
    "lens_jitter_px", "depth_spread_waves", "background_fraction", "hot_pixel_fraction",
    "prnu_percent", "dsnu_e",
)  # fmt: skip
_SENSOR_FIELDS = (
    "photons", "read_noise_e", "hot_pixel_fraction", "hot_pixel_e", "prnu_percent", "dsnu_e",
    "adc_bits", "full_well_e",
)  # fmt: skip
_PIXEL_FIELDS = ("lens_jitter_px", "distortion_error_px", "background_width_px")
#: Defocus planes per wave of depth spread (midpoint rule over the slab).
_PLANES_PER_WAVE = 10


def _differs(departures: Departures, fields: tuple[str, ...]) -> bool:
    nominal = Departures()
    return any(getattr(departures, f) != getattr(nominal, f) for f in fields)


def _fail(name: str, message: str) -> None:
    raise ConfigError(f"departures.{name}: {message}")


@dataclass(frozen=True)
class Departures(JsonFile):
    """The true instrument, as departures from the nominal system (all zero: none).

    Attributes
    ----------
    name : str
        Label recorded with every simulation (a named set's name, or ``"custom"``).
    seed : int
        Seeds what is fixed per instrument but random in layout: the per-lens jitter
        directions and the fixed-pattern maps (hot-pixel sites, gain and offset maps).
    mla_shift_px : (float, float)
        Translation ``(row, col)`` of the whole microlens array's images on the sensor,
        in pixels, relative to the calibrated chief rays.
    mla_rotation_deg : float
        Rotation of the lens lattice about its centre, in degrees; each lens's image moves
        with its rotated centre (a lens is rotationally symmetric, its image does not turn).
    lens_jitter_px : float
        Per-lens chief-ray error in pixels: each lens and axis is displaced by a value
        drawn uniformly in ``[-lens_jitter_px, lens_jitter_px]`` from ``seed``.
    spherical_error_waves, coma_error_waves, astigmatism_error_waves,
    field_curvature_error_waves : float
        Errors of the fitted Seidel coefficients W040, W131, W222, W220, in waves, added
        to the nominal ``optics`` values.
    distortion_error_px : float
        Error of the distortion at the reference field, in pixels.
    defocus_waves : float
        The sample's distance from the focal plane as defocus ``W020`` in waves at the
        pupil edge (``Δz = 2 λ W020 / NA²``).
    depth_spread_waves : float
        Thickness of the sample as a spread of defocus, in waves: the true PSF is the
        mean over a uniform slab ``defocus_waves ± depth_spread_waves / 2``.
    truth_psf_grid : int or None
        PSF grid of the true instrument (finer than ``optics.psf_grid``: the PSF varies
        more smoothly in the model than in the instrument); ``None`` keeps the nominal grid.
    truth_rank_tolerance : float or None
        Low-rank tolerance of the true operator (below the nominal ``rank_tolerance``:
        a more exact spatially varying model); ``None`` keeps the nominal one.
    background_fraction : float
        Out-of-focus haze: light from outside the focal plane, as a fraction of the
        in-focus light on the sensor, spread by a Gaussian of ``background_width_px``.
    background_width_px : float
        Standard deviation in pixels of the haze's spread on the sensor.
    photons : float or None
        Expected photo-electrons at intensity 1 (the object's peak); exact Poisson
        sampling. ``None`` keeps the nominal noise model.
    read_noise_e : float or None
        Read noise, RMS photo-electrons per pixel; ``None`` keeps the nominal read noise.
    hot_pixel_fraction : float
        Fraction of pixels with extra dark signal (hot pixels), sites from ``seed``.
    hot_pixel_e : float
        Mean extra dark signal of a hot pixel in photo-electrons (exponentially
        distributed over hot pixels, shot noise included).
    prnu_percent : float
        Photo-response non-uniformity: RMS pixel-to-pixel gain variation in percent.
    dsnu_e : float
        Dark-signal non-uniformity: RMS pixel-to-pixel offset in photo-electrons.
    adc_bits : int or None
        ADC bit depth: the reading is rounded to ``2**adc_bits - 1`` steps of the
        saturation level; ``None``: not quantised.
    full_well_e : float or None
        Saturation (full well or ADC full scale) in photo-electrons; ``None`` keeps the
        nominal ``noise.saturation``.
    """

    name: str = "custom"
    seed: int = 0
    mla_shift_px: tuple[float, float] = (0.0, 0.0)
    mla_rotation_deg: float = 0.0
    lens_jitter_px: float = 0.0
    spherical_error_waves: float = 0.0
    coma_error_waves: float = 0.0
    astigmatism_error_waves: float = 0.0
    field_curvature_error_waves: float = 0.0
    distortion_error_px: float = 0.0
    defocus_waves: float = 0.0
    depth_spread_waves: float = 0.0
    truth_psf_grid: int | None = None
    truth_rank_tolerance: float | None = None
    background_fraction: float = 0.0
    background_width_px: float = 24.0
    photons: float | None = None
    read_noise_e: float | None = None
    hot_pixel_fraction: float = 0.0
    hot_pixel_e: float = 0.0
    prnu_percent: float = 0.0
    dsnu_e: float = 0.0
    adc_bits: int | None = None
    full_well_e: float | None = None

    # ------------------------------------------------------------- validation
    def validate(self) -> Departures:
        """Check every field; raise :class:`ConfigError` naming the first bad one.

        Returns
        -------
        Departures
            ``self``, so that calls chain.
        """
        if not isinstance(self.name, str) or not self.name:
            _fail("name", f"must be a non-empty string, got {self.name!r}")
        check_int("departures.seed", self.seed, 0)
        shift = self.mla_shift_px
        if not isinstance(shift, (tuple, list)) or len(shift) != 2:
            _fail("mla_shift_px", f"must be a (row, col) pair, got {shift!r}")
        for value in shift:
            check_number("departures.mla_shift_px", value)
        rotation = check_number("departures.mla_rotation_deg", self.mla_rotation_deg)
        if abs(rotation) >= 45:
            _fail("mla_rotation_deg", f"must lie in (-45, 45) degrees, got {rotation!r}")
        for name in _SIGNED:
            check_number(f"departures.{name}", getattr(self, name))
        for name in ("lens_jitter_px", "depth_spread_waves", "background_fraction",
                     "hot_pixel_e", "prnu_percent", "dsnu_e"):  # fmt: skip
            check_number(f"departures.{name}", getattr(self, name), 0.0)
        check_number("departures.background_width_px", self.background_width_px, 0.0, strict=True)
        fraction = check_number("departures.hot_pixel_fraction", self.hot_pixel_fraction)
        if not 0 <= fraction <= 1:
            _fail("hot_pixel_fraction", f"must lie in [0, 1], got {fraction!r}")
        if self.prnu_percent >= 100:
            _fail("prnu_percent", f"must be < 100, got {self.prnu_percent!r}")
        if self.truth_psf_grid is not None:
            check_int("departures.truth_psf_grid", self.truth_psf_grid, 2)
        if self.truth_rank_tolerance is not None:
            check_number("departures.truth_rank_tolerance", self.truth_rank_tolerance, 0.0,
                         strict=True)
            if self.truth_rank_tolerance >= 1:
                _fail("truth_rank_tolerance", f"must be < 1, got {self.truth_rank_tolerance}")
        for name in ("photons", "full_well_e"):
            if getattr(self, name) is not None:
                check_number(f"departures.{name}", getattr(self, name), 0.0, strict=True)
        if self.read_noise_e is not None:
            check_number("departures.read_noise_e", self.read_noise_e, 0.0)
        if self.adc_bits is not None:
            check_int("departures.adc_bits", self.adc_bits, 1, 24)
        return self

    # --------------------------------------------------------------- queries
    @property
    def is_nominal(self) -> bool:
        """True when the instrument is exactly the nominal system."""
        return not (self.has_optics or self.background_fraction > 0 or self.has_sensor)

    @property
    def has_optics(self) -> bool:
        """True when the lens positions or PSFs differ from the nominal system."""
        return _differs(self, OPTICAL_FIELDS)

    @property
    def has_sensor(self) -> bool:
        """True when the camera differs from the nominal noise model."""
        return _differs(self, _SENSOR_FIELDS)

    def optical_key(self) -> str:
        """JSON of the fields that define the forward operator (a cache key)."""
        data = {name: getattr(self, name) for name in OPTICAL_FIELDS}
        data["seed"] = self.seed if self.lens_jitter_px else 0
        return json.dumps(data, sort_keys=True)

    def lens_offsets(self, system: SystemConfig) -> np.ndarray:
        """Displacement of each lens's image from its nominal chief ray, in pixels.

        Parameters
        ----------
        system : SystemConfig
            The nominal system (its chief rays define the lattice centre).

        Returns
        -------
        numpy.ndarray
            ``(9, 2)`` float64 ``(row, col)`` displacements: array shift, plus the rotation
            of each chief ray about the lattice centre, plus the per-lens jitter.
        """
        return sum(self._offset_parts(system).values())

    def _offset_parts(self, system: SystemConfig) -> dict[str, np.ndarray]:
        rays = np.asarray(system.chief_rays, dtype=np.float64)
        centre = rays.mean(axis=0)
        angle = math.radians(self.mla_rotation_deg)
        turn = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        relative = rays - centre
        jitter = np.random.default_rng([self.seed, 0x717]).uniform(-1.0, 1.0, (N_LENSES, 2))
        return {
            "mla_shift_px": np.broadcast_to(np.asarray(self.mla_shift_px, float), rays.shape),
            "mla_rotation_deg": relative @ turn.T - relative,
            "lens_jitter_px": jitter * self.lens_jitter_px,
        }

    def check_system(self, system: SystemConfig) -> None:
        """Raise :class:`ConfigError` if these departures cannot describe ``system``.

        A chief ray moved outside the padded sensor frame, or every chief ray moved off
        the sensor, is an error naming the geometric field responsible (the largest part).
        """
        parts = self._offset_parts(system)
        rays = np.asarray(system.chief_rays, dtype=np.float64) + sum(parts.values())
        rows, cols = system.padded_shape
        inside_frame = (rays >= -0.5).all(1) & (rays[:, 0] < rows - 0.5) & (rays[:, 1] < cols - 0.5)
        window = system.sensor_window
        on_sensor = (
            (rays[:, 0] >= window[0].start) & (rays[:, 0] < window[0].stop)
            & (rays[:, 1] >= window[1].start) & (rays[:, 1] < window[1].stop)
        )  # fmt: skip
        if inside_frame.all() and on_sensor.any():
            return
        culprit = max(parts, key=lambda name: float(np.abs(parts[name]).max()))
        if not on_sensor.any():
            _fail(culprit, "moves every lens's chief ray off the sensor "
                           f"({system.sensor_shape[0]}×{system.sensor_shape[1]} px)")  # fmt: skip
        lens = int(np.flatnonzero(~inside_frame)[0])
        _fail(culprit, f"moves lens {lens}'s chief ray to ({rays[lens, 0]:.1f}, "
                       f"{rays[lens, 1]:.1f}), outside the padded frame of {rows}×{cols} px")

    def depth_planes(self) -> np.ndarray:
        """Defocus values (waves) of the planes averaged for a thick sample.

        One plane at ``defocus_waves`` for a thin sample; else the midpoints of
        ``max(3, ceil(10 · spread))`` equal slices of the slab ``defocus ± spread / 2``.
        """
        if self.depth_spread_waves == 0:
            return np.array([self.defocus_waves])
        count = max(3, math.ceil(_PLANES_PER_WAVE * self.depth_spread_waves))
        steps = (np.arange(count) + 0.5) / count - 0.5
        return self.defocus_waves + self.depth_spread_waves * steps

    # ------------------------------------------------------------- sampling
    def sample(self, rng: np.random.Generator, name: str | None = None) -> Departures:
        """One instrument drawn with these departures as ranges (domain randomisation).

        Signed quantities (array shift per axis, rotation, aberration errors, defocus) are
        drawn uniformly in ``[-|m|, |m|]``; magnitudes (jitter, depth spread, haze, hot-pixel
        fraction, PRNU, DSNU, read noise) uniformly in ``[0, m]``; the photon level
        log-uniformly in ``[photons / 2, 2 · photons]``. The truth model, haze width,
        hot-pixel level, ADC and full well are kept. The seed is drawn afresh.

        Parameters
        ----------
        rng : numpy.random.Generator
            Source of the draws (it advances).
        name : str, optional
            Name of the result; default ``"<name> (sampled)"``.

        Returns
        -------
        Departures
        """
        self.validate()
        changes: dict[str, Any] = {
            "name": name or f"{self.name} (sampled)",
            "seed": int(rng.integers(2**31)),
            "mla_shift_px": tuple(float(rng.uniform(-abs(m), abs(m))) for m in self.mla_shift_px),
        }
        for field in _SIGNED:
            magnitude = abs(getattr(self, field))
            changes[field] = float(rng.uniform(-magnitude, magnitude))
        for field in _MAGNITUDES:
            changes[field] = float(rng.uniform(0.0, getattr(self, field)))
        if self.read_noise_e is not None:
            changes["read_noise_e"] = float(rng.uniform(0.0, self.read_noise_e))
        if self.photons is not None:
            changes["photons"] = float(self.photons * 2.0 ** rng.uniform(-1.0, 1.0))
        return dataclasses.replace(self, **changes).validate()

    def with_optics_of(self, other: Departures) -> Departures:
        """A copy whose optical fields (:data:`OPTICAL_FIELDS`) and seed are ``other``'s.

        The seed fixes the lens jitter, so it goes with the optics (and the fixed-pattern
        maps, which it also seeds, follow it).
        """
        fields = {f: getattr(other, f) for f in OPTICAL_FIELDS}
        return dataclasses.replace(self, seed=other.seed, **fields)

    # --------------------------------------------------------------- named sets
    @classmethod
    def named(cls, name: str, system: SystemConfig | None = None) -> Departures:
        """A named set (:data:`NAMED_SETS`), pixel quantities scaled to ``system``.

        Parameters
        ----------
        name : str
            ``none``, ``calibration``, ``model``, ``background``, ``low-light`` or
            ``realistic``.
        system : SystemConfig, optional
            Pixel magnitudes are multiplied by ``optics.airy_radius /``
            :data:`REFERENCE_AIRY_RADIUS_PX`; default no scaling (``cm2-mini``).

        Examples
        --------
        >>> Departures.named("none").is_nominal
        True
        """
        if name not in NAMED_SETS:
            raise ConfigError(f"departures: unknown set {name!r}; choose one of "
                              f"{', '.join(NAMED_SETS)} or give a JSON file")  # fmt: skip
        departures = cls(name=name, **NAMED_SETS[name])
        if system is None:
            return departures.validate()
        scale = system.optics.airy_radius / REFERENCE_AIRY_RADIUS_PX
        changes: dict[str, Any] = {f: getattr(departures, f) * scale for f in _PIXEL_FIELDS}
        changes["mla_shift_px"] = tuple(v * scale for v in departures.mla_shift_px)
        return dataclasses.replace(departures, **changes).validate()

    # ---------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of every field (``to_json`` and ``save`` write it)."""
        data = dataclasses.asdict(self)
        data["mla_shift_px"] = list(self.mla_shift_px)
        return data

    @classmethod
    def from_dict(cls, data: Any) -> Departures:
        """Build and validate from a dictionary; unknown fields are errors naming them."""
        departures = _build(cls, data, "departures")
        if isinstance(departures.mla_shift_px, list):
            departures = dataclasses.replace(departures,
                                             mla_shift_px=tuple(departures.mla_shift_px))
        return departures.validate()

    @classmethod
    def from_json(cls, text: str) -> Departures:
        """Parse a JSON string; see :meth:`from_dict`."""
        return cls.from_dict(parse_json(text, "departures"))

    @classmethod
    def load(cls, path: str | Path) -> Departures:
        """Read departures from a JSON file."""
        return cls.from_json(read_text(path, "departures file"))


#: The named sets, pixel values for an Airy radius of 2 px (docs/regimes.md explains them).
NAMED_SETS: dict[str, dict[str, Any]] = {
    "none": {},
    "calibration": {
        "mla_shift_px": (0.5, -0.3),
        "mla_rotation_deg": 0.05,
        "lens_jitter_px": 0.25,
        "seed": 14,
    },
    "model": {
        "spherical_error_waves": 0.02,
        "coma_error_waves": -0.05,
        "astigmatism_error_waves": 0.06,
        "field_curvature_error_waves": -0.05,
        "distortion_error_px": 0.3,
        "defocus_waves": 0.25,
        "depth_spread_waves": 0.5,
        "truth_psf_grid": 13,
        "truth_rank_tolerance": 3e-3,
    },
    "background": {
        "background_fraction": 0.5,
        "background_width_px": 24.0,
    },
    "low-light": {
        "photons": 200.0,
        "read_noise_e": 1.6,
        "adc_bits": 12,
        "full_well_e": 10000.0,
    },
}
NAMED_SETS["realistic"] = {
    **NAMED_SETS["calibration"],
    **NAMED_SETS["model"],
    "background_fraction": 0.25,
    "background_width_px": 24.0,
    "photons": 1000.0,
    "read_noise_e": 1.6,
    "hot_pixel_fraction": 1e-4,
    "hot_pixel_e": 200.0,
    "prnu_percent": 1.0,
    "dsnu_e": 0.5,
    "adc_bits": 12,
    "full_well_e": 10000.0,
}


def load_departures(spec: str | Path | Departures, system: SystemConfig | None = None
                    ) -> Departures:  # fmt: skip
    """Departures from a set name, a JSON file or an existing object.

    Parameters
    ----------
    spec : str, Path or Departures
        A name of :data:`NAMED_SETS` (scaled to ``system``), or the path of a JSON file
        as written by :meth:`Departures.save` (taken as is).
    system : SystemConfig, optional
        When given, the result is checked against it (:meth:`Departures.check_system`).

    Raises
    ------
    ConfigError
        For an unknown name, invalid JSON or invalid values (naming the field).
    FileNotFoundError
        For a path that does not exist.
    """
    if isinstance(spec, Departures):
        departures = spec.validate()
    elif str(spec) in NAMED_SETS:
        departures = Departures.named(str(spec), system)
    elif str(spec).endswith(".json") or Path(spec).exists():
        departures = Departures.load(spec)
    else:
        raise ConfigError(f"departures: {str(spec)!r} is neither a named set "
                          f"({', '.join(NAMED_SETS)}) nor a JSON file")  # fmt: skip
    if system is not None:
        departures.check_system(system)
    return departures
