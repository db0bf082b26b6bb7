"""The outer ring against the centre on the same content (bench/results/ring_gap.md).

The benchmark's centre and ring PSNRs compare different parts of each scene. Here every
scene of the benchmark (the same truths and noise seeds) is also imaged moved by half
the field along rows, columns and both (:mod:`svcode_bench.field_position`),
so the same content is reconstructed once in the centre and once in the outer ring. For
the bundled SV-CoDe model, every ``--weights`` model and LSV-ADMM (``K`` = 3,
``--admm-iterations``), per regime: the zone PSNRs in place (as in ``svcode bench``) and
the same-content PSNRs at the centre and in the ring, scene means. ``--tile`` runs
SV-CoDe on tiles of that size at half-tile stride instead of its planned tiling,
``--pool-window`` pools its channel attention over that many pixels,
``--refine-periphery`` refines its periphery with that many LSV-ADMM iterations.

Run: ``OMP_NUM_THREADS=1 python bench/ring_gap.py [--weights FILE ...]`` (about half a
minute per model and regime on one thread; LSV-ADMM at 50 iterations about 10 minutes
per regime, ``--no-admm`` skips it). ``--system cm2-v2`` measures the paper-scale model on
the paper-scale plan's three scenes, LSV-ADMM at 10 iterations (on one thread beside
another job about 15 minutes per regime for SV-CoDe, 30 for LSV-ADMM).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from probes import (
    Reconstruct,
    add_system_argument,
    admm_iterations,
    admm_method,
    earlier_rows,
    learned_methods,
    plan_truths,
    svcode_methods,
    write_report,
)

from svcode_bench.field_position import (
    edge_strip_width,
    half_field_shifts,
    moved_scene,
    same_content_zones,
)
from svcode_bench.regimes import REGIMES, regime_simulator
from svcode_core.config import load_system
from svcode_core.evaluation.metrics import edge_columns, image_quality
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.psf_io import model_psfs
from svcode_core.physics.simulate import Simulator

RESULTS = Path(__file__).parent / "results"
#: the moves of half_field_shifts, by where they take the centre's content
MOVES = ("rows", "columns", "corners")
#: the columns move, split at the edge strips that only six of the nine lenses see
COLUMN_PARTS = ("column_strips", "columns_inside")


def scene_row(reconstruct: Reconstruct, simulator: Simulator, index: int,
              truth: np.ndarray) -> dict[str, float]:
    """One scene: zone PSNRs in place and the same-content comparison."""
    begin = time.perf_counter()

    def image(scene: np.ndarray) -> np.ndarray:  # the benchmark's noise seed for the scene
        raw = simulator.simulate(scene, seed=100 + index).measurement
        return np.asarray(reconstruct(raw), dtype=np.float64)

    shifts = half_field_shifts(len(truth))
    estimate = image(truth)
    moved = {shift: image(moved_scene(truth, shift)) for shift in shifts}
    quality = image_quality(truth, estimate, data_range=1.0)
    same = same_content_zones(truth, estimate, moved)
    by_move = {f"same_gap_{name}": same_content_zones(truth, estimate, {shift: moved[shift]}).gap
               for name, shift in zip(MOVES, shifts, strict=True)}
    columns = {shifts[1]: moved[shifts[1]]}
    strips = edge_columns(len(truth), edge_strip_width(simulator.system))
    in_strips = same_content_zones(truth, estimate, columns, ring=strips)
    by_move["same_gap_column_strips"] = in_strips.gap
    by_move["strips_content_centre"] = in_strips.centre  # the gap's two ends, in dB
    by_move["strips_content_strips"] = in_strips.ring
    by_move["same_gap_columns_inside"] = same_content_zones(truth, estimate, columns,
                                                            ring=~strips).gap
    return {"psnr": quality["psnr"], "zone_centre": quality["psnr_centre"],
            "zone_ring": quality["psnr_ring"], "same_centre": same.centre,
            "same_ring": same.ring, "same_gap": same.gap, **by_move,
            "seconds": time.perf_counter() - begin}


def regime_rows(regime: str, simulator: Simulator, truths: dict[str, tuple[int, np.ndarray]],
                methods: list[tuple[str, Reconstruct]]) -> list[dict]:
    """One row per method in one regime: scene means and the per-scene values."""
    rows = []
    for label, reconstruct in methods:
        per_scene = {}
        for name, (index, truth) in truths.items():
            per_scene[name] = scene_row(reconstruct, simulator, index, truth)
            print(f"[{regime}] {label}, {name}: same-content gap "
                  f"{per_scene[name]['same_gap']:.2f} dB", flush=True)
        keys = next(iter(per_scene.values())).keys()
        mean = {key: float(np.mean([v[key] for v in per_scene.values()])) for key in keys}
        rows.append({"regime": regime, "method": label, **mean, "per_scene": per_scene})
    return rows


def write_markdown(report: dict, path: Path) -> None:
    """Scene means per regime and method, then the gaps per scene."""
    lines = [
        "# The outer ring against the centre on the same content", "",
        f"Generated by `bench/ring_gap.py` ({report['system']}, the benchmark's scenes and "
        "noise seeds, "
        f"{report['threads']} CPU thread(s)). *Zone*: the benchmark's centre (normalised "
        "field radius below 0.5) and outer-ring (above 0.8) PSNR of each scene in place: "
        "different content in each zone. *Same content*: every scene also imaged moved by "
        "half the field along rows, columns and both (wrapping round), and the PSNR of the "
        "content pixels that a move takes from one zone to the other, where they sat in "
        "the centre and where they sat in the ring. Scene means, dB.", "",
        "| regime | method | PSNR | zone centre | zone ring | zone gap | same-content centre "
        "| same-content ring | **same-content gap** |", "|---" * 9 + "|"]
    for row in report["rows"]:
        lines.append(
            f"| {row['regime']} | {row['method']} | {row['psnr']:.2f} | {row['zone_centre']:.2f} "
            f"| {row['zone_ring']:.2f} | {row['zone_centre'] - row['zone_ring']:.2f} "
            f"| {row['same_centre']:.2f} | {row['same_ring']:.2f} | **{row['same_gap']:.2f}** |")
    lines += ["", "## Same-content gap by move (scene means, dB)", "",
              "Moved along the rows the centre's content lands in the top and bottom rows "
              "(which one lens row loses off the sensor), along the columns in the left and "
              "right edges, along both in the corners. The columns move split: the "
              f"{report['strip']}-px edge strips (which three of the nine lenses lose off the "
              "sensor) and the ring's columns inside them; the last column gives the strips' "
              "gap's two ends, the PSNR of the content that lands in the strips where it sat "
              "in the centre and in the strips (– where the report predates it).", "",
              "| regime | method | " + " | ".join((*MOVES, *COLUMN_PARTS)).replace("_", " ")
              + " | strips' content: centre → strips |",
              "|---" * (3 + len(MOVES) + len(COLUMN_PARTS)) + "|"]
    for row in report["rows"]:
        gaps = " | ".join(f"{row[f'same_gap_{move}']:.2f}" for move in (*MOVES, *COLUMN_PARTS))
        ends = (f"{row['strips_content_centre']:.2f} → {row['strips_content_strips']:.2f}"
                if "strips_content_centre" in row else "–")
        lines.append(f"| {row['regime']} | {row['method']} | {gaps} | {ends} |")
    scenes = list(report["rows"][0]["per_scene"]) if report["rows"] else []
    lines += ["", "## Same-content gap per scene (dB)", "",
              "| regime | method | " + " | ".join(scenes) + " |", "|---" * (2 + len(scenes)) + "|"]
    for row in report["rows"]:
        gaps = " | ".join(f"{row['per_scene'][s]['same_gap']:.2f}" for s in scenes)
        lines.append(f"| {row['regime']} | {row['method']} | {gaps} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    """The script; ``argv`` its options (default: the command line's)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_system_argument(parser)
    parser.add_argument("--weights", type=Path, nargs="*", default=[],
                        help="further SV-CoDe model files (the bundled one always runs)")
    parser.add_argument("--learned", type=Path, nargs="*", default=[],
                        help="trained MultiWienerNet / SV-FourierNet model files")
    parser.add_argument("--no-svcode", action="store_true",
                        help="skip the SV-CoDe rows (with --merge: keep the earlier ones)")
    parser.add_argument("--regimes", nargs="+", default=["matched", "realistic"],
                        choices=list(REGIMES), help="default: matched realistic")
    parser.add_argument("--tile", type=int, default=None,
                        help="SV-CoDe tiles of TILE px at stride TILE/2 (default: planned)")
    parser.add_argument("--pool-window", type=int, default=None,
                        help="SV-CoDe's channel attention pooled over this many pixels")
    parser.add_argument("--refine-periphery", type=int, default=0, metavar="N",
                        help="SV-CoDe's periphery refined by N LSV-ADMM iterations")
    parser.add_argument("--admm-iterations", type=int, default=None,
                        help="LSV-ADMM iterations (default 50; 10 at paper scale)")
    parser.add_argument("--no-admm", action="store_true", help="skip LSV-ADMM")
    parser.add_argument("--out", type=Path, default=RESULTS / "ring_gap",
                        help="output stem (.json and .md; default bench/results/ring_gap)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of an earlier report at --out that this run does "
                        "not replace (same regime and method)")
    args = parser.parse_args(argv)
    system = load_system(args.system)
    kept = earlier_rows(args.out, system, "ring_gap") if args.merge else []
    psfs = model_psfs(system)
    nominal = Simulator(system, CM2Operator.from_psfs(system, psfs))
    options, knob = {"pool_window": args.pool_window}, ""
    if args.tile is not None:
        options |= {"tile_size": args.tile, "stride": args.tile // 2}
        knob += f", tile {args.tile}, stride {args.tile // 2}"
    if args.pool_window is not None:
        knob += f", pool {args.pool_window}"
    if args.refine_periphery:
        options |= {"refine_periphery": args.refine_periphery}
        knob += f", refine {args.refine_periphery}"
    methods = [] if args.no_svcode else svcode_methods(system, args.weights, knob, **options)
    methods += learned_methods(system, args.learned)
    if not args.no_admm:
        methods.append(admm_method(system, args.admm_iterations or admm_iterations(system)))
    truths = plan_truths(system)
    rows = []
    for regime in args.regimes:  # each regime's instrument is built once for every method
        simulator = regime_simulator(system, regime, nominal)
        rows += regime_rows(regime, simulator, truths, methods)
    done = {(row["regime"], row["method"]) for row in rows}
    rows = [row for row in kept if (row["regime"], row["method"]) not in done] + rows
    rows.sort(key=lambda row: list(REGIMES).index(row["regime"]))
    write_report(rows, args.out, write_markdown, system=system.name,
                 strip=edge_strip_width(system))


if __name__ == "__main__":
    main()
