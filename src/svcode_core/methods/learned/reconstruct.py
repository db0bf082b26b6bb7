"""Reconstructing raw frames with a trained learned baseline (MultiWienerNet, SV-FourierNet).

:class:`LearnedReconstructor` has the interface of
:class:`~svcode_core.reconstruct.Reconstructor` (``reconstruct`` of a frame or a stack,
returning a :class:`~svcode_core.reconstruct.ReconstructionResult`), and
:class:`LearnedSpec` is its picklable recipe, so :func:`svcode_core.stream.reconstruct_file`
and the dask back ends run these methods like the others. Both methods map the whole padded
frame to the object at once: there is no tiling and no demixing, so no views are returned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..config import SystemConfig
from ..geometry import pad_sensor_frame
from ..reconstruct import (
    ReconstructionResult,
    as_frame_stack,
    check_frame_shape,
    finite_frame,
    resolve_device,
)

__all__ = ["ARCHITECTURES", "LearnedReconstructor", "LearnedSpec"]

#: ``--method`` name → architecture stored in the model file
ARCHITECTURES = {"multiwiener": "MultiWienerNet", "fouriernet": "SVFourierNet"}
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16}


class LearnedReconstructor:
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
    """

    def __init__(
        self, model: nn.Module, system: SystemConfig, device: str = "cpu", precision: str = "fp32"
    ) -> None:
        if type(model).__name__ not in ARCHITECTURES.values():
            raise TypeError(
                f"model must be one of {sorted(ARCHITECTURES.values())}, got {type(model).__name__}"
            )
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        if model.system != system:
            raise ValueError("the model was built for another system configuration")
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()
        self.system = system
        self.precision = precision

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
        file's architecture. ``options`` are ``device`` and ``precision``.
        """
        from ..network import load_model, read_model_metadata

        architecture = read_model_metadata(path)["architecture"]
        if method is not None and ARCHITECTURES.get(method) != architecture:
            wanted = ARCHITECTURES.get(method, method)
            raise ValueError(
                f"{Path(path).name} holds a {architecture}, not a {wanted} (--method {method})"
            )
        if architecture not in ARCHITECTURES.values():
            raise ValueError(f"{Path(path).name} holds a {architecture}, not a learned baseline")
        model, system = load_model(path, system=system, device=options.get("device", "cpu"))
        return cls(model, system, **options)

    def _padded(self, frame: np.ndarray, index: int) -> torch.Tensor:
        check_frame_shape(frame.shape, self.system)
        values = finite_frame(frame, index)
        return pad_sensor_frame(torch.from_numpy(values).to(self.device), self.system)

    @torch.inference_mode()
    def reconstruct(self, frames: Any, return_views: bool = False) -> ReconstructionResult:
        """Reconstruct a raw frame ``(H, W)`` or a stack ``(T, H, W)``.

        Raises
        ------
        ValueError
            For views (these methods do not demix), a wrong frame size, NaN or Inf.
        """
        if return_views:
            raise ValueError(
                f"{type(self.model).__name__} reconstructs the object directly and has no "
                "demixed views; use --method svcode (or a model-based baseline) for views"
            )
        single = np.ndim(frames) == 2
        stack = as_frame_stack(frames)
        start = time.perf_counter()
        recons = []
        bf16 = self.precision == "bf16"
        for index, frame in enumerate(stack):
            padded = self._padded(frame, index)[None]
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
                estimate = self.model(padded)[0, 0]
            recons.append(estimate.float().cpu().numpy())
        recon = np.stack(recons)
        return ReconstructionResult(
            recon[0] if single else recon, None,
            timings={"total": time.perf_counter() - start},
        )  # fmt: skip


@dataclass(frozen=True)
class LearnedSpec:
    """Picklable recipe for a :class:`LearnedReconstructor` (a factory for the streaming
    and dask back ends, like :class:`~svcode_core.parallel.ReconstructorSpec`)."""

    method: str
    weights: str
    system: SystemConfig | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __call__(self) -> LearnedReconstructor:
        return LearnedReconstructor.from_weights(
            self.weights, self.system, self.method, **self.options
        )

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable description (recorded in outputs and resume state)."""
        return {"method": self.method, "weights": str(Path(self.weights).resolve()),
                **self.options}  # fmt: skip
