"""Fine-tuning for a calibrated cm2-v2, measured on a simulated drifted instrument.

The path a lab takes after recording a bead scan, each step the command a lab runs:

1. ``scan``: the drifted instrument (:data:`DRIFT`: the lens array moved by (3, -2) px and
   turned, each lens off by up to a pixel more, and the optics' aberrations of the
   ``model`` departures at cm2-v2's scale) records a 9 × 9 bead scan and 8 dark frames
   (simulated here, in two worker processes: about 45 s a frame on one thread);
2. ``calibrate``: ``svcode calibrate`` turns it into ``cal/system.json``;
3. ``dataset``: ``svcode dataset --system cal/system.json`` simulates training frames
   through the measured PSFs;
4. ``train``: ``svcode train --init pretrained`` fine-tunes the bundled model on them
   (every epoch's weights kept);
5. ``score``: held-out scenes (scikit-image images no training ever sees) recorded by the
   drifted instrument are reconstructed by whole ``svcode reconstruct`` processes with the
   bundled model given the nominal preset and given the calibrated system, with every
   fine-tuned epoch given the calibrated system (the last also with its tiles overlapping
   by the receptive radius instead of the overlap it inherited from the bundled file), and
   with LSV-ADMM (K = 3, 10 iterations) given the calibrated system; PSNR / SSIM after a
   least-squares gain and offset, seconds and peak memory of each process.

Every stage is skipped when its output exists, so an interrupted run continues. Writes
``finetune.{json,md}`` beside this script.

Usage (from the repository root)::

    python training/cm2-v2/finetune.py [--work runs/finetune-v2] [--frames 12] [--epochs 3] \\
        [--lr 2e-4 5e-5]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import tifffile
from whole_frames import gain_fitted, run

from svcode_core.config import SystemConfig
from svcode_core.io import write_tiff
from svcode_core.methods.model_file import record_extra
from svcode_core.phantoms import HELD_OUT_IMAGES, held_out_image
from svcode_core.physics.departures import Departures
from svcode_core.physics.scan import bead_object, scan_grid, with_dark_offset, write_positions
from svcode_core.physics.simulate import Simulator

HERE = Path(__file__).resolve().parent
NOMINAL = SystemConfig.preset("cm2-v2")
#: the drifted instrument: the model departures (aberrations, distortion, defocus, depth)
#: with the array moved by (3, -2) px, turned, and every lens off by up to a pixel more
DRIFT = dataclasses.replace(
    Departures.named("model", NOMINAL), name="drift", mla_shift_px=(3.0, -2.0),
    mla_rotation_deg=0.05, lens_jitter_px=1.0, seed=14)
DARK_OFFSET = 2e-3  # the scanning camera's black level
PEAK = 0.75  # the brightest bead's reading, a fraction of full scale
TRAIN = ["--patch-size", "384", "--precision", "bf16", "--normalise-exposure",
         "--mse-weight", "100", "--batch-size", "4", "--same-origin", "4",
         "--patches-per-epoch", "400", "--val-patches", "16", "--warmup-steps", "20",
         "--seed", "1", "--compile"]  # the long run's, at a lower rate (--lr)


def _scanner() -> Simulator:
    import torch

    torch.set_num_threads(1)
    return Simulator(with_dark_offset(NOMINAL, DARK_OFFSET), departures=DRIFT)


def _scan_part(positions: np.ndarray, brightness: float, first: int) -> np.ndarray:
    """Bead frames of ``positions``, frame ``n``'s noise seeded ``first + n`` (a worker's
    share of the scan; with no positions, the 8 dark frames)."""
    scanner = _scanner()
    size = NOMINAL.sub_view_size
    if len(positions) == 0:
        dark = scanner.simulate(np.zeros((size, size), np.float32), seed=first, frames=8)
        return dark.measurement.reshape(-1, *NOMINAL.sensor_shape)
    return np.stack([scanner.simulate(bead_object(size, p) * np.float32(brightness),
                                      seed=first + n).measurement
                     for n, p in enumerate(positions)])


def _brightness() -> float:
    """The bead value whose noiseless image peaks at :data:`PEAK` at the field's centre."""
    centre = bead_object(NOMINAL.sub_view_size, (NOMINAL.sub_view_size // 2,) * 2)
    frame = _scanner().simulate(centre, noise=False).measurement
    return PEAK / float(frame.max() - DARK_OFFSET)


def scan(work: Path, workers: int) -> dict:
    """Stage 1: the bead scan, dark frames and positions of the drifted instrument."""
    positions = scan_grid(NOMINAL, 9)
    with ProcessPoolExecutor(workers) as pool:
        brightness = pool.submit(_brightness).result()
        dark = pool.submit(_scan_part, positions[:0], 0.0, 10_000)
        shares = np.array_split(np.arange(len(positions)), workers)
        parts = [pool.submit(_scan_part, positions[s], brightness, 1 + int(s[0])) for s in shares]
        frames = np.concatenate([p.result() for p in parts])
    camera = with_dark_offset(NOMINAL, DARK_OFFSET)
    write_tiff(work / "scan.tif", frames, camera, kind="scan")
    write_tiff(work / "dark.tif", dark.result(), camera, kind="dark")
    write_positions(work / "pos.csv", positions)
    DRIFT.save(work / "drift.json")
    return {"frames": len(positions), "brightness": brightness, "peak": float(frames.max())}


def command(arguments: list[str]) -> dict:
    """Run a command line as a whole process; its peak resident GiB."""
    return {"peak_gib": round(run(arguments)[1], 2)}


def stage(name: str, work: Path, done: Path, log: dict, step) -> None:
    """Run ``step`` unless ``done`` exists; record its wall seconds in ``log``."""
    if done.exists():
        return
    print(f"{name} ...", flush=True)
    start = time.perf_counter()
    extra = step() or {}
    log[name] = {"seconds": time.perf_counter() - start, **extra}
    (work / "stages.json").write_text(json.dumps(log, indent=2) + "\n")
    print(f"{name}: {log[name]}", flush=True)


def dataset(work: Path, frames: int) -> dict:
    """Stage 3: training frames through the calibrated system (resumed if interrupted)."""
    peak = command(["svcode", "dataset", "--system", str(work / "cal" / "system.json"),
                    "--frames", str(frames), "--out", str(work / "data"), "--seed", "5",
                    "--dtype", "float16", "--no-progress"])
    (work / "dataset.done").touch()
    return peak


def train(work: Path, epochs: int, lr: float) -> dict:
    """Stage 4: fine-tune the bundled model at learning rate ``lr``; keep every epoch's
    weights."""
    out, kept = work / f"tuned-lr{lr:g}", work / f"epochs-lr{lr:g}"
    kept.mkdir(exist_ok=True)
    command = ["svcode", "train", "--data", str(work / "data"), "--out", str(out), "--init",
               "pretrained", "--epochs", str(epochs), "--lr", f"{lr:g}", *TRAIN, "--no-progress"]
    if (out / "checkpoints" / "latest.json").is_file():
        command.append("--resume")
    child = subprocess.Popen(command)
    while True:
        finished = child.poll() is not None
        for path in (out / "checkpoints").glob("epoch-*.safetensors"):
            if not (kept / path.name).exists():
                shutil.copy(path, kept / path.name)
        if finished:
            break
        time.sleep(5)
    if child.returncode:
        raise SystemExit(f"svcode train failed ({child.returncode})")
    (work / f"train-lr{lr:g}.done").touch()
    history = json.loads((out / "log.json").read_text())["history"]
    return {"cpu_hours": [round(sum(e["cpu_seconds"] for e in history[: i + 1]) / 3600, 3)
                          for i in range(len(history))],
            "val_psnr": [e["val_recon_psnr"] for e in history]}


def score(work: Path, scenes: list[str], rates: list[float]) -> list[dict]:
    """Stage 5: reconstruct the held-out frames every way; one row per (scene, method)."""
    cal = str(work / "cal" / "system.json")  # the bundled model is the system's default
    ways = {"bundled, nominal system": ["--system", "cm2-v2"],
            "bundled, calibrated system": ["--system", cal]}
    for n, lr in enumerate(rates):
        epochs = sorted((work / f"epochs-lr{lr:g}").glob("epoch-*.safetensors"))
        for path in epochs:
            ways[f"fine-tuned lr {lr:g}, epoch {int(path.stem.split('-')[1])}"] = [
                "--system", cal, "--weights", str(path)]
        if epochs and n == 0:  # the overlap the fine-tuning inherited, against the radius's
            radius = work / "radius-overlap.safetensors"
            shutil.copy(epochs[-1], radius)
            record_extra(radius, overlap_check={})
            ways[f"fine-tuned lr {lr:g}, epoch {len(epochs)}, tiles overlapping by the "
                 "receptive radius"] = ["--system", cal, "--weights", str(radius)]
    ways["LSV-ADMM K=3 10 it, calibrated"] = ["--system", cal, "--method", "admm", "--rank",
                                              "3", "--iterations", "10"]
    rows_file = work / "scores.json"
    rows = json.loads(rows_file.read_text()) if rows_file.is_file() else []
    done = {(r["scene"], r["way"]) for r in rows}
    for scene in scenes:
        folder = work / "scenes" / Path(scene).stem
        if not (folder / "measurement.tif").is_file():
            folder.mkdir(parents=True, exist_ok=True)
            tifffile.imwrite(folder / "truth.tif", held_out_image(scene, NOMINAL.sub_view_size))
            run(["svcode", "simulate", "--system", "cm2-v2", "--object", str(folder / "truth.tif"),
                 "--departures", str(work / "drift.json"), "--seed", "7", "--out", str(folder),
                 "--no-progress"])  # fmt: skip
        truth = tifffile.imread(folder / "object.tif").astype(np.float64)
        for way, options in ways.items():
            if (scene, way) in done:
                continue
            output = folder / f"{way.replace(' ', '_').replace(',', '')}.tif"
            seconds, peak = run(["svcode", "reconstruct", str(folder / "measurement.tif"),
                                 *options, "--out", str(output), "--no-progress"])
            quality = gain_fitted(truth, tifffile.imread(output).astype(np.float64))
            rows.append({"scene": scene, "way": way, "psnr": quality["psnr"],
                         "ssim": quality["ssim"], "seconds": seconds, "peak_gib": peak})
            print(f"{scene} {way}: {quality['psnr']:.2f} dB, {seconds:.0f} s", flush=True)
            rows_file.write_text(json.dumps(rows, indent=2) + "\n")
    return rows


def report(rows: list[dict], stages: dict) -> None:
    """Write finetune.json and finetune.md beside this script."""
    ways = list(dict.fromkeys(r["way"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cell = {(r["scene"], r["way"]): r for r in rows}
    mean = {w: {k: float(np.mean([cell[s, w][k] for s in scenes]))
                for k in ("psnr", "ssim", "seconds", "peak_gib")} for w in ways}
    (HERE / "finetune.json").write_text(json.dumps(
        {"departures": DRIFT.to_dict(), "stages": stages, "rows": rows, "mean": mean,
         "command": " ".join(sys.argv[1:])}, indent=2) + "\n")
    hours = {f"fine-tuned lr {name.split()[-1]}, epoch {i + 1}": h
             for name, info in stages.items() if name.startswith("train")
             for i, h in enumerate(info["cpu_hours"])}
    lines = ["# Fine-tuning for a calibrated cm2-v2 (a simulated drifted instrument)", "",
             "Generated by `python training/cm2-v2/finetune.py " + " ".join(sys.argv[1:])
             + "`; stage seconds are wall time on one thread of a 2-core machine beside another "
             "job.", "",
             f"Drift: {DRIFT.to_dict()}.", ""]
    for name, info in stages.items():
        lines.append(f"* {name}: {info['seconds']:.0f} s"
                     + "".join(f", {k} {v}" for k, v in info.items() if k != "seconds"))
    lines += ["", "Held-out scenes recorded by the drifted instrument, PSNR / SSIM after a "
              "least-squares gain and offset, whole `svcode reconstruct` processes:", "",
              "| way | fine-tuning CPU-hours | " + " | ".join(scenes) + " | mean | s/frame | "
              "peak GiB |", "|---|---|" + "---|" * (len(scenes) + 3)]
    for w in ways:
        lines.append(f"| {w} | {hours.get(w, '')} | "
                     + " | ".join(f"{cell[s, w]['psnr']:.2f} / {cell[s, w]['ssim']:.3f}"
                                  for s in scenes)
                     + f" | {mean[w]['psnr']:.2f} / {mean[w]['ssim']:.3f} | "
                     f"{mean[w]['seconds']:.1f} | {mean[w]['peak_gib']:.2f} |")
    (HERE / "finetune.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/finetune-v2"))
    parser.add_argument("--frames", type=int, default=12, help="training frames simulated")
    parser.add_argument("--epochs", type=int, default=3, help="fine-tuning epochs")
    parser.add_argument("--lr", type=float, nargs="+", default=[2e-4],
                        help="fine-tuning learning rates, one run each")
    parser.add_argument("--workers", type=int, default=2, help="processes of the scan")
    parser.add_argument("--scenes", nargs="+", choices=HELD_OUT_IMAGES, default=HELD_OUT_IMAGES)
    parser.add_argument("--until", choices=["scan", "calibrate", "dataset", "train", "score"],
                        default="score", help="stop after this stage")
    args = parser.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    log_file = work / "stages.json"
    stages = json.loads(log_file.read_text()) if log_file.is_file() else {}
    order = ["scan", "calibrate", "dataset", "train", "score"]
    steps = {
        "scan": (work / "drift.json", lambda: scan(work, args.workers)),
        "calibrate": (work / "cal" / "system.json", lambda: command(
            ["svcode", "calibrate", str(work / "scan.tif"), "--positions", str(work / "pos.csv"),
             "--system", "cm2-v2", "--dark", str(work / "dark.tif"), "--out", str(work / "cal")])),
        "dataset": (work / "dataset.done", lambda: dataset(work, args.frames)),
    }
    for name in order[: order.index(args.until) + 1]:
        if name == "score":
            report(score(work, args.scenes, args.lr), stages)
        elif name == "train":
            for lr in args.lr:
                stage(f"train lr {lr:g}", work, work / f"train-lr{lr:g}.done", stages,
                      lambda lr=lr: train(work, args.epochs, lr))
        else:
            done, step = steps[name]
            stage(name, work, done, stages, step)


if __name__ == "__main__":
    main()
