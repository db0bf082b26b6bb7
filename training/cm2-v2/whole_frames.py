"""Score cm2-v2 models on whole held-out frames, as the README's "Whole frames" table does.

Two frames the training data never held, each reconstructed given the nominal preset: a
dense cells scene through the nominal instrument (``--object cells --seed 7``) and
neurons through a realistically departed one (``--object neurons --seed 11 --departures
realistic``). Each model file (or ``admm``: LSV-ADMM, K = 3, 10 iterations) runs through
``svcode reconstruct`` as a whole process; its output is scored after a least-squares
gain and offset (PSNR and SSIM with the truth's range), with the seconds and peak memory
of the process.

Usage (from the repository root)::

    python training/cm2-v2/whole_frames.py runs/cm2-v2-long/best.safetensors admm \\
        [--out runs/whole-frames] [--precision bf16]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import tifffile

from svcode_core.evaluation.metrics import image_quality

SCENES = {
    "cells": ["--object", "cells", "--seed", "7"],
    "neurons": ["--object", "neurons", "--seed", "11", "--departures", "realistic"],
}


def gain_fitted(truth: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """PSNR and SSIM of ``a · estimate + b`` with ``a, b`` fitted by least squares."""
    design = np.stack([estimate.ravel(), np.ones(estimate.size)], axis=1)
    (gain, offset), *_ = np.linalg.lstsq(design, truth.ravel(), rcond=None)
    quality = image_quality(truth, gain * estimate + offset, float(truth.max() - truth.min()))
    return {"psnr": quality["psnr"], "ssim": quality["ssim"], "gain": float(gain)}


def run(command: list[str]) -> tuple[float, float]:
    """Wall seconds and peak resident GiB of a child process."""
    start = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(child.pid, 0)  # the child's own peak, not the largest so far
    code = os.waitstatus_to_exitcode(status)
    if code:
        raise SystemExit(f"failed ({code}): {' '.join(command)}")
    return time.perf_counter() - start, usage.ru_maxrss / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", help="model files, or admm")
    parser.add_argument("--out", type=Path, default=Path("runs/whole-frames"))
    parser.add_argument("--precision", default="auto",
                        help="for the model files (default: the command's, auto)")
    args = parser.parse_args()
    for scene, options in SCENES.items():
        folder = args.out / scene
        if not (folder / "object.tif").is_file():
            run(["svcode", "simulate", "--preset", "cm2-v2", *options, "--out", str(folder),
                 "--no-progress"])  # fmt: skip
        truth = tifffile.imread(folder / "object.tif").astype(np.float64)
        for model in args.models:
            name = "admm" if model == "admm" else Path(model).stem
            method = (["--method", "admm", "--rank", "3", "--iterations", "10"] if model == "admm"
                      else ["--weights", model, "--precision", args.precision])  # fmt: skip
            output = args.out / f"{scene}-{name}.tif"
            seconds, peak = run(["svcode", "reconstruct", str(folder / "measurement.tif"),
                                 "--system", "cm2-v2", *method, "--out", str(output),
                                 "--no-progress"])  # fmt: skip
            score = gain_fitted(truth, tifffile.imread(output).astype(np.float64))
            print(f"{scene:8s} {model}: PSNR {score['psnr']:.2f} dB, SSIM {score['ssim']:.3f} "
                  f"(gain {score['gain']:.3f}), {seconds:.1f} s, peak {peak:.2f} GiB", flush=True)


if __name__ == "__main__":
    main()
