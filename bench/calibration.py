"""Held-out check of ``svcode calibrate`` on ``cm2-mini`` with the ``calibration`` departures.

A 9×9 bead scan (and 8 dark frames) of the departed instrument is simulated with the
nominal camera plus a black level, calibrated, and the held-out scenes (the scikit-image
images no training ever sees) are reconstructed by LSV-ADMM (its ``cm2-mini`` settings,
the system's automatic rank) from one noisy frame of the same departed instrument, given

* the true instrument's operator (what made the frame),
* the calibrated system's operator (``CM2Operator.from_system`` of the calibrated system),
* the nominal preset's operator.

It also records the chief-ray error of the calibration against the departures and, for
chief-ray self-registration (:func:`svcode_core.physics.registration.register_frame`), the error of
the lens offsets (relative to the centre lens) it estimates from each held-out frame,
beside the error of assuming no drift.

Run: ``python bench/calibration.py [--scenes cell.png ...] [--iterations N]`` (writes
``bench/results/calibration.{json,md}``; default every held-out scene, the preset's
iterations).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import psnr
from svcode_core.methods.baselines import reconstruct_with_baseline
from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image
from svcode_core.physics.calibration import calibrate
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.departures import Departures
from svcode_core.physics.registration import register_frame
from svcode_core.physics.scan import scan_grid, simulate_scan, with_dark_offset
from svcode_core.physics.simulate import Simulator

RESULTS = Path(__file__).with_name("results")


def main() -> int:
    """Run the check and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=HELD_OUT_IMAGES, default=HELD_OUT_IMAGES)
    parser.add_argument("--iterations", type=int, help="LSV-ADMM iterations (default: preset)")
    args = parser.parse_args()
    options = {} if args.iterations is None else {"iterations": args.iterations}
    torch.set_num_threads(1)
    nominal = SystemConfig.preset("cm2-mini")
    departures = Departures.named("calibration", nominal)
    start = time.perf_counter()
    scanner = Simulator(with_dark_offset(nominal, 2e-3), departures=departures)
    positions = scan_grid(nominal, 9)
    frames, dark = simulate_scan(scanner, positions, seed=1)
    scanned = time.perf_counter()
    calibration = calibrate(frames, positions, nominal, dark=dark)
    calibrated = time.perf_counter()
    ray_error = np.abs(calibration.offsets - departures.lens_offsets(nominal))
    print(f"scan {scanned - start:.0f} s, calibration {calibrated - scanned:.0f} s, "
          f"chief-ray error max {ray_error.max():.3f} px", flush=True)
    instrument = Simulator(nominal, departures=departures)
    operators = {
        "true instrument": (instrument.instrument.truth, instrument.operator),
        "calibrated": (calibration.system, CM2Operator.from_psfs(calibration.system,
                                                                 calibration.psfs)),
        "nominal": (nominal, CM2Operator.from_system(nominal)),
    }
    true_offsets = departures.lens_offsets(nominal)
    relative = true_offsets - true_offsets[4]
    rows = []
    for name in args.scenes:
        obj = held_out_image(name, nominal.sub_view_size)
        frame = instrument.simulate(obj, seed=7).measurement
        registration = register_frame(frame, nominal, operators["nominal"][1])
        error = np.linalg.norm(registration.offsets - relative, axis=1)
        row = {"scene": name, "registration_error_px": {
            "mean": float(error.mean()), "max": float(error.max()),
            "no_drift_mean": float(np.linalg.norm(relative, axis=1).mean())}}
        print(name, "registration", row["registration_error_px"], flush=True)
        for label, (system, operator) in operators.items():
            recon = reconstruct_with_baseline("admm", frame, system, operator=operator,
                                              **options)  # fmt: skip
            row[label] = psnr(obj, recon, data_range=1.0)
            print(name, label, f"{row[label]:.2f} dB", flush=True)
        rows.append(row)
    mean = {label: float(np.mean([r[label] for r in rows])) for label in operators}
    result = {
        "system": nominal.name,
        "departures": departures.to_dict(),
        "scan_frames": len(positions),
        "admm_options": options,
        "chief_ray_error_px": ray_error.max(axis=1).tolist(),
        "chief_ray_error_max_px": float(ray_error.max()),
        "ranks": list(calibration.ranks),
        "psnr_db": rows,
        "mean_psnr_db": mean,
        "seconds": {"scan": scanned - start, "calibration": calibrated - scanned},
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "calibration.json").write_text(json.dumps(result, indent=2) + "\n")
    lines = [
        "# Calibration held-out check (cm2-mini, `calibration` departures)",
        "",
        f"Bead scan {len(positions)} frames; chief-ray error max "
        f"{ray_error.max():.3f} px; K per lens {list(calibration.ranks)}.",
        "",
        "| scene | " + " | ".join(operators) + " |",
        "| --- |" + " --- |" * len(operators),
    ]
    for row in rows:
        lines.append(f"| {row['scene']} | "
                     + " | ".join(f"{row[k]:.2f}" for k in operators) + " |")
    lines.append("| mean | " + " | ".join(f"{mean[k]:.2f}" for k in operators) + " |")
    lines += ["", "Self-registration from the same frames: lens offsets relative to the centre "
              "lens, error (px, Euclidean, mean / max over lenses) against assuming no drift:",
              "", "| scene | mean | max | no drift |", "| --- | --- | --- | --- |"]
    for row in rows:
        reg = row["registration_error_px"]
        lines.append(f"| {row['scene']} | {reg['mean']:.3f} | {reg['max']:.3f} | "
                     f"{reg['no_drift_mean']:.3f} |")
    lines.append("")
    lines.append("LSV-ADMM PSNR in dB against the object, one noisy frame of the departed "
                 f"instrument per scene, options {options or 'of the preset'}; generated by "
                 "`python bench/calibration.py " + " ".join(sys.argv[1:]) + "`.")
    (RESULTS / "calibration.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
