"""The stability battery of a reconstructor: extreme frames, and what came out of them.

:func:`stability_cases` builds the frames (zero, constant, saturated, a single-pixel
object, a 1e4 dynamic range, few photons, bf16 and fp16 arithmetic) for a system;
:func:`run_case` reconstructs one and reports figures: whether the output is finite, its
range, the PSNR against the ground truth where there is one, or the error raised. A case
passes when its output is finite or it raised a clear :class:`ValueError` (never NaN, Inf
or a crash). ``bench/stability.py`` runs it on the bundled model; ``tests/test_stability.py``
on a small random model.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from svcode_core.evaluation.metrics import psnr
from svcode_core.phantoms import make_object
from svcode_core.physics.noise import apply_sensor_noise
from svcode_core.physics.simulate import Simulator

__all__ = ["Case", "run_case", "stability_cases"]


@dataclass
class Case:
    """One frame of the battery.

    Attributes
    ----------
    name : str
    frame : numpy.ndarray
        Raw sensor frame.
    truth : numpy.ndarray or None
        The object it was simulated from, if any.
    precision : str
        Arithmetic of the reconstructor for this case.
    skip_empty : bool
        Whether tiles without signal are skipped.
    square : tuple of slice, optional
        The bright region of the dynamic-range case.
    point : tuple of int, optional
        The pixel of the single-pixel case.
    """

    name: str
    frame: np.ndarray
    truth: np.ndarray | None = None
    precision: str = "fp32"
    skip_empty: bool = True
    square: tuple[slice, slice] | None = None
    point: tuple[int, int] | None = None


def stability_cases(simulator: Simulator, seed: int = 0) -> list[Case]:
    """The battery for the system of ``simulator`` (noiseless unless the case is noise)."""
    system = simulator.system
    size, shape = system.sub_view_size, system.sensor_shape

    def measured(obj: np.ndarray, photons: float | None = None) -> np.ndarray:
        clean = simulator.simulate(obj, noise=False).measurement
        if photons is None:
            return clean
        generator = torch.Generator().manual_seed(seed)
        reading = apply_sensor_noise(torch.from_numpy(clean), system.noise, generator, photons)
        return reading.numpy()

    point = (size // 2 + size // 8, size // 2 - size // 5)
    single = np.zeros((size, size), np.float32)
    single[point] = 1.0
    side = max(size // 8, 2)
    square = (slice(size // 2 - side, size // 2), slice(size // 2 + side, size // 2 + 2 * side))
    ranged = np.full((size, size), 1e-4, np.float32)
    ranged[square] = 1.0
    scene = make_object("cells", size, seed)
    noisy = simulator.simulate(scene, seed=seed).measurement
    cases = [
        Case("zero frame", np.zeros(shape, np.float32)),
        Case("zero frame, every tile run", np.zeros(shape, np.float32), skip_empty=False),
        Case("constant frame 0.3", np.full(shape, 0.3, np.float32)),
        Case("saturated frame (1.0 everywhere)", np.ones(shape, np.float32)),
        Case("single-pixel object", measured(single), single, point=point),
        Case("dynamic range 1e4 (square 1 on 1e-4)", measured(ranged), ranged, square=square),
    ]
    for photons in (1.0, 10.0, 100.0):
        cases.append(Case(f"{photons:g} photon(s) at full scale", measured(scene, photons), scene))
    cases += [
        Case("cells, default noise, fp32", noisy, scene),
        Case("cells, default noise, bf16", noisy, scene, precision="bf16"),
        Case("cells, default noise, fp16", noisy, scene, precision="fp16"),
    ]
    return cases


def run_case(build: Callable[[str, bool], Any], case: Case) -> dict[str, Any]:
    """Reconstruct ``case`` with ``build(precision, skip_empty)``'s reconstructor.

    Returns
    -------
    dict
        ``name``, ``precision``, ``seconds``; then either ``error`` (the message of a
        :class:`ValueError`) or ``finite``, ``min``, ``max``, ``mean``, ``tiles_run`` and,
        where they apply, ``psnr`` (data range 1), ``peak_offset`` (pixels from the single
        pixel to the brightest output pixel), ``square_mean`` and ``floor_mean``.
    """
    row: dict[str, Any] = {"name": case.name, "precision": case.precision}
    start = time.perf_counter()
    try:
        result = build(case.precision, case.skip_empty).reconstruct(case.frame)
    except ValueError as err:
        row.update(error=str(err), seconds=time.perf_counter() - start)
        return row
    recon = np.asarray(result.reconstruction, dtype=np.float64)
    finite = bool(np.isfinite(recon).all())
    row.update(seconds=time.perf_counter() - start, finite=finite,
               tiles_run=int(result.tiles_run))  # fmt: skip
    if not finite:
        return row
    row.update(min=float(recon.min()), max=float(recon.max()), mean=float(recon.mean()))
    if case.truth is not None:
        row["psnr"] = float(psnr(case.truth, recon.astype(np.float32), 1.0))
    if case.point is not None:
        peak = np.unravel_index(int(np.argmax(recon)), recon.shape)
        row["peak_offset"] = float(np.hypot(peak[0] - case.point[0], peak[1] - case.point[1]))
    if case.square is not None:
        inside = np.zeros(recon.shape, bool)
        inside[case.square] = True
        row.update(square_mean=float(recon[inside].mean()), floor_mean=float(recon[~inside].mean()))
    return row
