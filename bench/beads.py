"""Beads from sparse to dense: how many each method finds, and how wide they come out
(bench/results/beads.md).

As in the seed paper's bead experiment, equal beads (Gaussian sigma 1 object pixel,
radius 2 px; a 10-µm bead is about half a pixel on ``cm2-mini``, so this is the smallest
spot the grid draws cleanly) are scattered at densities from one to eighty per
100 × 100 pixels, no two closer than two radii (:mod:`svcode_bench.beads`). Each
field is imaged through the realistic regime's departed instrument (the nominal system
given to the methods) and reconstructed. A bead is found when a detection (a local
maximum above Otsu's threshold of the smoothed reconstruction) lies within its radius,
paired one to one; the width of each found bead is fitted and compared with the truth.
Counts are pooled over the seeds of a density. Methods: the bundled SV-CoDe model,
LSV-ADMM (``K`` = 3, 50 iterations, λ from the frame) and Wiener (the registry's
defaults); the phantom itself is scored too (the detector's ceiling).

Run: ``OMP_NUM_THREADS=1 python bench/beads.py`` (about 8 minutes on one thread with three
seeds; LSV-ADMM is the slow part, ``--no-admm`` skips it). ``--learned FILE ...`` adds a
trained MultiWienerNet or SV-FourierNet (``--only-learned --merge``: only those, the other
rows kept from the earlier report).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from probes import admm_auto, learned_methods, write_report

from svcode_bench.beads import BEAD_SIGMA, BeadScore, bead_phantom, score_beads
from svcode_bench.regimes import regime_simulator
from svcode_core.config import SystemConfig
from svcode_core.methods.build import build_reconstructor

RESULTS = Path(__file__).parent / "results"
#: beads per 100 × 100 object pixels
DENSITIES = (1.0, 3.0, 10.0, 20.0, 40.0, 80.0)
TRUTH = "truth (the phantom)"


def methods(system: SystemConfig, admm: bool, learned: list[Path], others: bool) -> dict:
    """Label → reconstruction of a raw frame: the bundled SV-CoDe, LSV-ADMM and Wiener
    (unless ``others`` is off), and a trained baseline per file of ``learned``."""
    found = {}
    if others:
        found["SV-CoDe (bundled)"] = _run(build_reconstructor("svcode", system))
        if admm:
            label, admm = admm_auto(system)
            found[label] = _run(admm)
        found["Wiener"] = _run(build_reconstructor("wiener", system))
    return found | dict(learned_methods(system, learned))


def _run(reconstructor):
    return lambda raw: reconstructor.reconstruct(raw).reconstruction


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="fields per density (default 3)")
    parser.add_argument("--no-admm", action="store_true", help="skip LSV-ADMM")
    parser.add_argument("--learned", type=Path, nargs="*", default=[],
                        help="trained MultiWienerNet / SV-FourierNet model files")
    parser.add_argument("--only-learned", action="store_true",
                        help="run only the --learned rows (with --merge: keep the others)")
    parser.add_argument("--out", type=Path, default=RESULTS / "beads",
                        help="output stem (.json and .md; default bench/results/beads)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of an earlier report at --out that this run does "
                        "not replace (same method)")
    args = parser.parse_args()
    system = SystemConfig.preset("cm2-mini")
    simulator = regime_simulator(system, "realistic")
    reconstructors = methods(system, not args.no_admm, args.learned, not args.only_learned)
    labels = [TRUTH, *reconstructors]
    scores = {label: {d: [] for d in DENSITIES} for label in labels}
    seconds = {label: {d: [] for d in DENSITIES} for label in labels}
    for index, density in enumerate(DENSITIES):
        for seed in range(args.seeds):
            field = bead_phantom(system.sub_view_size, density, seed=1000 * index + seed)
            frame = simulator.simulate(field.image, seed=700 + 10 * index + seed)
            frame = frame.measurement.astype(np.float32)
            images = {TRUTH: field.image}
            for label, reconstruct in reconstructors.items():
                begin = time.perf_counter()
                images[label] = reconstruct(frame)
                seconds[label][density].append(time.perf_counter() - begin)
            for label, image in images.items():
                scores[label][density].append(score_beads(image, field))
            print(f"density {density:g}, seed {seed} ({len(field.centres)} beads): " + ", ".join(
                f"{label} F1 {scores[label][density][-1].f1:.2f}" for label in labels),
                flush=True)
    rows = []
    for label in labels:
        for density in DENSITIES:
            pooled = BeadScore.pooled(scores[label][density]).as_dict()
            rows.append({
                "method": label, "density": density,  # NaN (undefined) as null in the JSON
                **{k: None if v != v else v for k, v in pooled.items()},
                "f1_per_seed": [s.f1 for s in scores[label][density]],
                "seconds": float(np.mean(seconds[label][density]))
                if seconds[label][density] else None})
    earlier = args.out.with_suffix(".json")
    if args.merge and earlier.exists():
        done = {row["method"] for row in rows}
        kept = [row for row in json.loads(earlier.read_text())["rows"] if row["method"] not in done]
        rows = [row for row in rows if row["method"] == TRUTH] + [
            row for row in kept + rows if row["method"] != TRUTH]
    write_report(rows, args.out, write_markdown)


def _cell(value: float | None, digits: int = 2) -> str:
    if value is None or not np.isfinite(value):
        return "–"
    return f"{round(value, digits) + 0.0:.{digits}f}"  # + 0.0: no "-0.00"


def write_markdown(report: dict, path: Path) -> None:
    rows = report["rows"]
    seeds = len(rows[0]["f1_per_seed"])
    lines = [
        "# Beads across density", "",
        "Generated by `bench/beads.py` (cm2-mini, equal beads of Gaussian sigma "
        f"{BEAD_SIGMA:g} px (radius {2 * BEAD_SIGMA:g} px) through the realistic regime's "
        f"departed instrument, the nominal system given, {seeds} field(s) per density, "
        f"{report['threads']} CPU thread(s)). Density: beads per 100 × 100 object pixels. "
        "A bead is found when a detection (a local maximum of the reconstruction, smoothed "
        "by sigma/2, above Otsu's threshold over its background) lies within its radius, "
        "paired one to one (Hungarian). Recall, precision and F1 pool the counts over the "
        "fields; precision is – when nothing was detected. Size error: median |fitted "
        "sigma / true sigma − 1| over the found beads; bias: the signed median (> 0: "
        "wider). Seconds: per frame, reconstruction only.", "",
        "| method | density | beads | found | recall | precision | F1 | size error | "
        "size bias | s/frame |",
        "|---" * 10 + "|"]
    for row in rows:
        lines.append(
            f"| {row['method']} | {row['density']:g} | {row['beads']} | {row['found']} | "
            f"{_cell(row['recall'])} | {_cell(row['precision'])} | {_cell(row['f1'])} | "
            f"{_cell(row['size_error'])} | {_cell(row['size_bias'])} | "
            f"{_cell(row['seconds'], 1)} |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
