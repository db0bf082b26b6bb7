"""The field's periphery of an SV-CoDe reconstruction refined by the forward model.

The network is weakest where fewer than nine lenses see the object: the outer ring and
above all the 16-px column strips at the field's left and right edges. The measurement
still determines those regions nearly as well as the centre (LSV-ADMM, which inverts the
whole sensor at once, is within 1 dB of its centre in its ring), but a few LSV-ADMM
iterations started from the network's reconstruction also pull the centre back towards
the model-based solver's weaker estimate. :class:`PeripheryRefinement` keeps both
strengths: it runs ``iterations`` LSV-ADMM iterations warm-started at the network's
reconstruction ``x₀`` (rank ``K`` = 3, the system's LSV-ADMM settings, no early stop)
and returns

    ``w(ρ) · x_refined + (1 − w(ρ)) · x₀``,

with ``w`` rising linearly with the normalised field radius ``ρ`` from 0 at
``ρ = 0.5`` to 1 at ``ρ = 1.1`` (:func:`periphery_weight`): the network's
reconstruction inside half the field radius, the refined one in the corners. The ramp and
:data:`REFINE_ITERATIONS` (10, the benchmark's refined row) were chosen on validation
frames of the bundled ``cm2-mini`` model's training distribution, not on the benchmark's
scenes (the model card has the figures).

Only the reconstruction is refined; the demixed views stay the network's.
"""

from __future__ import annotations

import numpy as np
import torch

from ..config import SystemConfig
from ..physics.geometry import field_radius
from .baselines import BaselineReconstructor, settings_for

__all__ = ["PERIPHERY_RAMP", "REFINE_ITERATIONS", "REFINE_RANK", "PeripheryRefinement",
           "periphery_weight"]

#: normalised field radii where the refined estimate's weight starts to rise and reaches 1
PERIPHERY_RAMP = (0.5, 1.1)
#: low-rank order ``K`` of the operator the refinement inverts
REFINE_RANK = 3
#: the iterations chosen with the ramp (the benchmark's refined row)
REFINE_ITERATIONS = 10


def periphery_weight(size: int, ramp: tuple[float, float] = PERIPHERY_RAMP) -> np.ndarray:
    """Weight ``(size, size)`` of the refined estimate: 0 up to field radius ``ramp[0]``,
    rising linearly to 1 at ``ramp[1]`` and beyond.

    Examples
    --------
    >>> w = periphery_weight(8)
    >>> float(w[3:5, 3:5].max()), float(w[0, 0])
    (0.0, 1.0)
    """
    low, high = ramp
    if not 0 <= low < high:
        raise ValueError(f"ramp must rise: 0 <= start < end, got {ramp!r}")
    return np.clip((field_radius(size) - low) / (high - low), 0.0, 1.0)


class PeripheryRefinement:
    """LSV-ADMM iterations from a reconstruction, blended in towards the field's edge.

    Parameters
    ----------
    system : SystemConfig
        The instrument (its PSF model gives the operator).
    iterations : int
        LSV-ADMM iterations (≥ 1).
    device : str
        Where the solver runs.

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> refine = PeripheryRefinement(tiny, iterations=2)
    >>> frame = np.full(tiny.sensor_shape, 0.1, dtype=np.float32)
    >>> start = np.full((48, 48), 0.2, dtype=np.float32)
    >>> out = refine(frame, start)
    >>> out.shape, out.dtype, bool(out[24, 24] == start[24, 24])
    ((48, 48), dtype('float32'), True)
    """

    def __init__(self, system: SystemConfig, iterations: int, device: str = "cpu") -> None:
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"refinement iterations must be a positive integer, "
                             f"got {iterations!r}")  # fmt: skip
        # the fixed λ the refinement was measured with (the method's default is the frame's)
        self.solver = BaselineReconstructor("admm", system, device=str(device),
                                            rank=REFINE_RANK, iterations=iterations,
                                            tolerance=0.0,
                                            tv_weight=settings_for(system).tv_weight)  # fmt: skip
        lenses = self.solver.operator.lenses
        weight = periphery_weight(system.sub_view_size)
        self.weight = torch.as_tensor(weight, dtype=lenses.dtype, device=lenses.device)

    def __call__(self, frame: np.ndarray, reconstruction: np.ndarray, index: int = 0) -> np.ndarray:
        """The raw ``frame`` ``(H, W)`` and its reconstruction ``(S, S)`` → the blend, float32."""
        lenses = self.solver.operator.lenses
        start = torch.as_tensor(np.asarray(reconstruction), dtype=lenses.dtype,
                                device=lenses.device)  # fmt: skip
        refined = self.solver.reconstruct_tensor(frame, start, index)
        blend = self.weight * refined + (1.0 - self.weight) * start
        return blend.to("cpu", torch.float32).numpy()
