"""End-to-end simulation of CM² measurements: object → noisy raw frame, views, targets.

With :class:`~svcode_core.physics.departures.Departures` the frame comes from the true instrument
(:class:`~svcode_core.physics.instrument.Instrument`) while views are cut, as a user would, at the
nominal system's chief rays.
"""

from __future__ import annotations

import contextlib
import errno
import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..config import SystemConfig
from ..io import atomic_path, write_json_atomic, write_tiff
from ..outputs import NoSpaceError, OutputLock, free_bytes, no_space, require_space
from .cm2 import CM2Operator
from .departures import Departures, load_departures
from .geometry import extract_sub_views, pad_sensor_frame
from .instrument import Instrument
from .noise import SensorModel, apply_sensor_noise
from .scene_checks import check_system_geometry

__all__ = ["Simulation", "Simulator", "scene_bytes", "scene_files"]

SCENE_FILES = ("measurement.tif", "views.tif", "demixed.tif", "object.tif", "system.json")
#: bytes allowed per scene file beyond its pixels (TIFF header, metadata)
_HEADROOM = 1 << 16


def scene_files(out_dir: str | Path) -> dict[str, Path]:
    """The files :meth:`Simulation.save` writes to ``out_dir``, by name."""
    return {name: Path(out_dir) / name for name in SCENE_FILES}


def scene_bytes(sensor_shape: tuple[int, int], size: int, frames: int = 1) -> int:
    """Bytes of the files :meth:`Simulation.save` writes for ``frames`` sensor frames and
    sub-views of ``size`` (the TIFF headers and the JSON files rounded up)."""
    height, width = sensor_shape
    pixels = frames * height * width + (2 * 9 + 1) * size * size
    return 4 * pixels + len(SCENE_FILES) * _HEADROOM


@dataclass
class Simulation:
    """One simulated scene.

    Attributes
    ----------
    object : numpy.ndarray
        Ground truth ``(S, S)``.
    measurement : numpy.ndarray
        Raw sensor frame ``(H, W)``, or ``(T, H, W)`` for ``T`` noise draws of the scene.
    views : numpy.ndarray
        The nine sub-views ``(9, S, S)`` of the (first) padded measurement: the network input.
    demixed : numpy.ndarray
        Noiseless per-lens images ``(9, S, S)``: the demixing targets.
    """

    object: np.ndarray
    measurement: np.ndarray
    views: np.ndarray
    demixed: np.ndarray

    def save(
        self,
        out_dir: str | Path,
        system: SystemConfig,
        extra: dict | None = None,
        departures: Departures | None = None,
    ) -> Path:
        """Write ``measurement.tif``, ``views.tif``, ``demixed.tif``, ``object.tif`` and
        ``system.json`` to ``out_dir``; every TIFF records the system and ``extra``.

        With ``departures`` (the true instrument's), they are also recorded in every TIFF
        (key ``departures``) and written to ``departures.json``; ``system`` stays the
        nominal system a user would have.

        The files appear together or not at all: a failure leaves none of them (and an
        earlier scene in ``out_dir`` whole).

        Raises
        ------
        NoSpaceError
            Before writing, if the files do not fit on the disk (also when a write fails
            for want of space).
        """
        out_dir = Path(out_dir)
        require_space({out_dir: self.nbytes()})
        created = not out_dir.exists()
        out_dir.mkdir(parents=True, exist_ok=True)
        if departures is not None:
            extra = {**(extra or {}), "departures": departures.to_dict()}
        files = scene_files(out_dir)
        try:
            with OutputLock(out_dir / "scene"):  # one writer at a time: no mixed scenes
                self._write(files, system, extra, departures, out_dir / "departures.json")
        except OSError as err:
            if created:
                with contextlib.suppress(OSError):
                    out_dir.rmdir()  # made for this scene, and empty again
            if isinstance(err, NoSpaceError):
                raise
            # a full disk, whether or not the writer said so ("N requested and M written")
            if err.errno == errno.ENOSPC or free_bytes(out_dir) < self.nbytes():
                raise no_space(out_dir, self.nbytes()) from None
            raise
        return out_dir

    def _write(self, files: dict[str, Path], system: SystemConfig, extra: dict | None,
               departures: Departures | None, departures_path: Path) -> None:
        """Write every file under a temporary name, then rename them all: a failure
        (a full disk) leaves none of them, and an earlier scene there whole."""
        with contextlib.ExitStack() as written:
            for name in ("measurement", "views", "demixed", "object"):
                partial = written.enter_context(atomic_path(files[f"{name}.tif"]))
                write_tiff(partial, getattr(self, name), system, kind=name, extra=extra)
            partial = written.enter_context(atomic_path(files["system.json"]))
            write_json_atomic(partial, system.to_dict())
            if departures is not None:
                partial = written.enter_context(atomic_path(departures_path))
                departures.save(partial)

    def nbytes(self) -> int:
        """Bytes of the files :meth:`save` writes (:func:`scene_bytes`)."""
        frames = self.measurement.shape[0] if self.measurement.ndim == 3 else 1
        return scene_bytes(self.measurement.shape[-2:], self.object.shape[-1], frames)


class Simulator:
    """Simulate raw CM² frames of a system, with its forward model built once.

    Parameters
    ----------
    system : SystemConfig
        Refused if none of its chief rays lies on the sensor; warned about if some do not,
        or if two coincide (:func:`~svcode_core.physics.scene_checks.check_system_geometry`).
    operator : CM2Operator, optional
        Default: :meth:`CM2Operator.from_system` (pupil-model PSFs, ``system.rank``).
    device, dtype
        Where and in which precision the forward model runs.
    departures : Departures or str, optional
        The true instrument's departures from ``system`` (or a named set / JSON path);
        ``None`` or nominal departures simulate the nominal system itself. Not together
        with ``operator``.

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> scene = Simulator(tiny).simulate(np.zeros((48, 48)), seed=0)
    >>> scene.measurement.shape, scene.views.shape
    ((60, 80), (9, 48, 48))
    """

    def __init__(
        self,
        system: SystemConfig,
        operator: CM2Operator | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        departures: Departures | str | None = None,
        _reuse: Instrument | None = None,
    ) -> None:
        self.system = system.validate()
        check_system_geometry(self.system)
        if departures is not None:
            departures = load_departures(departures, self.system)
        self.departures = departures
        self.instrument: Instrument | None = None
        if departures is None or departures.is_nominal:
            self.operator = operator or CM2Operator.from_system(system, dtype=dtype, device=device)
            return
        if operator is not None:
            raise ValueError("give either an operator or departures, not both: the "
                             "departed instrument builds its own forward model")  # fmt: skip
        self.instrument = Instrument.build(self.system, departures, dtype, device, _reuse)
        self.operator = self.instrument.operator

    def with_departures(self, departures: Departures) -> Simulator:
        """A simulator of the same nominal system with other departures.

        The forward model is reused when the optical departures are this simulator's (only
        haze or camera differ), so per-frame draws of those cost no PSF computation.
        """
        departures = load_departures(departures, self.system)
        reuse = self.instrument or Instrument(
            self.system, Departures(), self.system, self.operator, SensorModel(self.system.noise)
        )
        if departures.is_nominal and not reuse.departures.has_optics:
            return Simulator(self.system, operator=self.operator, departures=departures)
        lenses = self.operator.lenses
        return Simulator(self.system, dtype=lenses.dtype, device=lenses.device,
                         departures=departures, _reuse=reuse)  # fmt: skip

    def simulate(
        self,
        obj: np.ndarray | torch.Tensor,
        seed: int | None = 0,
        noise: bool = True,
        frames: int = 1,
        progress: bool = False,
        margin: int = 0,
    ) -> Simulation:
        """Image ``obj`` through the instrument.

        Parameters
        ----------
        obj : array_like
            Object ``(S, S)``, normalised to ``[0, 1]``.
        seed : int or None
            Seed of the noise draws (``None``: fresh entropy).
        noise : bool
            Apply the sensor model of ``system.noise`` (noise, dark offset, saturation),
            or the departed camera's. ``False`` gives the expected reading: with
            departures, haze and fixed-pattern maps included, no random noise.
        frames : int
            Number of independent noise draws of the same scene (``T``).
        progress : bool
            Show a progress bar over frames.
        margin : int
            The sub-views (``views`` and ``demixed``) run this many pixels past their
            windows on every side, ``(9, S + 2·margin, S + 2·margin)``; at most the
            operator's margin.

        Returns
        -------
        Simulation
        """
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        op = self.operator
        x = torch.as_tensor(np.asarray(obj), dtype=op.lenses.dtype, device=op.lenses.device)
        if self.instrument is None:
            clean, targets = op.measure_with_targets(x, margin)
            read = functools.partial(apply_sensor_noise, noise=self.system.noise)
        else:
            clean, targets = self.instrument.observe(x, margin)
            read = self.instrument.sensor.read
        generator = torch.Generator(device=clean.device)
        if seed is None:
            generator.seed()
        else:
            generator.manual_seed(int(seed))
        readings = []
        for _ in tqdm(range(frames), desc="simulate", disable=not progress, leave=False):
            frame = read(clean, generator=generator) if noise else clean
            readings.append(frame)
        views = extract_sub_views(pad_sensor_frame(readings[0], self.system), self.system, margin)
        measurement = torch.stack(readings) if frames > 1 else readings[0]
        return Simulation(
            object=_numpy(x),
            measurement=_numpy(measurement),
            views=_numpy(views),
            demixed=_numpy(targets),
        )


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().to("cpu", torch.float32).numpy()
