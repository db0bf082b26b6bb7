"""The system configuration: every size and coefficient of one CM² instrument.

One :class:`SystemConfig` describes the sensor, the 3×3 microlens lattice, the object
grid and its sub-views, the optics (PSF grid, aberrations, vignetting), the low-rank
order, the sensor noise and the training patches. It is saved next to every dataset,
model and result the product writes, so nothing is ever reconstructed with the wrong
geometry.

Conventions (used everywhere in the package)
--------------------------------------------
* Image axes are ``(row, col)``; 2-D points are ``(row, col)`` pairs, and normalised
  object coordinates are ``r = (v, u)`` with ``v`` along rows and ``u`` along columns.
* Normalised object coordinates span ``[-1, 1]`` from the first to the last pixel
  centre of the ``S × S`` object grid: pixel ``i`` sits at ``2 i / (S - 1) - 1``.
* Lenses are numbered ``0..8`` row-major over the 3×3 lattice.
* Chief-ray coordinates are integer ``(row, col)`` pixel positions in the *padded*
  sensor frame; sub-view ``ℓ`` is the ``S × S`` crop whose pixel ``(S // 2, S // 2)``
  is the chief ray ``c_ℓ``. Object pixel ``(i, j)`` imaged by lens ``ℓ`` lands at padded
  sensor pixel ``c_ℓ - S // 2 + (i, j)`` (plus its distortion, carried by the PSF).
* Physical sizes are in micrometres: ``object_pixel_um`` (object space, also the
  object-space size of a sensor pixel, as one maps onto the other) and
  ``sensor_pixel_um`` (the camera); the magnification is their ratio. The presets carry
  plausible values for the instrument they model, not a datasheet's
  (:data:`PRESET_PIXEL_SIZES`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

N_LENSES = 9
#: one GiB: the default working-memory budget of the forward model, the tiling and the
#: coordinate-mask cache
DEFAULT_MEMORY_BUDGET = 1 << 30

__all__ = [
    "N_LENSES",
    "ConfigError",
    "NoiseConfig",
    "OpticsConfig",
    "SystemConfig",
    "available_presets",
    "check_int",
    "check_number",
    "load_system",
    "system_from_scale",
]


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or out of range."""


def _fail(name: str, message: str) -> None:
    raise ConfigError(f"{name}: {message}")


def check_number(name: str, value: Any, low: float | None = None, strict: bool = False) -> float:
    """``value`` as a float if it is a finite real number (not a bool) of at least ``low``
    (above it with ``strict``); else :class:`ConfigError` naming the field ``name``.

    The configuration checks of the whole package (systems, networks, departures, training)
    use this and :func:`check_int`, so every bad value reads ``name: must be ..., got ...``.

    Examples
    --------
    >>> check_number("noise.photons", 0.0, low=0, strict=True)
    Traceback (most recent call last):
    ...
    svcode_core.config.ConfigError: noise.photons: must be > 0, got 0.0
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        _fail(name, f"must be a finite number, got {value!r}")
    if low is not None and (value < low or (strict and value == low)):
        _fail(name, f"must be {'>' if strict else '>='} {low:g}, got {value!r}")
    return float(value)


def check_int(name: str, value: Any, minimum: int = 1, maximum: int | None = None) -> int:
    """``value`` if it is an integer (not a bool) in ``minimum..maximum``; else
    :class:`ConfigError` naming the field ``name`` (see :func:`check_number`)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        _fail(name, f"must be an integer, got {value!r}")
    if maximum is not None and not minimum <= value <= maximum:
        _fail(name, f"must be in {minimum}..{maximum}, got {value}")
    if value < minimum:
        _fail(name, f"must be >= {minimum}, got {value}")
    return int(value)


def _check_pair(name: str, value: Any, integer: bool) -> None:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        _fail(name, f"must be a (row, col) pair, got {value!r}")
    for item in value:
        ok = isinstance(item, int) if integer else isinstance(item, (int, float))
        if not ok or isinstance(item, bool) or not math.isfinite(item):
            kind = "integers" if integer else "finite numbers"
            _fail(name, f"must hold two {kind}, got {value!r}")


@dataclass(frozen=True)
class OpticsConfig:
    """Pupil-model optics of one microlens and its field-dependent aberrations.

    Aberration coefficients are Seidel wavefront coefficients in waves, given at the
    reference field radius ``field_radius`` (normalised object units measured from the
    lens's own axis); the field dependence follows the Seidel powers of the normalised
    field ``h = |r - a_ℓ| / field_radius``.

    Attributes
    ----------
    psf_grid : int
        PSFs are computed on a ``psf_grid × psf_grid`` regular grid over ``[-1, 1]²``.
    kernel_size : int
        Odd side of the PSF window on the sensor, in pixels.
    airy_radius : float
        Radius of the diffraction-limited Airy core (first zero) in sensor pixels.
    pupil_samples : int
        Pupil diameter in samples for the Fourier-optics PSF model.
    field_radius : float
        Normalised field distance at which the coefficients below apply.
    spherical, coma, astigmatism, field_curvature : float
        Seidel coefficients W040, W131, W222, W220 in waves.
    distortion : float
        Image-point displacement in pixels at ``field_radius`` (grows as ``h³``,
        positive is barrel-outwards).
    vignetting_angle : float
        Field angle in degrees at ``field_radius``; intensity falls as ``cos⁴``.
    pupil_clip : float
        Lateral shift of the clipping aperture, in pupil radii, at ``field_radius``;
        clips the pupil asymmetrically and grows linearly with the field.
    """

    psf_grid: int = 7
    kernel_size: int = 33
    airy_radius: float = 2.0
    pupil_samples: int = 64
    field_radius: float = 1.75
    spherical: float = 0.1
    coma: float = 0.3
    astigmatism: float = 0.4
    field_curvature: float = 0.3
    distortion: float = 2.0
    vignetting_angle: float = 25.0
    pupil_clip: float = 0.6

    def validate(self, prefix: str = "optics") -> None:
        """Raise :class:`ConfigError` naming the first invalid field."""
        check_int(f"{prefix}.psf_grid", self.psf_grid, minimum=2)
        check_int(f"{prefix}.kernel_size", self.kernel_size, minimum=3)
        if self.kernel_size % 2 == 0:
            _fail(f"{prefix}.kernel_size", f"must be odd, got {self.kernel_size}")
        check_number(f"{prefix}.airy_radius", self.airy_radius, low=0, strict=True)
        check_int(f"{prefix}.pupil_samples", self.pupil_samples, minimum=8)
        check_number(f"{prefix}.field_radius", self.field_radius, low=0, strict=True)
        for name in ("spherical", "coma", "astigmatism", "field_curvature", "distortion"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                _fail(f"{prefix}.{name}", f"must be a finite number, got {value!r}")
        check_number(f"{prefix}.vignetting_angle", self.vignetting_angle, low=0)
        if self.vignetting_angle >= 90:
            _fail(
                f"{prefix}.vignetting_angle", f"must be < 90 degrees, got {self.vignetting_angle}"
            )
        check_number(f"{prefix}.pupil_clip", self.pupil_clip, low=0)


@dataclass(frozen=True)
class NoiseConfig:
    """Sensor model on data normalised to a peak of 1.

    A reading is ``clip(y + sqrt(a·y + b)·n + dark_offset, 0, saturation)`` with
    ``n ~ N(0, 1)`` (mixed Poisson–Gaussian), or, when ``photons`` is set, exact Poisson
    sampling with ``photons`` expected photo-electrons at intensity 1.

    Attributes
    ----------
    poisson_gain : float
        ``a``, the signal-dependent variance per unit intensity.
    gaussian_variance : float
        ``b``, the signal-independent (read-noise) variance.
    photons : float or None
        Expected photo-electrons at intensity 1 for exact Poisson sampling.
    saturation : float
        Full-well level; readings are clipped to ``[0, saturation]``.
    dark_offset : float
        Constant added before clipping (the sensor's dark level).
    """

    poisson_gain: float = 8.75e-5
    gaussian_variance: float = 6.2e-8
    photons: float | None = None
    saturation: float = 1.0
    dark_offset: float = 0.0

    def validate(self, prefix: str = "noise") -> None:
        """Raise :class:`ConfigError` naming the first invalid field."""
        check_number(f"{prefix}.poisson_gain", self.poisson_gain, low=0)
        check_number(f"{prefix}.gaussian_variance", self.gaussian_variance, low=0)
        if self.photons is not None:
            check_number(f"{prefix}.photons", self.photons, low=0, strict=True)
        check_number(f"{prefix}.saturation", self.saturation, low=0, strict=True)
        if not isinstance(self.dark_offset, (int, float)) or not math.isfinite(self.dark_offset):
            _fail(f"{prefix}.dark_offset", f"must be a finite number, got {self.dark_offset!r}")


def _lattice(centre: tuple[float, float], pitch: float) -> tuple[tuple[float, float], ...]:
    return tuple(
        (centre[0] + (i - 1) * pitch, centre[1] + (j - 1) * pitch)
        for i in range(3)
        for j in range(3)
    )


class JsonFile:
    """``to_json`` and ``save`` for a configuration class that defines ``to_dict``."""

    def to_dict(self) -> dict[str, Any]:  # pragma: no cover - defined by subclasses
        raise NotImplementedError

    def to_json(self) -> str:
        """The configuration as an indented JSON string."""
        return json.dumps(self.to_dict(), indent=2)

    def save(self, path: str | Path) -> Path:
        """Write the configuration as JSON to ``path`` and return the path."""
        path = Path(path)
        path.write_text(self.to_json() + "\n", encoding="utf-8")
        return path


@dataclass(frozen=True)
class SystemConfig(JsonFile):
    """One CM² instrument: geometry, optics, low-rank order, noise and patches.

    Attributes
    ----------
    name : str
        Preset or user name, recorded in every file.
    sensor_shape : (int, int)
        Raw sensor size in pixels ``(rows, cols)``.
    padding : (int, int)
        Zeros added on each side ``(rows, cols)``; the padded frame is
        ``sensor_shape + 2 * padding``.
    sub_view_size : int
        ``S``: side of the object grid and of each sub-view crop.
    chief_rays : 9 × (int, int)
        Chief-ray coordinates ``c_ℓ`` in padded-sensor pixels, row-major lens order.
    lens_axes : 9 × (float, float)
        Optical axis ``a_ℓ`` of each lens in normalised object coordinates ``(v, u)``.
    rank : int or None
        Low-rank order ``K``; ``None`` chooses the smallest ``K`` meeting ``rank_tolerance``.
    rank_tolerance : float
        Largest acceptable fraction of PSF energy left out by the rank-``K`` model.
    patch_size, patch_stride : int
        Training and inference tile size ``P`` and stride.
    optics : OpticsConfig
    noise : NoiseConfig
    psf_model : str or None
        A measured PSF stack (TIFF of :mod:`svcode_core.physics.psf_io`, its positions JSON beside
        it) that replaces the pupil model of ``optics``; ``None``: the pupil model. In a
        JSON file the path is relative to the file; :meth:`load` makes it absolute and
        :meth:`save` writes it relative to the new file.
    object_pixel_um : float or None
        Object-space size of one pixel in micrometres: the object-grid pitch, and the
        object-space size of a sensor pixel (one object pixel images onto one sensor
        pixel). ``None``: unknown, sizes are in pixels only.
    sensor_pixel_um : float or None
        Pitch of the camera's pixels in micrometres; with ``object_pixel_um`` it gives
        :attr:`magnification`.

    Notes
    -----
    The two sizes label the data in physical units (file resolution tags, napari scale
    bars, the calibration report); no computation uses them, so they are left out of
    ``==``: two systems that differ only in them image alike. A JSON file written before
    they existed gets the values of the preset of its ``name`` (``cm2-v2``,
    ``cm2-mini``), else ``None``.
    """

    name: str
    sensor_shape: tuple[int, int]
    padding: tuple[int, int]
    sub_view_size: int
    chief_rays: tuple[tuple[int, int], ...]
    lens_axes: tuple[tuple[float, float], ...]
    rank: int | None = None
    rank_tolerance: float = 1e-2
    patch_size: int = 96
    patch_stride: int = 48
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    psf_model: str | None = None
    object_pixel_um: float | None = field(default=None, compare=False)
    sensor_pixel_um: float | None = field(default=None, compare=False)

    # ------------------------------------------------------------------ derived
    @property
    def magnification(self) -> float | None:
        """Sensor pixel over object pixel (``None`` unless both sizes are known).

        Examples
        --------
        >>> round(SystemConfig.preset("cm2-v2").magnification, 4)
        0.6154
        """
        if self.object_pixel_um is None or self.sensor_pixel_um is None:
            return None
        return self.sensor_pixel_um / self.object_pixel_um

    @property
    def padded_shape(self) -> tuple[int, int]:
        """Shape ``(rows, cols)`` of the zero-padded sensor frame."""
        return (
            self.sensor_shape[0] + 2 * self.padding[0],
            self.sensor_shape[1] + 2 * self.padding[1],
        )

    @property
    def sensor_window(self) -> tuple[slice, slice]:
        """Slices of the padded frame that the raw sensor covers."""
        return (
            slice(self.padding[0], self.padding[0] + self.sensor_shape[0]),
            slice(self.padding[1], self.padding[1] + self.sensor_shape[1]),
        )

    # --------------------------------------------------------------- validation
    def validate(self) -> SystemConfig:
        """Check every field; raise :class:`ConfigError` naming the first bad one.

        Returns
        -------
        SystemConfig
            ``self``, so that ``SystemConfig(...).validate()`` chains.
        """
        if not isinstance(self.name, str) or not self.name:
            _fail("name", f"must be a non-empty string, got {self.name!r}")
        _check_pair("sensor_shape", self.sensor_shape, integer=True)
        for value in self.sensor_shape:
            check_int("sensor_shape", value, minimum=1)
        _check_pair("padding", self.padding, integer=True)
        for value in self.padding:
            check_int("padding", value, minimum=0)
        check_int("sub_view_size", self.sub_view_size, minimum=8)
        for name, points, integer in (
            ("chief_rays", self.chief_rays, True),
            ("lens_axes", self.lens_axes, False),
        ):
            if not isinstance(points, (tuple, list)) or len(points) != N_LENSES:
                _fail(name, f"must list {N_LENSES} (row, col) points, got {points!r}")
            for lens, point in enumerate(points):
                _check_pair(f"{name}[{lens}]", point, integer=integer)
        rows, cols = self.padded_shape
        for lens, (r, c) in enumerate(self.chief_rays):
            if not (0 <= r < rows and 0 <= c < cols):
                _fail(
                    f"chief_rays[{lens}]",
                    f"({r}, {c}) lies outside the padded sensor frame of {rows}×{cols}",
                )
        if self.rank is not None:
            check_int("rank", self.rank, minimum=1)
        check_number("rank_tolerance", self.rank_tolerance, low=0, strict=True)
        if self.rank_tolerance >= 1:
            _fail("rank_tolerance", f"must be < 1, got {self.rank_tolerance}")
        check_int("patch_size", self.patch_size, minimum=8)
        check_int("patch_stride", self.patch_stride, minimum=1)
        if self.patch_size > self.sub_view_size:
            _fail(
                "patch_size",
                f"{self.patch_size} exceeds the sub-view size {self.sub_view_size}",
            )
        if self.patch_stride > self.patch_size:
            _fail("patch_stride", f"{self.patch_stride} exceeds patch_size {self.patch_size}")
        if not isinstance(self.optics, OpticsConfig):
            _fail("optics", f"must be an OpticsConfig, got {type(self.optics).__name__}")
        self.optics.validate()
        if not isinstance(self.noise, NoiseConfig):
            _fail("noise", f"must be a NoiseConfig, got {type(self.noise).__name__}")
        self.noise.validate()
        if self.psf_model is not None and (not isinstance(self.psf_model, str)
                                           or not self.psf_model):  # fmt: skip
            _fail("psf_model", f"must be a file path or null, got {self.psf_model!r}")
        for name in PIXEL_SIZE_FIELDS:
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), low=0, strict=True)
        return self

    # --------------------------------------------------------------- JSON I/O
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of every field (nested configs as dictionaries)."""
        data = dataclasses.asdict(self)
        data["sensor_shape"] = list(self.sensor_shape)
        data["padding"] = list(self.padding)
        data["chief_rays"] = [list(p) for p in self.chief_rays]
        data["lens_axes"] = [list(p) for p in self.lens_axes]
        for name in ("psf_model", *PIXEL_SIZE_FIELDS):
            if data[name] is None:
                del data[name]  # optional fields, left out when unset: JSON as before
        return data

    def save(self, path: str | Path) -> Path:
        """Write the configuration as JSON to ``path`` and return the path.

        An absolute ``psf_model`` is written relative to the folder of ``path``.
        """
        path = Path(path)
        config = self
        if self.psf_model is not None and Path(self.psf_model).is_absolute():
            relative = os.path.relpath(self.psf_model, path.parent.resolve())
            config = dataclasses.replace(self, psf_model=Path(relative).as_posix())
        return JsonFile.save(config, path)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SystemConfig:
        """Build and validate a configuration from a dictionary (as written by ``to_dict``).

        Raises
        ------
        ConfigError
            On unknown or missing fields and on invalid values; the message names the field.
        """
        if not isinstance(data, dict):
            raise ConfigError(f"system: expected a JSON object, got {type(data).__name__}")
        data = dict(data)
        nested = {"optics": OpticsConfig, "noise": NoiseConfig}
        for key, klass in nested.items():
            if key in data:
                data[key] = _build(klass, data[key], key)
        if not any(name in data for name in PIXEL_SIZE_FIELDS):
            data.update(_preset_pixel_sizes(data.get("name")))
        config = _build(cls, data, "system")
        config = dataclasses.replace(
            config,
            sensor_shape=_as_tuple(config.sensor_shape),
            padding=_as_tuple(config.padding),
            chief_rays=tuple(_as_tuple(p) for p in _as_list(config.chief_rays, "chief_rays")),
            lens_axes=tuple(_as_tuple(p) for p in _as_list(config.lens_axes, "lens_axes")),
        )
        return config.validate()

    @classmethod
    def from_json(cls, text: str) -> SystemConfig:
        """Parse a JSON string; see :meth:`from_dict`."""
        return cls.from_dict(parse_json(text, "system"))

    @classmethod
    def load(cls, path: str | Path) -> SystemConfig:
        """Read a configuration from a JSON file; a relative ``psf_model`` is resolved
        against the file's folder."""
        path = Path(path)
        config = cls.from_json(read_text(path, "system configuration"))
        if config.psf_model is not None and not Path(config.psf_model).is_absolute():
            model = (path.parent / config.psf_model).resolve()
            config = dataclasses.replace(config, psf_model=str(model))
        return config

    # ----------------------------------------------------------------- presets
    @classmethod
    def tiny(cls) -> SystemConfig:
        """A small system for examples and tests, not an instrument: a 60 × 80 sensor,
        48-pixel sub-views, 9-pixel kernels on a 3 × 3 PSF grid (fast to simulate), with
        round pixel sizes (10 µm object pixels, 5 µm sensor pixels).

        Examples
        --------
        >>> tiny = SystemConfig.tiny()
        >>> tiny.sensor_shape, tiny.sub_view_size, tiny.padded_shape
        ((60, 80), 48, (84, 84))
        """
        optics = OpticsConfig(psf_grid=3, kernel_size=9, airy_radius=1.0, pupil_samples=32,
                              distortion=0.5)  # fmt: skip
        system = system_from_scale("tiny", (60, 80), 48, 18, 16, optics, 1e-2)
        return dataclasses.replace(system, **TINY_PIXEL_SIZES).validate()

    @classmethod
    def preset(cls, name: str) -> SystemConfig:
        """A named preset: ``"cm2-v2"`` (paper scale) or ``"cm2-mini"`` (CPU scale).

        Examples
        --------
        >>> SystemConfig.preset("cm2-mini").sub_view_size
        384
        """
        builders = {"cm2-v2": _cm2_v2, "cm2-mini": _cm2_mini}
        if name not in builders:
            raise ConfigError(f"preset: unknown preset {name!r}; choose one of {sorted(builders)}")
        return builders[name]().validate()

    def replace(self, **changes: Any) -> SystemConfig:
        """A validated copy with some fields changed."""
        return dataclasses.replace(self, **changes).validate()


def parse_json(text: str, prefix: str) -> Any:
    """``json.loads(text)``, a :class:`ConfigError` starting with ``prefix`` if invalid."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise ConfigError(f"{prefix}: not valid JSON ({err})") from None


def read_text(path: str | Path, what: str) -> str:
    """The text of a configuration file; ``FileNotFoundError`` naming ``what`` if missing."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    return path.read_text(encoding="utf-8")


def _as_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _as_list(value: Any, name: str) -> list:
    if not isinstance(value, (list, tuple)):
        _fail(name, f"must be a list of (row, col) points, got {value!r}")
    return list(value)


def _build(klass: type, data: Any, prefix: str) -> Any:
    if not isinstance(data, dict):
        _fail(prefix, f"expected a JSON object, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(klass)}
    unknown = sorted(set(data) - names)
    if unknown:
        _fail(f"{prefix}.{unknown[0]}", f"unknown field (known: {sorted(names)})")
    try:
        return klass(**data)
    except TypeError as err:  # a required field is missing
        raise ConfigError(f"{prefix}: {err}") from None


def system_from_scale(
    name: str,
    sensor_shape: tuple[int, int],
    sub_view_size: int,
    pitch: int,
    patch_size: int,
    optics: OpticsConfig,
    rank_tolerance: float,
) -> SystemConfig:
    """A system whose ideal lens lattice is centred in the padded frame (how the presets
    are made; also for small test systems).

    The padded frame is ``S + 2·pitch`` square, so the nine sub-views tile it exactly.

    Examples
    --------
    >>> optics = OpticsConfig(psf_grid=3, kernel_size=9, airy_radius=1.0, pupil_samples=32)
    >>> tiny = system_from_scale("tiny", (60, 80), 48, 18, 16, optics, 1e-2).validate()
    >>> tiny.padded_shape, tiny.chief_rays[4]
    ((84, 84), (42, 42))
    """
    side = sub_view_size + 2 * pitch
    padding = ((side - sensor_shape[0]) // 2, (side - sensor_shape[1]) // 2)
    centre = (side // 2, side // 2)
    chief_rays = tuple((int(r), int(c)) for r, c in _lattice(centre, pitch))
    axis_pitch = 2.0 * pitch / (sub_view_size - 1)
    lens_axes = _lattice((0.0, 0.0), axis_pitch)
    return SystemConfig(
        name=name,
        sensor_shape=sensor_shape,
        padding=padding,
        sub_view_size=sub_view_size,
        chief_rays=chief_rays,
        lens_axes=tuple((round(v, 12), round(u, 12)) for v, u in lens_axes),
        rank=None,
        rank_tolerance=rank_tolerance,
        patch_size=patch_size,
        patch_stride=patch_size // 2,
        optics=optics,
        noise=NoiseConfig(),
    )


#: The pixel-size fields of :class:`SystemConfig` (physical labels, outside ``==``).
PIXEL_SIZE_FIELDS = ("object_pixel_um", "sensor_pixel_um")

#: Pixel sizes of the presets, in micrometres. Plausible values for the instrument each
#: preset models, not a datasheet: ``cm2-v2`` is a paper-scale CM² (3000 × 4000 CMOS of
#: 2 µm pixels, nine 2400² sub-views imaging a 7.8 mm field, so 3.25 µm object pixels
#: and a magnification of 0.615); ``cm2-mini`` is that instrument at 0.16 × the pixel
#: count: the same 7.8 mm field and magnification on 384² sub-views, so pixels
#: 1 / 0.16 times coarser (20.3125 µm in object space, 12.5 µm on the sensor).
PRESET_PIXEL_SIZES = {
    "cm2-v2": {"object_pixel_um": 3.25, "sensor_pixel_um": 2.0},
    "cm2-mini": {"object_pixel_um": 3.25 / 0.16, "sensor_pixel_um": 2.0 / 0.16},
}
#: Round values for the ``tiny`` test system (no instrument).
TINY_PIXEL_SIZES = {"object_pixel_um": 10.0, "sensor_pixel_um": 5.0}


def _preset_pixel_sizes(name: Any) -> dict[str, float]:
    """The pixel sizes a system file of ``name`` gets when it records none: a preset's
    (``tiny``, a name test systems of any geometry share, gets none)."""
    return dict(PRESET_PIXEL_SIZES.get(name, {})) if isinstance(name, str) else {}


def _cm2_v2() -> SystemConfig:
    """Paper scale: padded 4200², sub-views 2400², lens pitch 900 px, patches 480/240."""
    return system_from_scale(
        "cm2-v2",
        sensor_shape=(3000, 4000),
        sub_view_size=2400,
        pitch=900,
        patch_size=480,
        optics=OpticsConfig(psf_grid=9, kernel_size=129, airy_radius=8.0, pupil_samples=128,
                            distortion=8.0),
        rank_tolerance=1e-2,
    ).replace(**PRESET_PIXEL_SIZES["cm2-v2"])


def _cm2_mini() -> SystemConfig:
    """CPU scale (0.16 × paper): padded 672², sub-views 384², pitch 144 px, patches 96/48."""
    return system_from_scale(
        "cm2-mini",
        sensor_shape=(480, 640),
        sub_view_size=384,
        pitch=144,
        patch_size=96,
        optics=OpticsConfig(),
        rank_tolerance=1e-2,
    ).replace(**PRESET_PIXEL_SIZES["cm2-mini"])


def available_presets() -> list[str]:
    """Names accepted by :meth:`SystemConfig.preset`."""
    return ["cm2-mini", "cm2-v2"]


def load_system(spec: str | Path | SystemConfig) -> SystemConfig:
    """A system from a preset name, a JSON path, or an existing configuration."""
    if isinstance(spec, SystemConfig):
        return spec.validate()
    text = str(spec)
    if text in available_presets():
        return SystemConfig.preset(text)
    if text.endswith(".json") or Path(text).exists():
        return SystemConfig.load(text)
    raise ConfigError(
        f"system: {text!r} is neither a preset ({', '.join(available_presets())}) "
        "nor an existing JSON file"
    )
