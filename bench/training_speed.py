"""Training throughput on a CPU: a step in float32 and bf16, eager and compiled, and the
learning curve of one epoch in each setting that is offered.

Steps: the bundled cm2-mini network, batch 8 × 96² at one shared origin (as
``--same-origin 8`` draws them), forward, loss, backward, Adam; one thread; each setting
in a fresh process (the compiled ones after their compilation, whose time is reported:
with an empty compiler cache and with a warm one); the median of five steps.
Learning curves: ``--runs A B ...`` names run folders of ``svcode train`` that differ only
in ``--precision`` / ``--compile``, run side by side (one thread each), and quotes their
first epochs from ``log.csv``.

Another network: ``--weights FILE --patch P --batch B`` (steps only), e.g. the cm2-v2
arm's on one 384-px patch; its results are named after the file's system.

Results go to bench/results/training_speed[_SYSTEM].json and .md.
Run: ``python bench/training_speed.py [--runs runs/p43-fp32 runs/p43-bf16c]`` (quiet).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from svcode_core.methods.model_file import read_model_metadata
from svcode_core.network.compiled import compile_model
from svcode_core.run.allocator import reuse_freed_memory

RESULTS = Path(__file__).parent / "results"
SETTINGS = (("fp32", False), ("bf16", False), ("fp32", True), ("bf16", True))


def gradient_error(precision: str, workload: dict) -> float:
    """Relative L2 difference between the compiled and the eager gradients of one step
    (same weights, same patches); NaN when the compiled ones are not finite."""
    from network_parts import training_batch

    model, loss = training_batch(**workload)

    def gradients(net: torch.nn.Module) -> torch.Tensor:
        model.zero_grad(set_to_none=True)
        loss(net, precision).backward()
        return torch.cat([p.grad.flatten() for p in model.parameters()])

    eager = gradients(model)
    compiled = gradients(compile_model(model, precision == "bf16"))
    if not torch.isfinite(compiled).all():
        return math.nan
    return float((compiled - eager).norm() / eager.norm())


def measure(precision: str, compiled: bool, workload: dict, steps: int = 5) -> dict:
    """Seconds per step in this process (median of ``steps`` after the first); compiled,
    also the gradients' difference from eager (:func:`gradient_error`)."""
    from network_parts import train_workload

    torch.set_num_threads(1)
    reuse_freed_memory()
    error = gradient_error(precision, workload) if compiled else 0.0
    step = train_workload(precision, compiled, **workload)
    times = []
    for _ in range(steps + 1):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return {"precision": precision, "compile": compiled, "first_s": times[0],
            "step_s": statistics.median(times[1:]), "gradient_error": error}


def epochs(run: Path) -> list[dict]:
    """The rows of a run's log.csv, as numbers."""
    with open(run / "log.csv") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", nargs="*", type=Path, default=[])
    parser.add_argument("--weights", help="model file (default: the bundled cm2-mini)")
    parser.add_argument("--patch", type=int, default=96)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    workload = {"weights": args.weights, "patch": args.patch, "batch": args.batch}
    if args.one:
        print(json.dumps(measure(args.one[0], args.one[1] == "compile", workload)))
        return
    passed = ["--patch", str(args.patch), "--batch", str(args.batch)]
    if args.weights:
        passed += ["--weights", args.weights]
    rows = []
    for precision, compiled in SETTINGS:
        out = subprocess.run([sys.executable, __file__, "--one", precision,
                              "compile" if compiled else "eager", *passed],
                             check=True, capture_output=True, text=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(rows[-1], flush=True)
    curves = {}
    for run in args.runs:
        config = json.loads((run / "log.json").read_text())["train_config"]
        curves[run.name] = {"precision": config.get("precision", "auto"),
                            "compile": config.get("compile", False), "epochs": epochs(run)}
    name = "training_speed"
    if args.weights:
        name += "_" + read_model_metadata(args.weights)["system"].name
        what = f"`{args.weights}`'s network"
    else:
        what = "the bundled cm2-mini network"
    RESULTS.mkdir(exist_ok=True)
    report = {"steps": rows, "curves": curves, "network": what, **workload}
    (RESULTS / f"{name}.json").write_text(json.dumps(report, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(markdown(report))
    print((RESULTS / f"{name}.md").read_text())


def markdown(report: dict) -> str:
    base = report["steps"][0]["step_s"]
    lines = [
        "# Training throughput on a CPU",
        "",
        f"Generated by `bench/training_speed.py`: one training step of "
        f"{report.get('network', 'the bundled cm2-mini network')} "
        f"({report.get('batch', 8)} × {report.get('patch', 96)}² patches at one origin, "
        "forward, loss, backward, Adam), one thread, each setting in a fresh process; "
        "*first step* includes compiling (after the gradient check, so from a warm "
        "cache); *gradients*: the compiled step's relative L2 difference from eager on the "
        "same patches (NaN: not finite).",
        "",
        "| precision | compiled | first step s | step s | speed vs fp32 eager | gradients |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["steps"]:
        error = r.get("gradient_error")
        lines.append(f"| {r['precision']} | {'yes' if r['compile'] else 'no'} | "
                     f"{r['first_s']:.1f} | {r['step_s']:.3f} | {base / r['step_s']:.2f}× | "
                     f"{'–' if not r['compile'] or error is None else f'{error:.1e}'} |")
    if report["curves"]:
        lines += [
            "",
            "Learning curves: the same run (the v4 recipe: the bundled model fine-tuned on "
            "the v2 data, 3,200 patches an epoch, seed 12) in each setting, side by side on "
            "one thread each; validation on the same 128 patches.",
            "",
            "| run | precision | compiled | epoch | train loss | val recon PSNR | val recon "
            "SSIM | wall s | CPU s |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for name, curve in report["curves"].items():
            for e in curve["epochs"]:
                lines.append(
                    f"| {name} | {curve['precision']} | {'yes' if curve['compile'] else 'no'} "
                    f"| {e['epoch']:.0f} | {e['train_loss']:.3f} | {e['val_recon_psnr']:.2f} "
                    f"| {e['val_recon_ssim']:.4f} | {e['seconds']:.0f} | {e['cpu_seconds']:.0f} |"
                )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
