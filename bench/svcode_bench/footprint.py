"""Size of a reconstruction method: parameters and peak memory at the field size S and 2S.

The learned baselines filter the whole padded frame, so their parameters and memory grow
with the field of view; SV-CoDe works on fixed-size tiles with a fixed network, so only its
activations and (bounded) mask cache grow. :func:`model_footprint` measures both at the
system's own sub-view size and at twice it (:func:`doubled_system`), with the architecture
of a model file re-built for the larger system (the weights' values do not change the size).

Peak memory is the rise of the peak resident set size (``VmHWM`` in ``/proc/self/status``,
reset through ``/proc/self/clear_refs``) over building the model and reconstructing one
frame of uniform noise (no tile is empty, so none is skipped), measured in a fresh process
so that memory an earlier computation left to the allocator is not silently reused;
``None`` where the peak cannot be reset (not Linux).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from svcode_core.config import SystemConfig
from svcode_core.methods.registry import ARCHITECTURES, method_of_architecture

__all__ = ["Footprint", "PeakMemory", "doubled_system", "model_footprint"]


class PeakMemory:
    """Rise of the peak resident set size over a block, in MiB (Linux; ``None`` elsewhere)."""

    def __enter__(self) -> PeakMemory:
        self.mib: float | None = None
        self._start = _status_kib("VmRSS")
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            self._start = None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._start is not None:
            self.mib = max(_status_kib("VmHWM") - self._start, 0) / 1024


def _status_kib(field_name: str) -> int | None:
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        if line.startswith(field_name + ":"):
            return int(line.split()[1])
    return None


def doubled_system(system: SystemConfig) -> SystemConfig:
    """``system`` with every length on the sensor doubled (sensor, padding, sub-view size,
    chief rays); optics, patch size and noise unchanged."""
    return system.replace(
        name=f"{system.name}-2S",
        sensor_shape=tuple(2 * v for v in system.sensor_shape),
        padding=tuple(2 * v for v in system.padding),
        sub_view_size=2 * system.sub_view_size,
        chief_rays=tuple((2 * r, 2 * c) for r, c in system.chief_rays),
    )


@dataclass(frozen=True)
class Footprint:
    """Parameters (millions) and peak MiB of one frame at S and 2S (see the module)."""

    parameters_m: float
    parameters_m_2s: float
    peak_mib: float | None
    peak_mib_2s: float | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return dict(self.__dict__)


def _build(architecture: str, config: Any, system: SystemConfig) -> tuple[nn.Module, Any]:
    """A fresh model of ``architecture`` for ``system`` and a reconstructor around it."""
    from svcode_core.methods.build import build_reconstructor
    from svcode_core.methods.learned import LEARNED_MODELS
    from svcode_core.network import SVCoDe

    if architecture in LEARNED_MODELS:
        model = LEARNED_MODELS[architecture](config, system)
    else:
        model = SVCoDe(config)
    method = method_of_architecture(architecture)
    return model, build_reconstructor(method, system, model=model)


def _one_frame(
    architecture: str, config: Any, system: SystemConfig, threads: int
) -> tuple[int, float | None]:
    torch.set_num_threads(threads)
    frame = np.random.default_rng(0).random(system.sensor_shape, dtype=np.float32)
    with PeakMemory() as memory:
        model, reconstructor = _build(architecture, config, system)
        reconstructor.reconstruct(frame)
    return sum(p.numel() for p in model.parameters()), memory.mib


def _in_fresh_process(*args: Any) -> tuple[int, float | None]:
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(_one_frame, *args).result()


def model_footprint(weights: str | Path, system: SystemConfig) -> Footprint:
    """Parameters and peak memory of the model in ``weights`` at S and at 2S.

    Parameters
    ----------
    weights : str or Path
        A model file (SV-CoDe, MultiWienerNet or SV-FourierNet).
    system : SystemConfig
        The field size S it is measured at (and 2S, :func:`doubled_system`).
    """
    from svcode_core.methods.model_file import read_model_metadata

    meta = read_model_metadata(weights)
    architecture, config = meta["architecture"], meta["model_config"]
    if architecture not in ARCHITECTURES:
        raise ValueError(f"{Path(weights).name}: no footprint for a {architecture}")
    threads = torch.get_num_threads()
    params, peak = _in_fresh_process(architecture, config, system, threads)
    params_2s, peak_2s = _in_fresh_process(architecture, config, doubled_system(system), threads)
    return Footprint(params / 1e6, params_2s / 1e6, peak, peak_2s)
