"""Calibration accuracy at the drift limits, and how it falls with the scan's recording.

Issue 44, item 2: on simulated scans of ``cm2-mini`` instruments that drifted by up to 3 px
and 0.3° with aberrations off by ±25 %, the calibrated system should give LSV-ADMM within
:data:`PSNR_GAP_DB` of the true instrument on held-out scenes, and chief rays within
:data:`RAY_ERROR_PX`.

1. **Held-out instruments** (:data:`INSTRUMENTS`): each is scanned with the default recipe of
   ``bench/calibration.py`` (9 × 9 raster, 4 frames per position, bead value 3: a peak at
   about 75 % of full scale, 8 dark frames, a black level), calibrated at tolerance 1e-3,
   and the held-out scenes are reconstructed by LSV-ADMM from one noisy frame given the
   true instrument's, the calibrated and the nominal operator. Reported: chief-ray error
   (Euclidean per lens, max and mean), the forward-model error, PSNR and the gap.
2. **Recording sweep** on the first instrument, one factor at a time from the default: grid,
   bead brightness (photon level), frames per position. Reported: chief-ray error and the
   forward-model error ``‖A_cal x − A_true x‖ / ‖A_true x‖`` on the held-out cell scene.

The forward-model error is measured as in ``tests/test_calibration.py`` and
``docs/calibration.md`` (noiseless sensor frames of the held-out cell scene).

Scans are recorded as :func:`svcode_core.physics.scan.simulate_scan` does, except that the
``repeats`` frames of a position are independent noise draws of one noiseless frame
(:meth:`Simulator.simulate` with ``frames=repeats``) instead of one forward model per frame:
the same camera model and statistics, a quarter of the cost at 4 repeats.

Run: ``python bench/calibration_sweep.py [--scenes ...] [--iterations N] [--resume]``
(writes ``bench/results/calibration_sweep.{json,md}``; ``--resume`` keeps the finished
entries of an earlier run with the same settings).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from typing import Any

import numpy as np
import torch
from calibration import (
    RESULTS,
    admm_psnr,
    chief_ray_error,
    held_out_operators,
    scan_positions,
    scanner_for,
)

from svcode_core.config import SystemConfig
from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image
from svcode_core.physics.calibration import Calibration, CalibrationError, calibrate
from svcode_core.physics.departures import Departures
from svcode_core.physics.scan import bead_object, scan_grid
from svcode_core.physics.simulate import Simulator

#: the issue's targets
PSNR_GAP_DB = 1.5
RAY_ERROR_PX = 0.2
#: the default recipe (``bench/calibration.py``)
DEFAULT = {"grid": 9, "brightness": 3.0, "repeats": 4}
TOLERANCE = 1e-3
#: what the sweep varies, one factor at a time from :data:`DEFAULT`
SWEEP = {"grid": [5, 7, 9, 11], "brightness": [0.3, 1.0, 3.0], "repeats": [1, 4]}
#: how much worse than the sweep's best a recommended setting may be: forward error
#: (absolute, 0.5 percentage points) and centre-lens chief ray
FORWARD_SLACK = 0.005
RAY_SLACK_PX = 0.02
#: scene of the forward-model error
FORWARD_SCENE = "cell.png"


def _aberrations(nominal: SystemConfig, fraction: float) -> dict[str, float]:
    """Errors of the fitted Seidel coefficients and distortion: ``fraction`` of nominal."""
    optics = nominal.optics
    return {
        "spherical_error_waves": fraction * optics.spherical,
        "coma_error_waves": fraction * optics.coma,
        "astigmatism_error_waves": fraction * optics.astigmatism,
        "field_curvature_error_waves": fraction * optics.field_curvature,
        "distortion_error_px": fraction * optics.distortion,
    }


def instruments(nominal: SystemConfig) -> list[Departures]:
    """The held-out instruments: the issue's two extremes and one in between with jitter."""
    mixed = _aberrations(nominal, 0.125)
    for name in ("coma_error_waves", "field_curvature_error_waves"):
        mixed[name] = -mixed[name]
    return [
        Departures(name="extreme +", mla_shift_px=(3.0, -2.0), mla_rotation_deg=0.3,
                   **_aberrations(nominal, 0.25)),
        Departures(name="extreme -", mla_shift_px=(-2.5, 1.5), mla_rotation_deg=-0.3,
                   **_aberrations(nominal, -0.25)),
        Departures(name="between, jitter", mla_shift_px=(1.5, 2.0), mla_rotation_deg=0.15,
                   lens_jitter_px=0.5, seed=3, **mixed),
    ]  # fmt: skip


#: rank tolerance of a truth rendered close to its full PSFs (the attribution's last rows)
TIGHT_TRUTH = 1e-4


def attribution_set(departures: Departures, nominal: SystemConfig) -> list[Departures]:
    """``departures`` varied to show what is left of its chief-ray error: without its
    aberration errors, and with its truth rendered at rank tolerance :data:`TIGHT_TRUTH`
    (a simulated scan renders the true PSFs through their low-rank model, whose spots are
    not the pupil model's), with and without them."""
    geometry = dataclasses.replace(departures, name=f"{departures.name}: geometry only",
                                   **_aberrations(nominal, 0.0))
    tight = f"truth at tolerance {TIGHT_TRUTH:g}"
    return [
        geometry,
        dataclasses.replace(geometry, name=f"{geometry.name}, {tight}",
                            truth_rank_tolerance=TIGHT_TRUTH),
        dataclasses.replace(departures, name=f"{departures.name}: {tight}",
                            truth_rank_tolerance=TIGHT_TRUTH),
    ]


class Clock:
    """Wall and CPU seconds since the last :meth:`lap`."""

    def __init__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def lap(self) -> dict[str, float]:
        wall, cpu = time.perf_counter(), time.process_time()
        out = {"wall_s": round(wall - self.wall, 1), "cpu_s": round(cpu - self.cpu, 1)}
        self.wall, self.cpu = wall, cpu
        return out


def record_scan(scanner: Simulator, steps: int, repeats: int, brightness: float,
                seed: int = 1, dark_frames: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames, positions (each ``repeats`` times in a row) and dark frames of a raster scan.

    As :func:`~svcode_core.physics.scan.simulate_scan`, with the repeats of a position drawn
    from one noiseless frame (position ``n`` seeds ``seed + n``, the dark stack follows).
    """
    nominal = scanner.system
    grid = scan_grid(nominal, steps)
    frames = []
    for n, position in enumerate(grid):
        obj = bead_object(nominal.sub_view_size, position) * np.float32(brightness)
        shot = scanner.simulate(obj, seed=seed + n, frames=repeats).measurement
        frames.append(shot.reshape(-1, *nominal.sensor_shape))
    empty = np.zeros((nominal.sub_view_size,) * 2, np.float32)
    dark = scanner.simulate(empty, seed=seed + len(grid), frames=dark_frames).measurement
    return (np.concatenate(frames), scan_positions(nominal, steps, repeats),
            dark.reshape(-1, *nominal.sensor_shape))  # fmt: skip


def forward_error(operator, truth, x: torch.Tensor) -> float:
    """``‖A x − A_true x‖ / ‖A_true x‖`` on noiseless sensor frames."""
    with torch.no_grad():
        reference = truth.measure(x)
        return float(torch.linalg.norm(operator.measure(x) - reference)
                     / torch.linalg.norm(reference))  # fmt: skip


def scan_and_calibrate(nominal: SystemConfig, departures: Departures, recipe: dict[str, Any]
                       ) -> tuple[Calibration | None, dict[str, Any]]:  # fmt: skip
    """Scan ``departures`` with ``recipe``, calibrate; the calibration (``None`` if refused)
    and a JSON-able summary (chief-ray error, timings, peak reading, or the refusal)."""
    clock = Clock()
    frames, positions, dark = record_scan(scanner_for(nominal, departures), recipe["grid"],
                                          recipe["repeats"], recipe["brightness"])
    entry: dict[str, Any] = {"recipe": dict(recipe), "scan_frames": len(frames),
                             "peak_reading": float(frames.max()), "scan": clock.lap()}
    try:
        calibration = calibrate(frames, positions, nominal, dark=dark, tolerance=TOLERANCE)
    except CalibrationError as error:
        entry.update(refused=str(error), calibration=clock.lap())
        return None, entry
    entry["calibration"] = clock.lap()
    error = np.linalg.norm(chief_ray_error(calibration, departures, nominal), axis=1)
    entry.update(chief_ray_error_px={"max": float(error.max()), "mean": float(error.mean()),
                                     "per_lens": error.round(4).tolist()},
                 array_shift_px=calibration.array_shift.round(3).tolist(),
                 array_rotation_deg=round(float(calibration.array_rotation_deg), 4),
                 ranks=list(calibration.ranks))  # fmt: skip
    return calibration, entry


def evaluate(nominal: SystemConfig, departures: Departures, calibration: Calibration,
             scenes: list[str], options: dict) -> dict[str, Any]:  # fmt: skip
    """Forward-model errors and LSV-ADMM PSNR of the three operators on ``scenes``."""
    instrument, operators = held_out_operators(nominal, departures, calibration)
    truth = operators["true instrument"][1]
    x = torch.as_tensor(held_out_image(FORWARD_SCENE, nominal.sub_view_size))
    out: dict[str, Any] = {"forward_error": {
        label: forward_error(operators[label][1], truth, x) for label in ("calibrated", "nominal")}}
    print(f"  forward error {out['forward_error']}", flush=True)
    rows = []
    for name in scenes:
        obj = held_out_image(name, nominal.sub_view_size)
        frame = instrument.simulate(obj, seed=7).measurement
        row: dict[str, Any] = {"scene": name}
        for label, (system, operator) in operators.items():
            clock = Clock()
            row[label] = admm_psnr(obj, frame, system, operator, options)
            row[f"{label} cpu_s"] = clock.lap()["cpu_s"]
            print(f"  {name} {label}: {row[label]:.2f} dB", flush=True)
        row["gap"] = row["true instrument"] - row["calibrated"]
        rows.append(row)
    out["psnr_db"] = rows
    if rows:
        out["mean_psnr_db"] = {label: float(np.mean([r[label] for r in rows]))
                               for label in (*operators, "gap")}  # fmt: skip
        out["worst_gap_db"] = float(max(r["gap"] for r in rows))
    return out


def forward_only(nominal: SystemConfig, departures: Departures, calibration: Calibration
                 ) -> dict[str, float]:  # fmt: skip
    """The calibrated operator's forward-model error (a sweep point)."""
    instrument, operators = held_out_operators(nominal, departures, calibration)
    x = torch.as_tensor(held_out_image(FORWARD_SCENE, nominal.sub_view_size))
    return {"calibrated": forward_error(operators["calibrated"][1], instrument.operator, x)}


def main() -> int:
    """Run the check and the sweep, write the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", choices=HELD_OUT_IMAGES,
                        default=["cell.png", "ihc.png"],
                        help="held-out scenes of the LSV-ADMM check (default: cell, ihc)")
    parser.add_argument("--iterations", type=int, help="LSV-ADMM iterations (default: preset)")
    parser.add_argument("--instruments", type=int, default=3,
                        help="how many of the held-out instruments to check")
    parser.add_argument("--no-sweep", action="store_true", help="skip the recording sweep")
    parser.add_argument("--no-attribution", action="store_true",
                        help="skip the attribution of the first instrument's chief-ray error")
    parser.add_argument("--resume", action="store_true",
                        help="keep finished entries of an earlier run with the same settings")
    parser.add_argument("--markdown-only", action="store_true",
                        help="rewrite the .md from the .json of an earlier run")
    args = parser.parse_args()
    options = {} if args.iterations is None else {"iterations": args.iterations}
    torch.set_num_threads(1)
    nominal = SystemConfig.preset("cm2-mini")
    path = RESULTS / "calibration_sweep.json"
    settings = {"scenes": args.scenes, "admm_options": options, "tolerance": TOLERANCE,
                "forward_scene": FORWARD_SCENE}
    result: dict[str, Any] = {"system": nominal.name, "settings": settings,
                              "instruments": [], "sweep": []}
    if args.resume and path.exists():
        earlier = json.loads(path.read_text())
        if earlier.get("settings") == settings:
            result = earlier
    command = "python bench/calibration_sweep.py " + " ".join(sys.argv[1:])
    if args.resume and result.get("command") and result["command"] != command:
        command = f"{result['command']}`, then `{command}"  # what made the kept entries
    result["command"] = command
    result["machine"] = (f"{platform.machine()}, torch {torch.__version__}, 1 thread "
                         "(torch.set_num_threads(1), OMP_NUM_THREADS=1), on a 2-core machine "
                         "shared with a training job")
    RESULTS.mkdir(exist_ok=True)

    def save() -> None:
        path.write_text(json.dumps(result, indent=2) + "\n")

    def done(section: str, key: dict) -> dict | None:
        return next((e for e in result[section] if e["key"] == key), None)

    if args.markdown_only:
        write_markdown(json.loads(path.read_text()))
        return 0
    held_out = instruments(nominal)[: args.instruments]
    for departures in held_out:
        key = {"departures": departures.to_dict(), "recipe": DEFAULT}
        if done("instruments", key):
            continue
        print(f"{departures.name}: scanning and calibrating", flush=True)
        calibration, entry = scan_and_calibrate(nominal, departures, DEFAULT)
        print(f"  {entry}", flush=True)
        if calibration is not None:
            clock = Clock()
            entry.update(evaluate(nominal, departures, calibration, args.scenes, options))
            entry["evaluation"] = clock.lap()
        result["instruments"].append({"key": key, "name": departures.name, **entry})
        save()
    if not args.no_sweep:
        departures = held_out[0]
        for factor, values in SWEEP.items():
            for value in values:
                recipe = {**DEFAULT, factor: value}
                key = {"departures": departures.to_dict(), "recipe": recipe}
                if recipe == DEFAULT or done("sweep", key):
                    continue  # the default point is the instrument's own entry
                print(f"sweep {recipe}", flush=True)
                calibration, entry = scan_and_calibrate(nominal, departures, recipe)
                if calibration is not None:
                    entry["forward_error"] = forward_only(nominal, departures, calibration)
                print(f"  {entry}", flush=True)
                result["sweep"].append({"key": key, "factor": factor, **entry})
                save()
    result.setdefault("attribution", [])
    if not args.no_attribution:
        for departures in attribution_set(held_out[0], nominal):
            key = {"departures": departures.to_dict(), "recipe": DEFAULT}
            if done("attribution", key):
                continue
            print(f"attribution: {departures.name}", flush=True)
            calibration, entry = scan_and_calibrate(nominal, departures, DEFAULT)
            if calibration is not None:
                entry["forward_error"] = forward_only(nominal, departures, calibration)
            print(f"  {entry}", flush=True)
            result["attribution"].append({"key": key, "name": departures.name, **entry})
            save()
    result["cpu_s_total"] = round(sum(
        e[stage]["cpu_s"] for section in ("instruments", "sweep", "attribution")
        for e in result[section]
        for stage in ("scan", "calibration", "evaluation") if stage in e), 1)
    save()
    write_markdown(result)
    return 0


def _pct(value: float) -> str:
    return f"{100 * value:.1f} %"


def write_markdown(result: dict[str, Any]) -> None:
    """``calibration_sweep.md`` from the JSON results."""
    settings = result["settings"]
    options = settings["admm_options"] or "of the preset (50 iterations)"
    lines = [
        "# Calibration accuracy at the drift limits, and the scan's recording (issue 44)",
        "",
        f"Generated by `{result['command']}` on {result['machine']}; "
        f"{result['cpu_s_total']:.0f} CPU-s in all (scans, calibrations, evaluation). "
        f"Targets: LSV-ADMM within {PSNR_GAP_DB} dB of the true instrument, chief rays "
        f"within {RAY_ERROR_PX} px (Euclidean error per lens).",
        "",
        "Scan recipe unless varied: 9 × 9 raster, 4 frames per position, bead value 3 (peak "
        "reading about 0.8 of full scale), 8 dark frames, black level 2e-3; calibrated at "
        f"tolerance {settings['tolerance']}. Held-out frames: one noisy frame per scene at the "
        f"nominal noise; LSV-ADMM options {options}; scenes {', '.join(settings['scenes'])} "
        "(a subset of the held-out scenes, to fit the CPU budget). Forward-model error: "
        f"‖A x − A_true x‖ / ‖A_true x‖ on the noiseless frame of {settings['forward_scene']}. "
        "The repeats of a scan position are independent noise draws of one noiseless frame "
        "(the same camera model as `simulate_scan`, one forward model per position).",
        "",
        "## Held-out instruments",
        "",
        "| instrument | shift px | rotation ° | jitter px | aberrations | chief-ray error "
        "max / mean px | forward error cal. / nom. | mean PSNR true | calibrated | nominal | "
        "gap mean (worst scene) dB | pass |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for entry in result["instruments"]:
        d = entry["key"]["departures"]
        fraction = d["coma_error_waves"] / 0.3
        aberr = (f"{100 * fraction:+.0f} %" if d["name"].startswith("extreme")
                 else "±12.5 % (mixed signs)")
        head = (f"| {entry['name']} | ({d['mla_shift_px'][0]:g}, {d['mla_shift_px'][1]:g}) | "
                f"{d['mla_rotation_deg']:+g} | {d['lens_jitter_px']:g} | {aberr} | ")
        if "refused" in entry:
            lines.append(head + f"refused: {entry['refused']} |" + " |" * 6)
            continue
        ray = entry["chief_ray_error_px"]
        fwd = entry["forward_error"]
        mean = entry.get("mean_psnr_db")
        ok_ray = ray["max"] <= RAY_ERROR_PX
        if mean:
            ok_gap = entry["worst_gap_db"] <= PSNR_GAP_DB
            psnr_cells = (f"{mean['true instrument']:.2f} | {mean['calibrated']:.2f} | "
                          f"{mean['nominal']:.2f} | {mean['gap']:+.2f} "
                          f"({entry['worst_gap_db']:+.2f})")
            verdict = (f"rays {'yes' if ok_ray else 'NO'}, PSNR {'yes' if ok_gap else 'NO'}")
        else:
            psnr_cells, verdict = "– | – | – | –", f"rays {'yes' if ok_ray else 'NO'}"
        lines.append(head + f"{ray['max']:.3f} / {ray['mean']:.3f} | "
                     f"{_pct(fwd['calibrated'])} / {_pct(fwd['nominal'])} | {psnr_cells} | "
                     f"{verdict} |")
    lines += ["", "PSNR (dB) per scene:", "", "| instrument | scene | true instrument | "
              "calibrated | nominal | gap |", "| --- | --- | --- | --- | --- | --- |"]
    for entry in result["instruments"]:
        for row in entry.get("psnr_db", []):
            lines.append(f"| {entry['name']} | {row['scene']} | {row['true instrument']:.2f} | "
                         f"{row['calibrated']:.2f} | {row['nominal']:.2f} | {row['gap']:+.2f} |")
    lines += ["", "Fitted array motion, low-rank order and time per instrument:", "",
              "| instrument | array shift px | rotation ° | K per lens | scan CPU-s | "
              "calibration CPU-s | evaluation CPU-s |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for entry in result["instruments"]:
        if "refused" in entry:
            continue
        lines.append(f"| {entry['name']} | {tuple(entry['array_shift_px'])} | "
                     f"{entry['array_rotation_deg']:+.3f} | {entry['ranks']} | "
                     f"{entry['scan']['cpu_s']:.0f} | {entry['calibration']['cpu_s']:.0f} | "
                     f"{entry.get('evaluation', {}).get('cpu_s', 0):.0f} |")
    if result.get("attribution"):
        first = result["instruments"][0]["name"]
        lines += ["", f"What is left of the chief-ray error of `{first}` (same scan recipe; "
                  "without its aberration errors, and with its truth rendered closer to its "
                  "full PSFs):", "",
                  "| instrument | chief-ray error max / mean px | per lens px | forward error |",
                  "| --- | --- | --- | --- |"]
        for entry in [result["instruments"][0], *result["attribution"]]:
            if "refused" in entry:
                lines.append(f"| {entry['name']} | refused: {entry['refused']} | | |")
                continue
            ray = entry["chief_ray_error_px"]
            lines.append(f"| {entry['name']} | {ray['max']:.3f} / {ray['mean']:.3f} | "
                         f"{', '.join(f'{v:.2f}' for v in ray['per_lens'])} | "
                         f"{_pct(entry['forward_error']['calibrated'])} |")
    lines += ["", *findings(result)]
    sweep = sweep_table(result)
    if sweep:
        base = result["instruments"][0]
        lines += ["", f"## How accuracy falls with the recording (instrument `{base['name']}`)",
                  "", "One factor at a time from the default (the default row is the "
                  "instrument's own entry above).", ""]
        for factor, rows in sweep.items():
            lines += [f"| {factor} | frames | peak reading | chief-ray error max / mean px | "
                      "centre lens px | forward error | scan + calibration CPU-s |",
                      "| --- | --- | --- | --- | --- | --- | --- |"]
            for value, entry in rows:
                label = f"{value}×{value}" if factor == "grid" else f"{value:g}"
                label += " (default)" if value == DEFAULT[factor] else ""
                cost = entry["scan"]["cpu_s"] + entry["calibration"]["cpu_s"]
                if "refused" in entry:
                    lines.append(f"| {label} | {entry['scan_frames']} | "
                                 f"{entry['peak_reading']:.2f} | refused: {entry['refused']} | – | "
                                 f"– | {cost:.0f} |")
                    continue
                ray = entry["chief_ray_error_px"]
                lines.append(f"| {label} | {entry['scan_frames']} | {entry['peak_reading']:.2f} | "
                             f"{ray['max']:.3f} / {ray['mean']:.3f} | {ray['per_lens'][4]:.3f} | "
                             f"{_pct(entry['forward_error']['calibrated'])} | {cost:.0f} |")
            lines.append("")
        lines += ["## How to record", "", *advice(sweep)]
    (RESULTS / "calibration_sweep.md").write_text("\n".join(lines) + "\n")


def findings(result: dict[str, Any]) -> list[str]:
    """What the instrument tables say, with their figures."""
    checked = [e for e in result["instruments"] if "refused" not in e and "worst_gap_db" in e]
    if not checked:
        return []
    worst = max(checked, key=lambda e: e["worst_gap_db"])
    rays = [e["chief_ray_error_px"]["max"] for e in checked]
    gain = [e["mean_psnr_db"]["calibrated"] - e["mean_psnr_db"]["nominal"] for e in checked]
    fwd = [e["forward_error"]["calibrated"] for e in checked]
    nom = [e["forward_error"]["nominal"] for e in checked]
    rigid = [e for e in checked if not e["key"]["departures"]["lens_jitter_px"]] or checked
    shift = max(float(np.abs(np.subtract(e["array_shift_px"],
                                         e["key"]["departures"]["mla_shift_px"])).max())
                for e in rigid)  # fmt: skip
    turn = max(abs(e["array_rotation_deg"] - e["key"]["departures"]["mla_rotation_deg"])
               for e in rigid)  # fmt: skip
    centre = max(e["chief_ray_error_px"]["per_lens"][4] for e in checked)
    met_gap = sum(e["worst_gap_db"] <= PSNR_GAP_DB for e in checked)
    met_ray = sum(r <= RAY_ERROR_PX for r in rays)
    lines = [
        f"**PSNR target met on {met_gap} of {len(checked)} instruments**: the worst scene gap "
        f"is {worst['worst_gap_db']:.2f} dB (`{worst['name']}`); the calibrated system is "
        f"{min(gain):.1f}–{max(gain):.1f} dB above the nominal preset on the mean, its forward "
        f"model {_pct(min(fwd))}–{_pct(max(fwd))} off the instrument's (nominal "
        f"{_pct(min(nom))}–{_pct(max(nom))}).",
        "",
        f"**Chief-ray target met on {met_ray} of {len(checked)} instruments** (worst lens "
        + ", ".join(f"{r:.2f}" for r in rays) + " px). The array shift and rotation of the "
        f"unjittered instruments are found within {shift:.3f} px and {turn:.3f}° (the "
        "jittered one's fit absorbs part of its jitter; its per-lens offsets pass); the centre "
        f"lens is within {centre:.3f} px, the corner lenses are worst. The aberration errors "
        "move every spot's centroid from the nominal model's by an amount that depends on the "
        "spot's field, and an outer lens sees only part of its field, so a mean over its spots "
        "would carry that move as a bias (0.64-0.89 px before it was fitted); the calibration "
        "fits the move, shared by the lenses, beside the offsets (`field_shift`).",
    ]
    attribution = result.get("attribution") or []
    parts = {e["name"].split(": ", 1)[-1]: e["chief_ray_error_px"]["max"] for e in attribution
             if "refused" not in e}  # fmt: skip
    tight_truth = [v for name, v in parts.items() if f"tolerance {TIGHT_TRUTH:g}" in name]
    if len(parts) == 3 and tight_truth:
        lines[-1] += (
            f" On `{checked[0]['name']}` the geometry alone leaves {parts['geometry only']:.2f} px "
            f"({rays[0]:.2f} with the aberration errors); with the truth rendered at rank "
            f"tolerance {TIGHT_TRUTH:g} instead of the operator's, {max(tight_truth):.3f} px or "
            "less. What is left is the simulated truth's own: its PSFs pass through a low-rank "
            "model whose corner-lens spots sit up to a tenth of a pixel from the pupil model's, "
            "an error a real bead's image does not have. The calibrated operator depends little "
            "on the chief rays (its PSFs are fitted to the scan windows and carry the true image "
            "positions); the fitted chief rays alone matter to a network given them and to the "
            "sub-view boxes.")
    return lines


def sweep_table(result: dict[str, Any]) -> dict[str, list[tuple[Any, dict]]]:
    """Per factor, ``(value, entry)`` sorted by value, the default from the first instrument."""
    if not result["sweep"] or not result["instruments"]:
        return {}
    base = result["instruments"][0]
    table: dict[str, list[tuple[Any, dict]]] = {}
    for factor in SWEEP:
        rows = [(e["recipe"][factor], e) for e in result["sweep"] if e["factor"] == factor]
        rows.append((DEFAULT[factor], base))
        table[factor] = sorted(rows, key=lambda row: row[0])
    return table


def _setting(factor: str, value: Any, entry: dict) -> str:
    if factor == "grid":
        return f"{value}×{value}"
    if factor == "brightness":
        return f"bead {value:g} (peak {entry['peak_reading']:.2f})"
    return f"{value:g}"


def advice(sweep: dict[str, list[tuple[Any, dict]]]) -> list[str]:
    """Three lines of advice from the sweep: per factor, the cheapest setting whose forward
    error is within :data:`FORWARD_SLACK` of the best measured and whose centre-lens chief
    ray (the lens whose whole field is on the sensor: noise, no field-sampling bias) is
    within :data:`RAY_SLACK_PX` of the best."""
    lines = []
    words = {"grid": "Grid", "brightness": "Brightness (photon level)",
             "repeats": "Frames per position"}
    for factor, rows in sweep.items():
        usable = [(v, e) for v, e in rows if "refused" not in e]
        refused = [v for v, e in rows if "refused" in e]
        best = min(e["forward_error"]["calibrated"] for _, e in usable)
        best_ray = min(e["chief_ray_error_px"]["per_lens"][4] for _, e in usable)
        good = [(v, e) for v, e in usable
                if e["forward_error"]["calibrated"] <= best + FORWARD_SLACK
                and e["chief_ray_error_px"]["per_lens"][4] <= best_ray + RAY_SLACK_PX]
        figures = ", ".join(
            f"{_setting(factor, v, e)}: {_pct(e['forward_error']['calibrated'])} / "
            f"{e['chief_ray_error_px']['per_lens'][4]:.3f} px" for v, e in usable)
        choice = min(good, key=lambda row: row[0])[0]
        text = (f"- **{words[factor]}** (forward error / centre-lens chief ray): {figures}"
                + (f"; {', '.join(f'{v}×{v}' for v in refused)} refused: the raster needs as "
                   "many rows and columns as the PSF grid (7 on cm2-mini)" if refused else "")
                + f". Record at least {_setting(factor, choice, dict(good)[choice])}.")
        lines.append(text)
    lines.append(f"  (\"At least\": the cheapest setting within {100 * FORWARD_SLACK:.1f} "
                 f"points of the best forward error and {RAY_SLACK_PX} px of the best "
                 "centre-lens chief ray.)")
    return lines


if __name__ == "__main__":
    sys.exit(main())
