"""Stability of the bundled SV-CoDe model on extreme frames (the network's rows of
bench/results/stability.md).

Runs :func:`svcode_bench.stability.stability_cases` for ``cm2-mini`` (zero, constant,
saturated, single-pixel, 1e4 dynamic range, 1 to 100 photons, bf16 and fp16) through the
bundled model on the CPU and writes bench/results/stability_network.json and the network
section of bench/results/stability.md (between its ``network`` markers; the rest of the
file is kept). A case passes when its output is finite or it raised a clear error.

Run: ``OMP_NUM_THREADS=2 python bench/stability.py`` (about 2 to 4 minutes on 1 to 2 cores).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from svcode_bench.stability import run_case, stability_cases
from svcode_core.config import SystemConfig
from svcode_core.methods.svcode import Reconstructor
from svcode_core.physics.simulate import Simulator

RESULTS = Path(__file__).parent / "results"
BEGIN, END = "<!-- network: begin (bench/stability.py) -->", "<!-- network: end -->"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--markdown-only", action="store_true",
                        help="rewrite the markdown from the saved JSON without running")
    if parser.parse_args().markdown_only:
        saved = json.loads((RESULTS / "stability_network.json").read_text())
        _write_markdown(saved["rows"], saved["meta"])
        return
    system = SystemConfig.preset("cm2-mini")
    start = time.perf_counter()
    cases = stability_cases(Simulator(system))
    print(f"{len(cases)} cases simulated in {time.perf_counter() - start:.1f} s", flush=True)
    built: dict[tuple[str, bool], Reconstructor] = {}

    def build(precision: str, skip_empty: bool) -> Reconstructor:
        key = (precision, skip_empty)
        if key not in built:
            built[key] = Reconstructor.pretrained(system, precision=precision,
                                                  skip_empty=skip_empty)  # fmt: skip
        return built[key]

    rows = []
    for case in cases:
        rows.append(run_case(build, case))
        print(_cells(rows[-1]), flush=True)
    meta = {"system": system.name, "threads": torch.get_num_threads(), "torch": torch.__version__}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "stability_network.json").write_text(
        json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n"
    )
    _write_markdown(rows, meta)


def _write_markdown(rows: list[dict], meta: dict) -> None:
    """Replace the network section of stability.md (between the markers)."""
    report = RESULTS / "stability.md"
    text = report.read_text(encoding="utf-8")
    head, rest = text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    report.write_text(head + BEGIN + "\n" + _markdown(rows, meta) + END + tail, encoding="utf-8")
    print(f"wrote {report}")


def _passed(row: dict) -> str:
    if "error" in row:
        return "clear error"
    return "finite" if row["finite"] else "**NaN/Inf**"


def _cells(row: dict) -> str:
    if "error" in row:
        return (f"| {row['name']} | {row['precision']} | clear error: “{row['error']}” "
                f"| | | | | {row['seconds']:.1f} |")  # fmt: skip
    if not row["finite"]:
        return (f"| {row['name']} | {row['precision']} | **NaN or Inf** | | | "
                f"| {row['tiles_run']} | {row['seconds']:.1f} |")  # fmt: skip
    other = []
    if "peak_offset" in row:
        other.append(f"peak {row['peak_offset']:.1f} px from the pixel")
    if "square_mean" in row:
        other.append(f"square mean {row['square_mean']:.3f}, floor mean {row['floor_mean']:.2e}")
    quality = f"{row['psnr']:.2f}" if "psnr" in row else ""
    return (f"| {row['name']} | {row['precision']} | {_passed(row)} | "
            f"{row['min']:.3g} / {row['max']:.3g} / {row['mean']:.3g} | {quality} | "
            f"{'; '.join(other)} | {row['tiles_run']} | {row['seconds']:.1f} |")  # fmt: skip


def _markdown(rows: list[dict], meta: dict) -> str:
    passed = sum("error" in r or r["finite"] for r in rows)
    lines = [
        "## The SV-CoDe network (bundled `cm2-mini` model)",
        "",
        f"Made by `bench/stability.py` (`OMP_NUM_THREADS=2 python bench/stability.py`; figures "
        f"in `stability_network.json`), CPU, {meta['threads']} thread(s), torch "
        f"{meta['torch']}. Frames of the `cm2-mini` system (480×640), simulated through its "
        "pupil-model operator without noise unless stated; the `cells` phantom (seed 0) "
        "for the noisy scenes. Empty tiles are skipped unless stated. A case passes when the "
        f"output is finite or a clear error is raised: **{passed} of {len(rows)} pass**. "
        "The same battery runs on a small random SV-CoDe model of the 48-pixel `tiny` "
        "system in `tests/test_stability.py` (`test_network_battery`).",
        "",
        "| case | precision | result | min / max / mean | PSNR (dB) | other | tiles run "
        "| time (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [_cells(row) for row in rows]
    lines += [
        "",
        "PSNR: against the object, data range 1 (for the single pixel it mostly counts the "
        "zero background). `peak`: distance from the object's pixel to the brightest output "
        "pixel. `square`/`floor` mean: output mean inside the bright square (truth 1) and "
        "outside it (truth 1e-4). Times are wall-clock on a CPU shared with other jobs.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
