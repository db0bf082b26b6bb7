"""Training data against validation PSNR, SV-CoDe (patches) against the learned baselines
(whole frames), on one validation set (bench/results/data_efficiency.md).

The seed paper claims SV-CoDe needs far less training data than the spatially varying
networks before it. Every method here learned from the same 432 training frames of the
v2 data (``runs/data-v2``: cm2-mini through the realistic departures, fresh noise at every
use), SV-CoDe from 96² patches and the baselines from whole 384² frames; data is counted
as object pixels of the training targets seen. Every model is scored the way the
baselines' validation is: the 48 whole validation frames with the trainer's fixed noise
(seed 0), reconstructed through the product's own path (each frame brought to one
exposure level and scaled back), PSNR and SSIM against the object per frame, averaged.

SV-CoDe's points are the bundled model's first training run at epochs 10, 15 and 19
(their files are read from the git history, where that run's resume states were kept)
and the bundled model itself (37 epochs of 3200 patches). A baseline's points are its
own validation log (``training/baselines/ARCH/log.csv``, the same frames and noise,
exposure gain as its trainer measured it: ``training/baselines/README.md``), and its final
file when given with ``--learned``, scored here as the others are.

Run: ``OMP_NUM_THREADS=1 python bench/data_efficiency.py --learned FILE ...`` (about 6
CPU-minutes; needs the v2 data, which ``training/resume.sh`` makes); ``--merge`` keeps an
earlier report's rows for files not given now.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import torch
from probes import Reconstruct, learned_methods, write_report

from svcode_core.config import SystemConfig
from svcode_core.methods import registry
from svcode_core.methods.build import build_reconstructor
from svcode_core.physics.geometry import crop_to_sensor
from svcode_core.pretrained import require_bundled_weights
from svcode_core.training import TrainingData
from svcode_core.training.loss import psnr_per_sample, ssim_per_sample
from svcode_core.training.sampler import FrameDataset

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results"
PATCH_PIXELS = 3200 * 96**2  # an SV-CoDe epoch of the bundled model's recipes
FRAME_PIXELS = 384**2
RUN = "training/cm2-mini-v3/context-scratch/best.safetensors"
#: the bundled model's first run: (commit holding its best file, epochs trained)
LINEAGE = (("b580b66", 10), ("66fff74", 15), ("345a14e", 19))
#: the first run, then the five fine-tunings up to the kept epoch
BUNDLED_EPOCHS = 20 + 6 + 7 + 4 + 4 + 4


def validation_frames(data: TrainingData) -> list[tuple[np.ndarray, torch.Tensor]]:
    """The baselines' validation frames as raw sensor frames, with their objects."""
    frames = FrameDataset(data, data.val_frames, fixed_noise=True, seed=0,
                          normalise_exposure=True)  # fmt: skip
    out = []
    for item in (frames[i] for i in range(len(frames))):
        gain = float(item["gain"])
        raw = crop_to_sensor(item["frame"] / gain, data.system).numpy()
        out.append((raw, item["object"] / gain))
    return out


def score(reconstruct: Reconstruct, frames) -> tuple[float, float]:
    """Mean PSNR and SSIM over the frames, as the trainer's validation computes them."""
    psnr, ssim = [], []
    for raw, truth in frames:
        estimate = torch.from_numpy(reconstruct(raw))[None, None]
        psnr.append(float(psnr_per_sample(estimate, truth[None])))
        ssim.append(float(ssim_per_sample(estimate, truth[None])))
    return float(np.mean(psnr)), float(np.mean(ssim))


def _svcode(system: SystemConfig, path: Path) -> Reconstruct:
    reconstructor = build_reconstructor("svcode", system, path)
    return lambda raw: reconstructor.reconstruct(raw).reconstruction


def baseline_log(path: Path) -> list[dict]:
    """A baseline's validation curve: (epoch, target pixels, PSNR, SSIM) rows."""
    with path.open() as handle:
        rows = list(csv.DictReader(handle))
    return [{"epoch": int(r["epoch"]), "pixels": int(r["epoch"]) * 432 * FRAME_PIXELS,
             "psnr": float(r["val_recon_psnr"]), "ssim": float(r["val_recon_ssim"])}
            for r in rows]  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT / "runs/data-v2")
    parser.add_argument("--learned", type=Path, nargs="*", default=[],
                        help="trained MultiWienerNet / SV-FourierNet files to score")
    parser.add_argument("--out", type=Path, default=RESULTS / "data_efficiency")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of an earlier report at --out that this run does "
                        "not replace (same method and point: e.g. a baseline scored before, "
                        "whose file is not given now)")
    args = parser.parse_args()
    data = TrainingData(args.data)
    system = SystemConfig.preset("cm2-mini")
    frames = validation_frames(data)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for commit, epochs in LINEAGE:
            path = Path(folder) / f"epoch{epochs}.safetensors"
            path.write_bytes(subprocess.run(["git", "show", f"{commit}:{RUN}"], cwd=ROOT,
                                            check=True, capture_output=True).stdout)
            psnr, ssim = score(_svcode(system, path), frames)
            rows.append({"method": "SV-CoDe", "point": f"first run, epoch {epochs}",
                         "pixels": epochs * PATCH_PIXELS, "psnr": psnr, "ssim": ssim})
            print(rows[-1], flush=True)
    psnr, ssim = score(_svcode(system, require_bundled_weights(system)), frames)
    rows.append({"method": "SV-CoDe", "point": "bundled model",
                 "pixels": BUNDLED_EPOCHS * PATCH_PIXELS, "psnr": psnr, "ssim": ssim})
    for arch in ("multiwiener", "fouriernet"):
        log = ROOT / "training/baselines" / arch / "log.csv"
        if log.exists():
            label = registry.method(arch).label
            rows += [{"method": label, "point": f"epoch {r['epoch']} (its validation log)",
                      **{k: r[k] for k in ("pixels", "psnr", "ssim")}}
                     for r in baseline_log(log)]  # fmt: skip
    for label, reconstruct in learned_methods(system, args.learned):
        method, path = label.split(": ", 1)
        psnr, ssim = score(reconstruct, frames)
        rows.append({"method": method, "point": f"{path} (its best epoch), scored here",
                     "pixels": None, "psnr": psnr, "ssim": ssim})
    earlier = args.out.with_suffix(".json")
    if args.merge and earlier.exists():
        done = {(row["method"], row["point"]) for row in rows}
        rows += [row for row in json.loads(earlier.read_text())["rows"]
                 if (row["method"], row["point"]) not in done]
    write_report(rows, args.out, write_markdown)


def write_markdown(report: dict, path: Path) -> None:
    lines = [
        "# Training data against validation PSNR", "",
        "Generated by `bench/data_efficiency.py` (its docstring says how; "
        f"{report['threads']} CPU thread(s)). Every model learned from the same 432 "
        "training frames of the v2 data (cm2-mini through the realistic departures); data "
        "is the object pixels of the training targets seen (SV-CoDe: 96² patches, the "
        "baselines: whole 384² frames). Scored on the same 48 whole validation frames with "
        "the same noise: PSNR and SSIM per frame against the object, averaged.", "",
        "| method | point | target pixels seen (10⁸) | validation PSNR (dB) | SSIM |",
        "|---|---|---|---|---|"]
    for row in report["rows"]:
        pixels = "–" if row["pixels"] is None else f"{row['pixels'] / 1e8:.1f}"
        lines.append(f"| {row['method']} | {row['point']} | {pixels} | {row['psnr']:.2f} | "
                     f"{row['ssim']:.3f} |")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
