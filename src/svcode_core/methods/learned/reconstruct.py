"""Reconstructing raw frames with a trained learned baseline (MultiWienerNet, SV-FourierNet).

:class:`LearnedReconstructor` keeps the contract of every method
(:class:`~svcode_core.methods.base.BaseReconstructor`), so the streaming command line and
the dask back end run these methods like the others. Both map the whole padded frame to the
object at once: there is no tiling and no demixing, so no views are returned. Frames are
brought to one exposure level before the network and the output scaled back
(:mod:`~svcode_core.methods.exposure`).
"""

from __future__ import annotations

import threading
from collections.abc import Generator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ...config import SystemConfig
from ...physics.geometry import pad_sensor_frame
from .. import registry
from ..base import (
    FrameByFrame,
    FrameProgress,
    ReconstructionResult,
    precision_dtype,
    resolve_device,
)
from ..exposure import exposure_gain
from ..frames import finite_frame
from ..registry import LEARNED_METHODS, method_of_architecture

__all__ = ["LearnedReconstructor"]


class LearnedReconstructor(FrameByFrame):
    """Reconstruct raw CM² frames with a trained MultiWienerNet or SV-FourierNet.

    Parameters
    ----------
    model : MultiWienerNet or SVFourierNet
    system : SystemConfig
        Must be the system the model was built for.
    device : str
    precision : {"fp32", "bf16"}
        ``bf16`` runs the refinement U-Net under autocast; the Fourier filters always run
        in float32 (torch has no half-precision FFT on the CPU).
    normalise_exposure : bool
        Bring each frame to the training level and scale the output back (default);
        ``False`` runs the frames as they are.
    """

    has_views = False

    def __init__(
        self,
        model: nn.Module,
        system: SystemConfig,
        device: str = "cpu",
        precision: str = "fp32",
        normalise_exposure: bool = True,
    ) -> None:
        architectures = [registry.method(name).architecture for name in LEARNED_METHODS]
        if type(model).__name__ not in architectures:
            raise TypeError(f"model must be one of {architectures}, got {type(model).__name__}")
        self.method = method_of_architecture(type(model).__name__)
        precision_dtype(precision, self.method)
        if model.system != system:
            raise ValueError("the model was built for another system configuration")
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.system = system
        self.precision = precision
        self.normalise_exposure = bool(normalise_exposure)
        self._gains: dict[int, float] = {}

    @classmethod
    def build(
        cls,
        method: str,
        system: SystemConfig | None,
        weights: str | Path | None = None,
        model: nn.Module | None = None,
        **options: Any,
    ) -> LearnedReconstructor:
        """From ``model``, else the model file ``weights`` (one of ``method``); none is
        bundled."""
        if model is not None:
            return cls(model, system, **options)
        if weights is None:
            raise ValueError(
                f"{registry.method(method).title} needs a trained model file: none is "
                f"bundled; train one with `svcode train --method {method}`"
            )
        return cls.from_weights(weights, system, method, **options)

    @classmethod
    def from_weights(
        cls,
        path: str | Path,
        system: SystemConfig | None = None,
        method: str | None = None,
        **options: Any,
    ) -> LearnedReconstructor:
        """Load a model file (and its system, unless given).

        ``method`` (``"multiwiener"`` or ``"fouriernet"``), when given, must name the
        file's architecture. ``options`` are those of the constructor (``device``,
        ``precision``, ``normalise_exposure``).
        """
        from ..model_file import load_model, read_model_metadata

        architecture = read_model_metadata(path)["architecture"]
        learned = {name: registry.method(name).architecture for name in LEARNED_METHODS}
        if method is not None and learned.get(method) != architecture:
            raise ValueError(
                f"{Path(path).name} holds a {architecture}, not a "
                f"{learned.get(method, method)} (--method {method})"
            )
        if architecture not in learned.values():
            raise ValueError(f"{Path(path).name} holds a {architecture}, not a learned baseline")
        model, trained = load_model(path, system=system, device=options.get("device", "cpu"))
        return cls(model, trained if system is None else system, **options)

    def start_stack(self) -> None:
        self._gains = {}  # each frame's exposure gain, by index

    def iter_reconstruct(
        self, frames: Any, return_views: bool = False, cancel: threading.Event | None = None
    ) -> Generator[FrameProgress, None, ReconstructionResult]:
        result = yield from super().iter_reconstruct(frames, return_views, cancel)
        if self.normalise_exposure:  # a blank frame is 0, whatever its gain: 1 as for SV-CoDe
            count = 1 if result.reconstruction.ndim == 2 else len(result.reconstruction)
            result.exposure_gains = np.array([self._gains.get(i, 1.0) for i in range(count)])
        return result

    def reconstruct_frame(
        self, frame: np.ndarray, index: int, return_views: bool
    ) -> tuple[np.ndarray, None]:
        """One raw frame → its float32 reconstruction (these methods do not demix)."""
        values = finite_frame(frame, index)
        gain = exposure_gain(np.maximum(values, 0.0)) if self.normalise_exposure else 1.0
        self._gains[index] = gain
        padded = pad_sensor_frame(
            torch.from_numpy(values * np.float32(gain)).to(self.device), self.system
        )
        bf16 = self.precision == "bf16"
        with torch.inference_mode(), torch.autocast(self.device.type, dtype=torch.bfloat16,
                                                    enabled=bf16):  # fmt: skip
            estimate = self.model(padded[None])[0, 0]
        return estimate.float().cpu().numpy() / np.float32(gain), None
