"""Held-out check of ``svcode calibrate`` and of self-registration on ``cm2-mini``.

The instrument has drifted from the nominal preset (:data:`DRIFT` by default: the
microlens array moved by about a pixel and turned by 0.2°, each lens off by up to half a
pixel more; or a named set of :mod:`svcode_core.physics.departures`). A 9×9 bead scan of it is
simulated the way a lab records one (source bright enough to reach about 75 % of full
scale, ``--repeats`` frames averaged per position by the fit, 8 dark frames, the nominal
camera plus a black level), calibrated, and the held-out scenes (the scikit-image images
no training ever sees) are reconstructed by LSV-ADMM from one noisy frame of the same
instrument, given

* the true instrument's operator (what made the frame),
* the calibrated system's operator,
* the nominal preset's operator,
* the nominal preset moved by chief-ray self-registration of that frame
  (:func:`svcode_core.methods.baselines.self_registration.self_register`).

It also records the chief-ray error of the calibration and the error of the
self-registered lens offsets (relative to the centre lens), beside assuming no drift.

Run: ``python bench/calibration.py [--scenes cell.png ...] [--iterations N]`` (writes
``bench/results/calibration.{json,md}``).
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
from svcode_core.methods.baselines.self_registration import MAX_LENS_RESIDUAL_PX, self_register
from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image
from svcode_core.physics.calibration import Calibration, calibrate
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.departures import Departures
from svcode_core.physics.scan import scan_grid, simulate_scan, with_dark_offset
from svcode_core.physics.simulate import Simulator

RESULTS = Path(__file__).with_name("results")
#: the drift checked by default: array shift and turn plus per-lens jitter
DRIFT = Departures(name="drift", mla_shift_px=(1.0, -0.6), mla_rotation_deg=0.2,
                   lens_jitter_px=0.5, seed=14)
#: the scanning camera's black level (above zero, so a dark frame removes it unbiased)
DARK_OFFSET = 2e-3


def scanner_for(nominal: SystemConfig, departures: Departures) -> Simulator:
    """The departed instrument as it records a bead scan (the camera with a black level)."""
    return Simulator(with_dark_offset(nominal, DARK_OFFSET), departures=departures)


def scan_positions(nominal: SystemConfig, steps: int = 9, repeats: int = 4) -> np.ndarray:
    """A ``steps × steps`` raster, each position ``repeats`` times in a row."""
    return np.repeat(scan_grid(nominal, steps), repeats, axis=0)


def chief_ray_error(calibration: Calibration, departures: Departures,
                    nominal: SystemConfig) -> np.ndarray:  # fmt: skip
    """``(9, 2)`` absolute error of the calibrated lens offsets, pixels per axis."""
    return np.abs(calibration.offsets - departures.lens_offsets(nominal))


def held_out_operators(nominal: SystemConfig, departures: Departures, calibration: Calibration
                       ) -> tuple[Simulator, dict[str, tuple[SystemConfig, CM2Operator]]]:
    """The instrument that records the held-out frames (nominal camera), and the
    ``(system, operator)`` pairs LSV-ADMM is given: true instrument, calibrated, nominal."""
    instrument = Simulator(nominal, departures=departures)
    return instrument, {
        "true instrument": (instrument.instrument.truth, instrument.operator),
        "calibrated": (calibration.system, CM2Operator.from_psfs(calibration.system,
                                                                 calibration.psfs)),
        "nominal": (nominal, CM2Operator.from_system(nominal)),
    }


def admm_psnr(obj: np.ndarray, frame: np.ndarray, system: SystemConfig, operator: CM2Operator,
              options: dict) -> float:  # fmt: skip
    """PSNR (dB, data range 1) of LSV-ADMM's reconstruction of ``frame`` against ``obj``."""
    recon = reconstruct_with_baseline("admm", frame, system, operator=operator, **options)
    return psnr(obj, recon, data_range=1.0)


def main() -> int:
    """Run the check and write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=HELD_OUT_IMAGES, default=HELD_OUT_IMAGES)
    parser.add_argument("--iterations", type=int, help="LSV-ADMM iterations (default: preset)")
    parser.add_argument("--departures", help="a named departure set instead of DRIFT")
    parser.add_argument("--brightness", type=float, default=3.0,
                        help="bead value (3: peak at about 75 %% of full scale)")
    parser.add_argument("--repeats", type=int, default=4, help="frames per scan position")
    parser.add_argument("--tolerance", type=float, default=1e-3,
                        help="low-rank tolerance of the calibration")
    args = parser.parse_args()
    options = {} if args.iterations is None else {"iterations": args.iterations}
    torch.set_num_threads(1)
    nominal = SystemConfig.preset("cm2-mini")
    departures = DRIFT if args.departures is None else Departures.named(args.departures, nominal)
    start = time.perf_counter()
    scanner = scanner_for(nominal, departures)
    positions = scan_positions(nominal, 9, args.repeats)
    frames, dark = simulate_scan(scanner, positions, brightness=args.brightness, seed=1)
    scanned = time.perf_counter()
    calibration = calibrate(frames, positions, nominal, dark=dark, tolerance=args.tolerance)
    calibrated = time.perf_counter()
    ray_error = chief_ray_error(calibration, departures, nominal)
    print(f"scan {scanned - start:.0f} s, calibration {calibrated - scanned:.0f} s, "
          f"chief-ray error max {ray_error.max():.3f} px", flush=True)
    instrument, operators = held_out_operators(nominal, departures, calibration)
    true_offsets = departures.lens_offsets(nominal)
    relative = true_offsets - true_offsets[4]
    rows = []
    for name in args.scenes:
        obj = held_out_image(name, nominal.sub_view_size)
        frame = instrument.simulate(obj, seed=7).measurement
        begun = time.perf_counter()
        registration, moved, moved_psfs = self_register(frame, nominal)
        misfit = float(np.linalg.norm(registration.residuals, axis=1).max())
        accepted = misfit <= MAX_LENS_RESIDUAL_PX  # as svcode reconstruct --register
        moved, moved_operator = ((moved, CM2Operator.from_psfs(moved, moved_psfs)) if accepted
                                 else operators["nominal"])
        error = np.linalg.norm(registration.offsets - relative, axis=1)
        row = {"scene": name, "registration_error_px": {
            "mean": float(error.mean()), "max": float(error.max()),
            "no_drift_mean": float(np.linalg.norm(relative, axis=1).mean()),
            "no_drift_max": float(np.linalg.norm(relative, axis=1).max()),
            "largest_lens_misfit": misfit, "accepted": accepted,
            "seconds": time.perf_counter() - begun}}
        print(name, "registration", row["registration_error_px"], flush=True)
        for label, (system, operator) in {**operators,
                                          "self-registered": (moved, moved_operator)}.items():
            row[label] = admm_psnr(obj, frame, system, operator, options)
            print(name, label, f"{row[label]:.2f} dB", flush=True)
        rows.append(row)
    labels = [*operators, "self-registered"]
    mean = {label: float(np.mean([r[label] for r in rows])) for label in labels}
    result = {
        "system": nominal.name,
        "departures": departures.to_dict(),
        "scan_frames": len(positions),
        "scan": {"brightness": args.brightness, "repeats": args.repeats,
                 "tolerance": args.tolerance},
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
        f"# Calibration held-out check (cm2-mini, `{departures.name}` departures)",
        "",
        f"Departures {departures.to_dict()}.",
        "",
        f"Bead scan {len(positions)} frames (9 × 9 positions, {args.repeats} frames each, "
        f"bead value {args.brightness}, peak reading {frames.max():.2f}), 8 dark frames; "
        f"calibration tolerance {args.tolerance}: chief-ray error max "
        f"{ray_error.max():.3f} px; K per lens {list(calibration.ranks)}; scan "
        f"{scanned - start:.0f} s, calibration {calibrated - scanned:.0f} s.",
        "",
        "| scene | " + " | ".join(labels) + " |",
        "| --- |" + " --- |" * len(labels),
    ]
    for row in rows:
        lines.append(f"| {row['scene']} | "
                     + " | ".join(f"{row[k]:.2f}" for k in labels) + " |")
    lines.append("| mean | " + " | ".join(f"{mean[k]:.2f}" for k in labels) + " |")
    lines += ["", "Self-registration from the same frames: lens offsets relative to the centre "
              "lens, error (px, Euclidean, mean / max over lenses) against assuming no drift:",
              "", "| scene | mean | max | no drift, mean | no drift, max | lens misfit | "
              "applied | seconds |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        reg = row["registration_error_px"]
        lines.append(f"| {row['scene']} | {reg['mean']:.3f} | {reg['max']:.3f} | "
                     f"{reg['no_drift_mean']:.3f} | {reg['no_drift_max']:.3f} | "
                     f"{reg['largest_lens_misfit']:.2f} | {'yes' if reg['accepted'] else 'no'} | "
                     f"{reg['seconds']:.0f} |")
    lines.append("")
    lines.append("A registration whose largest lens misfit (distance from the array's fitted "
                 f"translation and rotation) exceeds {MAX_LENS_RESIDUAL_PX} px is not applied "
                 "(as in `svcode reconstruct --register`): the self-registered column is then "
                 "the nominal system's.")
    lines.append("")
    lines.append("LSV-ADMM PSNR in dB against the object, one noisy frame of the departed "
                 f"instrument per scene, options {options or 'of the preset'}; generated by "
                 "`python bench/calibration.py " + " ".join(sys.argv[1:]) + "`.")
    (RESULTS / "calibration.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
