"""The finest line pair each method resolves at the centre, mid-field, ring and corner
(bench/results/resolution.md).

A bar target (:mod:`svcode_bench.resolution`: three vertical and three horizontal
bars per period, at four field positions at once) of every period is imaged in each regime
asked (default: the nominal instrument, ``matched``, and the ``realistic`` regime's departed
one; the methods are given the nominal system; one noise seed per period) and
reconstructed; a group is resolved when the dip between its bars reaches the Rayleigh dip
(26.4 %), in both orientations. Methods: the bundled SV-CoDe model and LSV-ADMM (``K`` =
3, 50 iterations, 10 at paper scale, λ from the frame); ``--refine-periphery N`` adds the
bundled model with its periphery refined. The matched regime tells which losses across the
field are the instrument's (LSV-ADMM, which inverts the whole sensor, loses them too).

Run: ``OMP_NUM_THREADS=1 python bench/resolution.py`` (about 6 minutes on one thread).
``--system cm2-v2`` measures the paper-scale model, the periods and the groups' spacing
scaled with its PSF (about half an hour on one thread beside another job).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from probes import add_system_argument, admm_auto, write_report

from svcode_bench.regimes import REGIMES, regime_simulator
from svcode_bench.resolution import (
    GROUP_GAP,
    PERIODS_AIRY_RADIUS,
    POSITIONS,
    RAYLEIGH_DIP,
    bar_dip,
    bar_target,
    finest_resolved,
    periods_for,
)
from svcode_core.config import SystemConfig
from svcode_core.methods.build import build_reconstructor

RESULTS = Path(__file__).parent / "results"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_system_argument(parser)
    parser.add_argument("--weights", type=Path, nargs="*", default=[],
                        help="further SV-CoDe model files")
    parser.add_argument("--refine-periphery", type=int, default=0, metavar="N",
                        help="also the bundled model with its periphery refined by N "
                             "LSV-ADMM iterations")
    parser.add_argument("--no-admm", action="store_true", help="skip LSV-ADMM")
    parser.add_argument("--regimes", nargs="+", default=["matched", "realistic"],
                        choices=list(REGIMES), help="instruments imaged (default matched "
                        "realistic)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=RESULTS / "resolution",
                        help="output stem (.json and .md; default bench/results/resolution)")
    args = parser.parse_args()
    system = SystemConfig.preset(args.system)
    periods = periods_for(system.optics.airy_radius)
    gap = GROUP_GAP * system.optics.airy_radius / PERIODS_AIRY_RADIUS
    methods = {"SV-CoDe (bundled)": build_reconstructor("svcode", system)}
    if args.refine_periphery:
        methods[f"SV-CoDe (bundled), refine {args.refine_periphery}"] = build_reconstructor(
            "svcode", system, refine_periphery=args.refine_periphery)
    for path in args.weights:
        methods[f"SV-CoDe: {path}"] = build_reconstructor("svcode", system, path)
    if not args.no_admm:
        label, admm = admm_auto(system)
        methods[label] = admm
    targets = [bar_target(system.sub_view_size, period, gap=gap) for period in periods]
    rows = [_row("truth", "–", [target for target, _ in targets], targets, periods)]
    for regime in args.regimes:
        simulator = regime_simulator(system, regime)
        frames = [simulator.simulate(target, seed=300 + index).measurement.astype(np.float32)
                  for index, (target, _) in enumerate(targets)]
        for label, rec in methods.items():
            images = [rec.reconstruct(frame).reconstruction for frame in frames]
            rows.append(_row(label, regime, images, targets, periods))
            print(f"{regime}, {label}: finest " + ", ".join(
                f"{n} {v}" for n, v in rows[-1]["finest"].items()), flush=True)
    write_report(rows, args.out, write_markdown, system=system.name, periods=periods,
                 pixel_um=system.object_pixel_um)


def _row(label: str, regime: str, images: list[np.ndarray], targets: list, periods: list
         ) -> dict:  # fmt: skip
    """The report row of one method in one regime: its dips and finest periods."""
    dips = {name: {} for name in POSITIONS}
    for image, (_, groups), period in zip(images, targets, periods, strict=True):
        for name, pair in groups.items():
            dips[name][period] = min(bar_dip(image, group) for group in pair)
    return {"method": label, "regime": regime,
            "finest": {name: finest_resolved(by_period) for name, by_period in dips.items()},
            "dips": {name: {str(p): v for p, v in by_period.items()}
                     for name, by_period in dips.items()}}


def write_markdown(report: dict, path: Path) -> None:
    names, periods = list(POSITIONS), report["periods"]
    lines = [
        "# Resolution across the field", "",
        f"Generated by `bench/resolution.py` ({report['system']}, a bar target at four "
        "field positions imaged in each regime below (matched: the nominal instrument; "
        "the others: their departed instruments), the methods given the nominal system, "
        f"{report['threads']} CPU thread(s)). Finest line-pair period resolved (object "
        f"pixels of {report['pixel_um']:g} µm; a dip of at least {RAYLEIGH_DIP:.1%} between "
        "bars in both orientations, every coarser period resolved too; – none). Positions "
        "in normalised field coordinates (row, col): " + ", ".join(
            f"{n} {POSITIONS[n]}" for n in names) + ".", "",
        "| regime | method | " + " | ".join(names) + " |", "|---" * (2 + len(names)) + "|"]
    for row in report["rows"]:
        cells = ["–" if row["finest"][n] is None else f"{row['finest'][n]:g}" for n in names]
        lines.append(f"| {row['regime']} | {row['method']} | " + " | ".join(cells) + " |")
    lines += ["", "## Dip between bars (the smaller of the two orientations)", "",
              "| regime | method | position | " + " | ".join(f"{p:g} px" for p in periods)
              + " |", "|---" * (3 + len(periods)) + "|"]
    for row in report["rows"]:
        for name in names:
            lines.append(f"| {row['regime']} | {row['method']} | {name} | " + " | ".join(
                f"{row['dips'][name][str(p)]:.2f}" for p in periods) + " |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
