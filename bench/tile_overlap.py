"""How much must planned tiles overlap? One SV-CoDe model file on held-out scenes, its
planned tiles overlapping by the receptive radius and by less.

Where a sub-view does not fit the memory budget as one tile, the planned tiles overlap by
the model's receptive radius (at most half a tile): at ``cm2-v2``'s scale, for a network on
a coarse grid, that computes every pixel about four times. The radius is what the
convolutions can reach, not what they use. This script reconstructs the benchmark's scenes
(at paper scale cells, neurons and ``ihc``, matched and realistic) with the planned tile
at the radius's overlap and at smaller ones, scores them against the truth, and finds the
smallest overlap whose mean PSNR in every regime is within 0.05 dB of the radius's
(seconds a frame after one warm-up frame each). ``--record`` writes it into the model file
(``overlap_check`` in its metadata), which the planned tiling then uses
(:func:`svcode_core.methods.svcode.tile_overlap`).

Run: ``OMP_NUM_THREADS=1 python bench/tile_overlap.py --weights FILE --system cm2-v2
[--record]`` (a paper-scale model: about half an hour on one thread).
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
from probes import add_check_arguments, add_scene_arguments, planned_scenes, write_report

from svcode_bench.regimes import make_scenes, regime_simulator
from svcode_core.config import SystemConfig
from svcode_core.evaluation.metrics import psnr, ssim
from svcode_core.methods.build import build_reconstructor
from svcode_core.methods.model_file import load_model, record_extra
from svcode_core.methods.svcode import AUTO_TOLERANCE_DB, plan_tiles, tile_overlap

#: overlaps tried below the radius (sub-view pixels; rounded up to the model's stride)
CANDIDATES = (256, 128, 64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--weights", type=Path, required=True, help="SV-CoDe model file")
    parser.add_argument("--system", default="cm2-v2", help="preset (default cm2-v2)")
    add_scene_arguments(parser)
    add_check_arguments(parser, "the chosen overlap", "tile_overlap")
    args = parser.parse_args()
    system = SystemConfig.preset(args.system)
    regimes, scene_names = planned_scenes(args, system)
    model, _ = load_model(args.weights, system)
    model.overlap_check = {}  # measured from the radius, whatever the file recorded
    tile, stride, batch = plan_tiles(model, system.sub_view_size)
    if stride == tile:
        raise SystemExit(f"{args.weights.name}: a whole {system.sub_view_size}-px sub-view is "
                         "one planned tile: there is no overlap to choose")
    radius = tile - stride
    overlaps = [radius, *(o for o in CANDIDATES if o < radius)]
    reconstructors = {o: build_reconstructor("svcode", system, args.weights, precision="fp32",
                                             tile_size=tile, stride=tile - o, batch_size=batch)
                      for o in overlaps}  # fmt: skip
    rows = []
    for regime in regimes:
        scenes = make_scenes(system, scene_names, regime_simulator(system, regime))
        if not rows:  # masks made and kept, kernels chosen: timed as in a recording
            for reconstructor in reconstructors.values():
                reconstructor.reconstruct(scenes[0].raw)
        for overlap, reconstructor in reconstructors.items():
            per_scene, seconds = {}, 0.0
            for scene in scenes:
                begin = time.perf_counter()
                estimate = reconstructor.reconstruct(scene.raw).reconstruction
                seconds += time.perf_counter() - begin
                per_scene[scene.name] = {"psnr": psnr(scene.truth, estimate, 1.0),
                                         "ssim": ssim(scene.truth, estimate, 1.0)}
            rows.append({"regime": regime, "overlap": overlap, "tiles": len(reconstructor.grid),
                         "psnr": float(np.mean([v["psnr"] for v in per_scene.values()])),
                         "ssim": float(np.mean([v["ssim"] for v in per_scene.values()])),
                         "seconds": seconds / len(scenes), "per_scene": per_scene})
            print(f"{regime}, overlap {overlap}: {rows[-1]['psnr']:.3f} dB, "
                  f"{rows[-1]['seconds']:.1f} s a frame", flush=True)
    check = overlap_check(rows, radius, tile)
    write_report(rows, args.out, lambda report, path: write_markdown(report, path, args.weights,
                                                                     system, check))
    print(f"smallest overlap within {AUTO_TOLERANCE_DB} dB: {check['overlap']} px")
    if args.record:
        record_extra(args.weights, overlap_check=check)
        model.overlap_check = check
        print(f"recorded in {args.weights}: planned tiles {plan_tiles(model, system.sub_view_size)}"
              f" (tile, stride, batch), overlap {tile_overlap(model)} px")


def overlap_check(rows: list[dict], radius: int, tile: int) -> dict:
    """The smallest overlap whose mean PSNR is within :data:`AUTO_TOLERANCE_DB` of the
    radius's in every regime, and what it was measured on."""
    regimes = list(dict.fromkeys(row["regime"] for row in rows))
    base = {row["regime"]: row["psnr"] for row in rows if row["overlap"] == radius}
    good = [o for o in dict.fromkeys(row["overlap"] for row in rows)
            if all(base[row["regime"]] - row["psnr"] <= AUTO_TOLERANCE_DB
                   for row in rows if row["overlap"] == o)]  # fmt: skip
    return {"overlap": min(good), "radius": radius, "tile": tile, "regimes": regimes,
            "scenes": list(rows[0]["per_scene"]), "date": datetime.date.today().isoformat()}


def write_markdown(report: dict, path: Path, weights: Path, system: SystemConfig,
                   check: dict) -> None:
    lines = [
        "# How much planned tiles must overlap", "",
        f"Generated by `bench/tile_overlap.py` ({system.name}, model `{weights.name}`, tiles "
        f"of {check['tile']} px, scenes {', '.join(check['scenes'])}, {report['threads']} CPU "
        "thread(s), float32). Mean PSNR / SSIM against the truth; seconds a frame as a ratio "
        f"within this run. The receptive radius's overlap is {check['radius']} px (capped at "
        f"half a tile); the smallest overlap within {AUTO_TOLERANCE_DB} dB of it in every "
        f"regime: **{check['overlap']} px**.", "",
        "| regime | overlap px | tiles | PSNR | SSIM | s / frame |", "|---|---|---|---|---|---|"]
    for row in report["rows"]:
        lines.append(f"| {row['regime']} | {row['overlap']} | {row['tiles']} | "
                     f"{row['psnr']:.3f} | {row['ssim']:.4f} | {row['seconds']:.1f} |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
