"""Does the physics fix the bundled model's outer ring? Its reconstruction refined by the
forward model, on the benchmark's scenes.

Three refinements start from SV-CoDe's reconstruction ``x₀`` and use the benchmark's
LSV-ADMM operator (``K`` = 3, the nominal instrument): LSV-ADMM warm-started at ``x₀``
(the TV-regularised problem; duals start at zero), conjugate gradients on the normal
equations ``AᵀA x = Aᵀy`` from ``x₀`` and projected Landweber steps
``x ← max(0, x − Aᵀ(Ax − y) / ‖A‖²)``; the last two stop early, which is their only
regularisation. Per regime (matched, realistic) and refinement, scene means of the PSNR,
the benchmark's centre and ring zones, and the 16-px edge strips against the columns
inside them. Unlike ``bench/ring_gap.py`` each scene is imaged in place only, so centre
and ring hold different content; the question is what a refinement gains and loses.

Usage (from the repository root):
``PYTHONPATH=bench python training/cm2-mini-v3/refine_probe.py``; about 10 minutes on one
thread. Writes ``refine-probe.md`` beside this file.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from svcode_bench.regimes import ADMM_RANK, SCENES, regime_simulator, scene_object
from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import edge_columns, image_quality, psnr
from svcode_core.methods.build import build_reconstructor
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.psf_io import model_psfs
from svcode_core.physics.simulate import Simulator
from svcode_core.pretrained import require_bundled_weights
from svcode_core.training.loss import EDGE_STRIP

REGIMES = ("matched", "realistic")
ADMM_STEPS = (5, 10, 20)
CG_STEPS = (1, 2, 3, 5, 10)
LANDWEBER_STEPS = (3, 10, 30)
COLUMNS = ("psnr", "centre", "ring", "strips", "inside")
OUT = Path(__file__).with_name("refine-probe.md")


def conjugate_gradients(operator: CM2Operator, x0: torch.Tensor, y: torch.Tensor,
                        steps: int) -> dict[int, torch.Tensor]:
    """CG on ``AᵀA x = Aᵀy`` from ``x0``; the iterate after each step, clipped at zero."""
    x = x0.clone()
    residual = operator.adjoint(y - operator.forward(x))
    direction, energy = residual.clone(), float((residual * residual).sum())
    iterates = {}
    for step in range(1, steps + 1):
        normal = operator.adjoint(operator.forward(direction))
        alpha = energy / float((direction * normal).sum())
        x = x + alpha * direction
        residual = residual - alpha * normal
        previous, energy = energy, float((residual * residual).sum())
        direction = residual + (energy / previous) * direction
        iterates[step] = x.clamp(min=0)
    return iterates


def landweber(operator: CM2Operator, x0: torch.Tensor, y: torch.Tensor, steps: int,
              lipschitz: float) -> dict[int, torch.Tensor]:
    """Projected gradient steps of ``½‖Ax − y‖²`` at step ``1 / lipschitz``."""
    x, iterates = x0.clone(), {}
    for step in range(1, steps + 1):
        x = (x - operator.adjoint(operator.forward(x) - y) / lipschitz).clamp(min=0)
        iterates[step] = x
    return iterates


def scores(truth: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """PSNR over the field, its centre and ring zones, the edge strips and inside them."""
    strips = edge_columns(len(truth), EDGE_STRIP)
    quality = image_quality(truth, estimate, data_range=1.0)
    return {"psnr": quality["psnr"], "centre": quality["psnr_centre"],
            "ring": quality["psnr_ring"], "strips": psnr(truth, estimate, 1.0, strips),
            "inside": psnr(truth, estimate, 1.0, ~strips)}


def refinements(system: SystemConfig) -> Callable[[np.ndarray], dict[str, np.ndarray]]:
    """A function from a raw frame to SV-CoDe's reconstruction and every refinement."""
    svcode = build_reconstructor("svcode", system, require_bundled_weights(system))
    admm = build_reconstructor("admm", system, rank=ADMM_RANK)
    solver = admm.solver
    operator, lipschitz = solver.operator, solver.weights[2]  # c₃ = ‖A‖²

    def run(raw: np.ndarray) -> dict[str, np.ndarray]:
        start = np.asarray(svcode.reconstruct(raw).reconstruction, dtype=np.float64)
        y = solver._frame(admm._padded(raw, 0))
        x0 = torch.as_tensor(start, dtype=y.dtype)
        found = {"SV-CoDe": x0}
        found |= {f"LSV-ADMM from it, {n} it": solver.solve(y, x0, n, tolerance=0.0).x
                  for n in ADMM_STEPS}
        cg = conjugate_gradients(operator, x0, y, max(CG_STEPS))
        found |= {f"CG from it, {n} steps": cg[n] for n in CG_STEPS}
        steps = landweber(operator, x0, y, max(LANDWEBER_STEPS), lipschitz)
        found |= {f"Landweber from it, {n} steps": steps[n] for n in LANDWEBER_STEPS}
        return {label: x.double().numpy() for label, x in found.items()}

    return run


def main() -> None:
    system = SystemConfig.preset("cm2-mini")
    nominal = Simulator(system, CM2Operator.from_psfs(system, model_psfs(system)))
    run = refinements(system)
    lines = ["# SV-CoDe's reconstruction refined by the forward model", "",
             "Made by `refine_probe.py` (its docstring says how). Scene means over the "
             f"benchmark's {len(SCENES)} scenes, dB; *strips*: the {EDGE_STRIP}-px edge "
             "columns, *inside*: the rest.", "",
             "| regime | reconstruction | " + " | ".join(COLUMNS) + " | centre − ring |",
             "|---" * (len(COLUMNS) + 3) + "|"]
    for regime in REGIMES:
        simulator = regime_simulator(system, regime, nominal)
        table: dict[str, list[dict[str, float]]] = {}
        for index, (name, kind, params) in enumerate(SCENES):
            truth = scene_object(kind, system.sub_view_size, index, params)
            raw = simulator.simulate(truth, seed=100 + index).measurement  # the benchmark's
            for label, estimate in run(raw).items():
                table.setdefault(label, []).append(scores(truth, estimate))
            print(f"[{regime}] {name}", flush=True)
        for label, rows in table.items():
            mean = {key: float(np.mean([row[key] for row in rows])) for key in COLUMNS}
            cells = " | ".join(f"{mean[key]:.2f}" for key in COLUMNS)
            lines.append(f"| {regime} | {label} | {cells} | {mean['centre'] - mean['ring']:.2f} |")
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
