"""LSV-ADMM's TV weight against the noise level (bench/results/admm_tv_weight.md).

How :data:`~svcode_core.methods.baselines.admm.AUTO_TV_GAIN` was chosen, on validation
objects of the training data (``runs/data-v2``, validation objects 20–27), never on the
benchmark's scenes: each object is imaged by the nominal instrument (``matched``), at 200
photons a pixel (``low-light``) and by the ``realistic`` instrument, with fresh noise
seeds, and reconstructed by LSV-ADMM (``K`` = 3, 50 iterations, no early stop) with
``λ`` ∈ {1e-4, 1e-3, 3e-3, 1e-2}. Reported per regime: the mean PSNR for each ``λ``, the
frames' noise gain ``σ̂² / m`` (their estimated noise variance over their mean) and, per
frame, the best ``λ`` over ``σ̂² / m``: the ``γ`` that :func:`auto_tv_weight` would need
to hit it.

Run from the repository root after ``svcode dataset`` made ``runs/data-v2``:
``OMP_NUM_THREADS=1 python bench/admm_tv_weight.py`` (about 25 minutes on one thread;
resumable, the runs kept in ``runs/tv-noise/results.jsonl``).
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from svcode_bench.regimes import regime_simulator
from svcode_core.evaluation.metrics import psnr
from svcode_core.methods.build import build_reconstructor
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.noise import estimate_noise_std
from svcode_core.physics.psf_io import model_psfs
from svcode_core.physics.simulate import Simulator
from svcode_core.training.dataset import TrainingData

REGIMES = ("low-light", "matched", "realistic")
WEIGHTS = (1e-4, 1e-3, 3e-3, 1e-2)
ITERATIONS = 50
OBJECTS = slice(20, 28)
RUNS = Path("runs/tv-noise/results.jsonl")
OUT = Path(__file__).parent / "results" / "admm_tv_weight.md"


def measure() -> list[dict]:
    """Every (regime, object, λ) run, appended to :data:`RUNS` as it ends."""
    data = TrainingData("runs/data-v2")
    system = data.system
    done = [json.loads(line) for line in RUNS.read_text().splitlines()] if RUNS.exists() else []
    have = {(r["regime"], r["index"], r["tv"]) for r in done}
    nominal = Simulator(system, CM2Operator.from_psfs(system, model_psfs(system)))
    solvers = {w: build_reconstructor("admm", system, rank=3, iterations=ITERATIONS,
                                      tolerance=0.0, tv_weight=w) for w in WEIGHTS}  # fmt: skip
    RUNS.parent.mkdir(parents=True, exist_ok=True)
    for regime in REGIMES:
        simulator = regime_simulator(system, regime, nominal)
        for index in data.val_frames[OBJECTS]:
            truth = np.asarray(data.objects[index], dtype=np.float64)
            raw = np.asarray(simulator.simulate(truth, seed=7000 + int(index)).measurement,
                             dtype=np.float64)  # fmt: skip
            for weight, solver in solvers.items():
                if (regime, int(index), weight) in have:
                    continue
                start = time.perf_counter()
                estimate = solver.reconstruct(raw).reconstruction.astype(np.float64)
                row = {"regime": regime, "index": int(index), "tv": weight,
                       "sigma": estimate_noise_std(raw), "mean": float(raw.mean()),
                       "psnr": psnr(truth, estimate, 1.0),
                       "seconds": time.perf_counter() - start}  # fmt: skip
                with RUNS.open("a") as file:
                    file.write(json.dumps(row) + "\n")
                done.append(row)
                print(row, flush=True)
    return done


def main() -> None:
    runs = measure()
    frames: dict[tuple[str, int], dict[float, float]] = defaultdict(dict)
    gain: dict[tuple[str, int], float] = {}
    for r in runs:
        frames[(r["regime"], r["index"])][r["tv"]] = r["psnr"]
        gain[(r["regime"], r["index"])] = r["sigma"] ** 2 / r["mean"]
    lines = ["# LSV-ADMM's TV weight against the noise level", "",
             "Made by `bench/admm_tv_weight.py` (its docstring says how): "
             f"{OBJECTS.stop - OBJECTS.start} validation objects of the training data, "
             f"LSV-ADMM K = 3, {ITERATIONS} iterations. Mean PSNR (dB) per λ; the frames' "
             "noise gain σ̂²/m (median); per frame the best λ of the four over σ̂²/m "
             "(median and range).", "",
             "| regime | " + " | ".join(f"λ = {w:g}" for w in WEIGHTS)
             + " | σ̂²/m | best λ / (σ̂²/m) |", "|---" * (len(WEIGHTS) + 3) + "|"]
    for regime in REGIMES:
        keys = [k for k in frames if k[0] == regime]
        means = [np.mean([frames[k][w] for k in keys]) for w in WEIGHTS]
        ratios = [max(frames[k], key=frames[k].get) / gain[k] for k in keys]
        lines.append(f"| {regime} | " + " | ".join(f"{m:.2f}" for m in means)
                     + f" | {np.median([gain[k] for k in keys]):.1e} | {np.median(ratios):.1f}"
                     f" ({min(ratios):.1f}–{max(ratios):.1f}) |")
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
