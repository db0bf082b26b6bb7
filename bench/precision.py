"""bf16 against fp32 for one SV-CoDe model file on the held-out benchmark
(bench/results/precision.md).

Every benchmark scene of every regime (the benchmark's truths, departures and noise seeds)
is reconstructed by the same model file in fp32 and in bf16, with the command's other
defaults; PSNR and SSIM against the truth, seconds a frame (a ratio within this run: the
two precisions alternate scene by scene). The model's *bf16 loss* is the largest drop of a
regime's mean PSNR. ``--record`` writes it into the model file (``precision_check`` in its
metadata), which is what ``--precision auto`` (the default) reads: bf16 is then chosen on
processors and GPUs with bf16 units when the loss is at most 0.05 dB.

Run: ``OMP_NUM_THREADS=1 python bench/precision.py [--weights FILE] [--record]`` (the
bundled cm2-mini model: about 3 minutes on one thread).
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
import torch
from probes import add_check_arguments, add_scene_arguments, planned_scenes, write_report

from svcode_bench.regimes import make_scenes, regime_simulator
from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import psnr, ssim
from svcode_core.methods.base import native_bf16
from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.model_file import read_model_metadata, record_extra
from svcode_core.pretrained import require_bundled_weights

PRECISIONS = ("fp32", "bf16")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--weights", type=Path, help="model file (default: the bundled one)")
    parser.add_argument("--system", default="cm2-mini", help="preset (default cm2-mini)")
    add_scene_arguments(parser)
    add_check_arguments(parser, "the bf16 loss", "precision")
    args = parser.parse_args()
    system = SystemConfig.preset(args.system)
    regimes, scene_names = planned_scenes(args, system)
    weights = args.weights or require_bundled_weights(system)
    read_model_metadata(weights)  # a model file, or a clear error before any work
    if not native_bf16(torch.device("cpu")):
        print("note: this processor has no bf16 units: bf16 is emulated (slow); the PSNR "
              "figures still hold")
    reconstructors = {p: build_reconstructor("svcode", system, weights, precision=p)
                      for p in PRECISIONS}
    rows = []
    for regime in regimes:
        scenes = make_scenes(system, scene_names, regime_simulator(system, regime))
        per_scene = {p: {} for p in PRECISIONS}
        seconds = dict.fromkeys(PRECISIONS, 0.0)
        for scene in scenes:
            for precision, reconstructor in reconstructors.items():
                begin = time.perf_counter()
                estimate = reconstructor.reconstruct(scene.raw).reconstruction
                seconds[precision] += time.perf_counter() - begin
                per_scene[precision][scene.name] = {
                    "psnr": psnr(scene.truth, estimate, 1.0),
                    "ssim": ssim(scene.truth, estimate, 1.0)}
        for precision in PRECISIONS:
            values = per_scene[precision].values()
            rows.append({"regime": regime, "precision": precision,
                         "psnr": float(np.mean([v["psnr"] for v in values])),
                         "ssim": float(np.mean([v["ssim"] for v in values])),
                         "seconds": seconds[precision] / len(scenes),
                         "per_scene": per_scene[precision]})
        print(f"{regime}: fp32 {rows[-2]['psnr']:.3f} dB, bf16 {rows[-1]['psnr']:.3f} dB, "
              f"{rows[-2]['seconds']:.2f} / {rows[-1]['seconds']:.2f} s a frame", flush=True)
    check = bf16_check(rows)
    write_report(rows, args.out, lambda report, path: write_markdown(report, path, weights,
                                                                     system, check))
    print(f"bf16 loss: {check['loss_db']:.3f} dB (worst scene {check['worst_scene_db']:.3f})")
    if args.record:
        record_extra(weights, precision_check={"bf16": check})
        print(f"recorded in {weights}")


def bf16_check(rows: list[dict]) -> dict:
    """The largest drop of a regime's mean PSNR from fp32 to bf16 (``loss_db``), the
    largest of a single scene, and what they were measured on."""
    pairs = [(a, b) for a, b in zip(rows[::2], rows[1::2], strict=True)]
    scenes = list(pairs[0][0]["per_scene"])
    return {
        "loss_db": round(max(a["psnr"] - b["psnr"] for a, b in pairs), 4),
        "worst_scene_db": round(max(a["per_scene"][s]["psnr"] - b["per_scene"][s]["psnr"]
                                    for a, b in pairs for s in scenes), 4),
        "regimes": [a["regime"] for a, _ in pairs],
        "scenes": scenes,
        "date": datetime.date.today().isoformat(),
    }


def write_markdown(report: dict, path: Path, weights: Path, system: SystemConfig,
                   check: dict) -> None:
    rows = report["rows"]
    lines = [
        "# bf16 against fp32 on the held-out benchmark", "",
        f"Generated by `bench/precision.py` ({system.name}, model `{weights.name}`, "
        f"{len(check['scenes'])} benchmark scenes a regime, {report['threads']} CPU "
        "thread(s)). Mean PSNR / SSIM against the truth; seconds a frame as a ratio within "
        "this run (the precisions alternate scene by scene). The bf16 loss (the largest drop "
        f"of a regime's mean): **{check['loss_db']:.3f} dB** (worst single scene "
        f"{check['worst_scene_db']:.3f} dB); `--precision auto` chooses bf16 where the "
        "processor has bf16 units when it is at most 0.05 dB.", "",
        "| regime | fp32 PSNR / SSIM | bf16 PSNR / SSIM | loss dB | fp32 s | bf16 s | speed |",
        "|---|---|---|---|---|---|---|"]
    for a, b in zip(rows[::2], rows[1::2], strict=True):
        lines.append(f"| {a['regime']} | {a['psnr']:.3f} / {a['ssim']:.4f} | {b['psnr']:.3f} "
                     f"/ {b['ssim']:.4f} | {a['psnr'] - b['psnr']:.3f} | {a['seconds']:.2f} "
                     f"| {b['seconds']:.2f} | {a['seconds'] / b['seconds']:.2f}× |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
