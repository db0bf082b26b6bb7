"""How much harder are the strips for the best linear estimator?

The linear minimum-mean-square-error reconstruction with the whole forward model (the
nominal instrument, the matched regime) and an oracle Gaussian prior: each scene's own
mean and power spectrum (its periodogram, smoothed over 3 × 3 frequencies). With ``C``
that prior's covariance (diagonal in Fourier) and ``σ²`` the frame's noise variance
(measured from a second noise draw), the estimate is ``x̂ = m + C^½ z`` with
``(C^½ AᵀA C^½ / σ² + I) z = C^½ Aᵀ(y − A m) / σ²``, solved by conjugate gradients from 0.
Scored as ``bench/ring_gap.py`` scores a method: the same-content gap of the whole outer
ring and of the 16-px column strips, with the strips' two ends.

Usage (from the repository root; about 5 minutes a scene on one thread at 60 steps)::

    python training/cm2-mini-v5/linear_probe.py --out runs/linear.json [--scenes cells ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import uniform_filter

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from probes import plan_truths  # noqa: E402

from svcode_bench.field_position import (  # noqa: E402
    edge_strip_width,
    half_field_shifts,
    moved_scene,
    same_content_zones,
)
from svcode_core.config import load_system  # noqa: E402
from svcode_core.evaluation.metrics import edge_columns  # noqa: E402
from svcode_core.physics.cm2 import CM2Operator  # noqa: E402
from svcode_core.physics.geometry import pad_sensor_frame  # noqa: E402
from svcode_core.physics.simulate import Simulator  # noqa: E402


def linear_estimate(operator: CM2Operator, simulator: Simulator, scene: np.ndarray,
                    spectrum: np.ndarray, seed: int, steps: int) -> np.ndarray:  # fmt: skip
    """The oracle-prior LMMSE reconstruction of ``scene`` read with noise ``seed``."""
    system = operator.system
    raw = simulator.simulate(scene, seed=seed).measurement
    variance = float(np.var(raw - simulator.simulate(scene, seed=seed + 1000).measurement) / 2)
    mean = float(scene.mean())
    root = torch.as_tensor(np.sqrt(spectrum), dtype=torch.complex64)

    def c_half(v: torch.Tensor) -> torch.Tensor:
        return torch.fft.ifft2(torch.fft.fft2(v) * root).real

    def normal(z: torch.Tensor) -> torch.Tensor:
        return c_half(operator.adjoint(operator.forward(c_half(z)))) / variance + z

    y = pad_sensor_frame(torch.as_tensor(raw, dtype=torch.float32), system)
    y = y - operator.forward(torch.full(scene.shape, mean))
    rhs = c_half(operator.adjoint(y)) / variance
    z, r = torch.zeros_like(rhs), rhs.clone()
    p, rs = r.clone(), (r * r).sum()
    for _ in range(steps):
        ap = normal(p)
        alpha = rs / (p * ap).sum()
        z, r = z + alpha * p, r - alpha * ap
        new = (r * r).sum()
        p, rs = r + new / rs * p, new
    return (c_half(z) + mean).numpy().astype(np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="*", help="default: the benchmark's")
    parser.add_argument("--steps", type=int, default=60, help="conjugate-gradient steps")
    parser.add_argument("--out", type=Path, default=Path("runs/linear.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = load_system("cm2-mini")
    simulator = Simulator(system)
    operator = CM2Operator.from_system(system)
    strips = edge_columns(system.sub_view_size, edge_strip_width(system))
    rows = {}
    for name, (index, truth) in plan_truths(system).items():
        if args.scenes and name not in args.scenes:
            continue
        begin = time.perf_counter()
        spectrum = uniform_filter(np.abs(np.fft.fft2(truth - truth.mean())) ** 2 / truth.size,
                                  3, mode="wrap") + 1e-12  # fmt: skip

        def estimate(scene, truth=truth, index=index, spectrum=spectrum):
            return linear_estimate(operator, simulator, scene, spectrum, 100 + index, args.steps)

        shifts = half_field_shifts(len(truth))
        still = estimate(truth)
        moved = {shift: estimate(moved_scene(truth, shift)) for shift in shifts}
        ring = same_content_zones(truth, still, moved)
        in_strips = same_content_zones(truth, still, {shifts[1]: moved[shifts[1]]}, ring=strips)
        rows[name] = {"same_gap": ring.gap, "same_gap_column_strips": in_strips.gap,
                      "strips_content_centre": in_strips.centre,
                      "strips_content_strips": in_strips.ring,
                      "seconds": time.perf_counter() - begin}  # fmt: skip
        print(name, {k: round(v, 2) for k, v in rows[name].items()}, flush=True)
        args.out.write_text(json.dumps({"steps": args.steps, "scenes": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
