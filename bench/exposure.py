"""Exposure and photon sweeps: the same scenes read at other gains, and with fewer photons
(bench/results/exposure.md).

*Exposure*: every benchmark scene of the realistic regime (the benchmark's truths and noise
seeds) is simulated once, and the recorded frame multiplied by ``s`` (the same photons
read with a lower ADC gain); each method reconstructs ``s · frame`` and the result is
divided by ``s`` before it is scored against the truth. A method that is equivariant to
the scale scores the same at every ``s``. *Photons*: the scene made dimmer by a factor
``f`` before it is imaged by the same camera (fewer photo-electrons: relatively more shot
and read noise), reconstructed as recorded and divided by ``f``. Methods: the bundled
SV-CoDe model with its exposure normalisation (the default), the same model fed the
frames as they are (``normalise_exposure=False``), every ``--learned`` MultiWienerNet or
SV-FourierNet file, and LSV-ADMM (``K`` = 3, 50 iterations, 10 at paper scale, λ from the
frame).

Run: ``OMP_NUM_THREADS=1 python bench/exposure.py`` (about 15 minutes on one thread;
``--no-admm`` skips LSV-ADMM, the slow part). ``--system cm2-v2`` measures the
paper-scale model on the paper-scale plan's three scenes (with ``--normalised-only``
about half an hour on two threads). ``--merge`` keeps an earlier report's rows of the
methods this run leaves out, e.g. ``--no-svcode --no-admm --learned FILE --merge`` adds a
learned baseline's rows (about a minute).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from probes import (
    Reconstruct,
    add_system_argument,
    admm_auto,
    earlier_rows,
    learned_methods,
    plan_truths,
    write_report,
)

from svcode_bench.regimes import regime_simulator
from svcode_core.config import SystemConfig, load_system
from svcode_core.evaluation.metrics import psnr
from svcode_core.methods.build import build_reconstructor

RESULTS = Path(__file__).parent / "results"
SCALES = (1.0, 0.2, 0.05, 0.02)
#: the scenes' brightness as fractions of the benchmark's (fewer photons)
PHOTON_FRACTIONS = (1.0, 0.25, 0.0625)


def methods(system: SystemConfig, args: argparse.Namespace) -> dict[str, Reconstruct]:
    found = {}
    if not args.no_svcode:
        found["SV-CoDe (bundled)"] = build_reconstructor("svcode", system)
        if not args.normalised_only:
            found["SV-CoDe, frames as they are"] = build_reconstructor(
                "svcode", system, normalise_exposure=False)
    if not args.no_admm:
        label, reconstructor = admm_auto(system)
        found[label] = reconstructor
    found = {label: lambda raw, r=r: r.reconstruct(raw).reconstruction
             for label, r in found.items()}
    return found | dict(learned_methods(system, args.learned))


def main(argv: list[str] | None = None) -> None:
    """The script; ``argv`` its options (default: the command line's)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_system_argument(parser)
    parser.add_argument("--no-admm", action="store_true", help="skip LSV-ADMM")
    parser.add_argument("--no-svcode", action="store_true", help="skip the SV-CoDe rows")
    parser.add_argument("--normalised-only", action="store_true",
                        help="skip the model fed the frames as they are")
    parser.add_argument("--learned", type=Path, nargs="*", default=[],
                        help="trained MultiWienerNet / SV-FourierNet model files")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of an earlier report at --out of the methods "
                        "this run does not measure")
    parser.add_argument("--out", type=Path, default=RESULTS / "exposure",
                        help="output stem (.json and .md; default bench/results/exposure)")
    args = parser.parse_args(argv)
    system = load_system(args.system)
    kept = earlier_rows(args.out, system, "exposure") if args.merge else []
    simulator = regime_simulator(system, "realistic")
    realistic = simulator.departures
    truths = plan_truths(system)
    recorded = {fraction: {} for fraction in PHOTON_FRACTIONS}
    for fraction in PHOTON_FRACTIONS:
        for name, (index, truth) in truths.items():
            recorded[fraction][name] = simulator.simulate(
                truth * np.float32(fraction), seed=100 + index).measurement.astype(np.float32)
    rows = []
    measured = methods(system, args)
    for label, reconstruct in measured.items():
        sweeps = [("exposure", s, 1.0) for s in SCALES]
        sweeps += [("photons", 1.0, f) for f in PHOTON_FRACTIONS[1:]]
        if label.startswith("LSV-ADMM"):  # scale-equivariant by construction: two points
            sweeps = [("exposure", 1.0, 1.0), ("exposure", 0.05, 1.0),
                      *(("photons", 1.0, f) for f in PHOTON_FRACTIONS[1:])]
        for sweep, scale, fraction in sweeps:
            begin, per_scene = time.perf_counter(), {}
            for name, (_, truth) in truths.items():
                frame = recorded[fraction][name] * np.float32(scale)
                estimate = reconstruct(frame) / np.float32(scale * fraction)
                per_scene[name] = psnr(truth, estimate, 1.0)
            seconds = (time.perf_counter() - begin) / len(truths)
            rows.append({"method": label, "sweep": sweep, "scale": scale,
                         "photons": realistic.photons * fraction,
                         "psnr": float(np.mean(list(per_scene.values()))),
                         "seconds": seconds, "per_scene": per_scene})
            print(f"{label}: {sweep} s={scale} photons={realistic.photons * fraction:g}: "
                  f"{rows[-1]['psnr']:.2f} dB", flush=True)
    rows = [row for row in kept if row["method"] not in measured] + rows
    write_report(rows, args.out, write_markdown, system=system.name)


def write_markdown(report: dict, path: Path) -> None:
    rows = report["rows"]
    scenes = list(rows[0]["per_scene"])
    lines = [
        "# Exposure and photon sweeps", "",
        f"Generated by `bench/exposure.py` ({report['system']}, realistic regime, the benchmark's "
        f"{len(scenes)} scenes and noise seeds, {report['threads']} CPU thread(s)). PSNR "
        "(dB) of the reconstruction divided by the frame's scale, against the truth; "
        "scene means, then per scene.", "",
        "| method | sweep | frame scale | photo-electrons at intensity 1 | PSNR | s / frame "
        "| " + " | ".join(scenes) + " |", "|---" * (6 + len(scenes)) + "|"]
    for row in rows:
        lines.append(
            f"| {row['method']} | {row['sweep']} | {row['scale']:g} | {row['photons']:g} "
            f"| **{row['psnr']:.2f}** | {row['seconds']:.2f} | "
            + " | ".join(f"{row['per_scene'][s]:.2f}" for s in scenes) + " |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
