"""Expensive core objects the widgets share, built on demand and cached in memory."""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from svcode_core.config import SystemConfig
from svcode_core.methods.model_file import FREE_FIELDS, load_model
from svcode_core.physics.simulate import Simulator
from svcode_core.pretrained import bundled_weights as bundled_model

__all__ = ["FREE_FIELDS", "NO_BUNDLED_MODEL", "available_devices", "bundled_model",
           "cached_model", "simulator"]


@functools.lru_cache(maxsize=4)
def simulator(system: SystemConfig, departures: str = "none") -> Simulator:
    """The :class:`~svcode_core.physics.simulate.Simulator` of ``system`` as it is, or of
    the instrument that departs from it by a named set of departures
    (:data:`~svcode_core.physics.departures.NAMED_SETS`); PSFs built once."""
    if departures == "none":
        return Simulator(system)
    return simulator(system, "none").with_departures(departures)  # the nominal one's PSFs


NO_BUNDLED_MODEL = (
    "No bundled SV-CoDe model is installed for this system; choose 'model file' and select "
    "a .safetensors model trained for this system"
)


def cached_model(path: str | Path, system: SystemConfig | None = None):
    """``(model, training system)`` of a model file, loaded once per file version.

    ``system`` (optional) is checked against the model's training system, except for
    :data:`FREE_FIELDS`: the model applies unchanged to a system whose sub-views are cut
    at other chief rays (a moved sub-view box, calibrated chief rays) or whose forward
    model is measured (a calibration's PSFs).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        A model trained for another system: the differing fields first (short enough for
        a toast), then the full comparison.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    model, stored = _load(str(path.resolve()), path.stat().st_mtime_ns)
    if system is None:
        return model, stored
    placed = system.replace(**{name: getattr(stored, name) for name in FREE_FIELDS})
    if placed != stored:
        given, trained = placed.to_dict(), stored.to_dict()
        fields = [name for name in sorted(given.keys() | trained.keys())
                  if given.get(name) != trained.get(name)]
        try:
            load_model(path, system=placed)  # raises, naming the differing fields in full
        except ValueError as err:
            raise ValueError(f"{path.name} was trained for system {stored.name!r}, which "
                             f"differs in {', '.join(fields)}; {err}") from None
    return model, stored


@functools.lru_cache(maxsize=2)
def _load(path: str, mtime_ns: int):
    return load_model(path)


def available_devices() -> list[str]:
    """Devices PyTorch can use here, CPU first."""
    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += [f"cuda:{index}" for index in range(torch.cuda.device_count())]
    if torch.backends.mps.is_available():
        devices.append("mps")
    return devices
