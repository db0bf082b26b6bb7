"""How many LSV-ADMM iterations, and blended in where, refine the bundled model's periphery?

Chosen on validation phantoms of the training distribution (the first 16 validation
objects of ``runs/data-v2``), never on the benchmark's scenes: each object is imaged by
the nominal instrument (``matched``) and by the ``realistic`` one with a fresh noise seed,
reconstructed by the bundled model (``x₀``) and refined by LSV-ADMM warm-started at
``x₀`` for 5, 10 and 20 iterations (``K`` = 3, the system's settings, no early stop:
:class:`~svcode_core.methods.periphery.PeripheryRefinement`'s solver). Two readings:

* per ring of normalised field radius ``ρ`` (0.1 wide), the blend weight ``w`` of the
  refined estimate that minimises the squared error of ``w x_n + (1 − w) x₀`` over the
  frames (least squares: ``w = Σ (t − x₀)(x_n − x₀) / Σ (x_n − x₀)²``);
* linear ramps of ``w`` from 0 at ``ρ = a`` to 1 at ``ρ = b`` (``a`` 0–1, ``b`` up to
  1.4, steps of 0.1) ranked by the PSNR gain over ``x₀``, averaged over both regimes.

Usage (from the repository root, after ``svcode dataset`` made ``runs/data-v2``):
``OMP_NUM_THREADS=1 PYTHONPATH=bench python training/cm2-mini-v3/periphery_blend.py``;
about 8 minutes on one thread, the reconstructions kept in ``runs/periphery-blend`` for a
rerun. Writes ``periphery-blend.md`` beside this file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from svcode_bench.regimes import regime_simulator
from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import field_zones, psnr
from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.periphery import REFINE_RANK, periphery_weight
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import field_radius
from svcode_core.physics.psf_io import model_psfs
from svcode_core.physics.simulate import Simulator
from svcode_core.pretrained import require_bundled_weights
from svcode_core.training.dataset import TrainingData

REGIMES = ("matched", "realistic")
ITERATIONS = (5, 10, 20)
FRAMES = 16
CACHE = Path("runs/periphery-blend")
OUT = Path(__file__).with_name("periphery-blend.md")
RING_WIDTH = 0.1


def reconstructions(data: TrainingData, system: SystemConfig) -> dict[str, list[dict]]:
    """Per regime, per frame: truth, ``x0`` and ``x{n}`` (cached in :data:`CACHE`)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    nominal = Simulator(system, CM2Operator.from_psfs(system, model_psfs(system)))
    network = build_reconstructor("svcode", system, require_bundled_weights(system))
    admm = {n: build_reconstructor("admm", system, rank=REFINE_RANK, iterations=n,
                                   tolerance=0.0) for n in ITERATIONS}  # fmt: skip
    found: dict[str, list[dict]] = {}
    for regime in REGIMES:
        simulator = regime_simulator(system, regime, nominal)
        for index in data.val_frames[:FRAMES]:
            path = CACHE / f"{regime}_{index}.npz"
            if not path.exists():
                truth = np.asarray(data.objects[index], dtype=np.float64)
                raw = simulator.simulate(truth, seed=5000 + index).measurement
                x0 = np.asarray(network.reconstruct(raw).reconstruction, dtype=np.float64)
                start = torch.as_tensor(x0, dtype=torch.float32)
                refined = {f"x{n}": solver.reconstruct_tensor(raw, start).double().numpy()
                           for n, solver in admm.items()}
                np.savez_compressed(path, truth=truth, x0=x0, **refined)
                print(f"[{regime}] frame {index}", flush=True)
            found.setdefault(regime, []).append(dict(np.load(path)))
    return found


def best_weight_per_ring(frames: list[dict], n: int, radius: np.ndarray) -> list[float]:
    """The least-squares blend weight of ``x{n}`` in each ring of the field radius."""
    weights = []
    for low in np.arange(0.0, radius.max(), RING_WIDTH):
        ring = (radius >= low) & (radius < low + RING_WIDTH)
        step = [(f[f"x{n}"] - f["x0"])[ring] for f in frames]
        miss = [(f["truth"] - f["x0"])[ring] for f in frames]
        weights.append(sum(float(a @ b) for a, b in zip(miss, step, strict=True))
                       / sum(float(a @ a) for a in step))  # fmt: skip
    return weights


def ramp_scores(frames: list[dict], n: int, ramp: tuple[float, float]) -> dict[str, float]:
    """Scene means of PSNR gain, centre and ring PSNR of the blend with ``ramp``."""
    size = frames[0]["truth"].shape[0]
    weight, zones = periphery_weight(size, ramp), field_zones(size)
    rows = []
    for f in frames:
        blend = weight * f[f"x{n}"] + (1 - weight) * f["x0"]
        rows.append((psnr(f["truth"], blend, 1.0) - psnr(f["truth"], f["x0"], 1.0),
                     psnr(f["truth"], blend, 1.0, zones["centre"]),
                     psnr(f["truth"], blend, 1.0, zones["ring"])))  # fmt: skip
    gain, centre, ring = np.mean(rows, axis=0)
    return {"gain": gain, "centre": centre, "ring": ring}


def main() -> None:
    data = TrainingData("runs/data-v2")
    system = data.system
    found = reconstructions(data, system)
    size = system.sub_view_size
    zones = field_zones(size)
    radius = field_radius(size)
    lines = ["# The periphery refinement chosen on validation frames", "",
             f"Made by `periphery_blend.py` (its docstring says how): {FRAMES} validation "
             "objects of `runs/data-v2`, each regime. Scene means, dB.", "",
             "## The network alone", "", "| regime | PSNR | centre | ring |", "|---|---|---|---|"]
    for regime, frames in found.items():
        scores = np.mean([(psnr(f["truth"], f["x0"], 1.0),
                           psnr(f["truth"], f["x0"], 1.0, zones["centre"]),
                           psnr(f["truth"], f["x0"], 1.0, zones["ring"]))
                          for f in frames], axis=0)  # fmt: skip
        lines.append(f"| {regime} | " + " | ".join(f"{v:.2f}" for v in scores) + " |")
    rings = np.arange(0.0, radius.max(), RING_WIDTH)
    lines += ["", "## The best blend weight of the refined estimate per ring of field radius",
              "", "| iterations | regime | " + " | ".join(f"{r:.1f}" for r in rings) + " |",
              "|---" * (len(rings) + 2) + "|"]
    for n in ITERATIONS:
        for regime, frames in found.items():
            weights = best_weight_per_ring(frames, n, radius)
            lines.append(f"| {n} | {regime} | " + " | ".join(f"{w:.2f}" for w in weights) + " |")
    ranked = []
    for n in ITERATIONS:
        for low in np.arange(0.0, 1.01, 0.1):
            for high in np.arange(low + 0.1, 1.41, 0.1):
                scores = {r: ramp_scores(frames, n, (low, high)) for r, frames in found.items()}
                mean = float(np.mean([s["gain"] for s in scores.values()]))
                ranked.append((mean, n, round(low, 1), round(high, 1), scores))
    ranked.sort(key=lambda entry: -entry[0])
    lines += ["", "## Linear ramps, the best ten (gain over the network alone)", "",
              "| iterations | ramp | mean gain | " + " | ".join(
                  f"{r}: gain / centre / ring" for r in found) + " |",
              "|---" * (3 + len(found)) + "|"]
    for mean, n, low, high, scores in ranked[:10]:
        cells = " | ".join(f"{s['gain']:+.2f} / {s['centre']:.2f} / {s['ring']:.2f}"
                           for s in scores.values())  # fmt: skip
        lines.append(f"| {n} | {low}–{high} | {mean:+.3f} | {cells} |")
    lines += ["", "The best ramp for each iteration count:", ""]
    for n in ITERATIONS:
        mean, _, low, high, _ = next(entry for entry in ranked if entry[1] == n)
        lines.append(f"- {n} iterations: {low}–{high}, mean gain {mean:+.3f} dB")
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
