"""How far along the lens rows the readings that determine the left edge strip lie.

A pointwise linear fit of each lens's demixed image (the training target) in the left
16-px strip of the sub-view from the padded frame's readings at column ``u + k·pitch``
(rows ``r + a·pitch`` of the three lens rows), for ``k`` from -1 up to a reach; one fit
per lens and 48-row band, on 80 training frames of ``runs/data-v2``, scored on 24
validation frames as the relative squared error ``Σ (fit − target)² / Σ target²``.
Columns 64-79 are the comparison away from the edge.

Usage (from the repository root, after ``training/resume.sh`` made the data):
``python training/cm2-mini-v3/strip_reach.py``; about 15 s on one thread.
"""

from __future__ import annotations

import json

import numpy as np
import torch

from svcode_core.config import SystemConfig
from svcode_core.physics.geometry import assemble_frame, lens_pitch

DATA = "runs/data-v2"
LENSES = (1, 4, 2, 5)  # middle and right lens columns, top two rows: they see the strip
BAND = 48


def readings(frame: np.ndarray, rows: np.ndarray, cols: np.ndarray, reach: int,
             pitch: int) -> np.ndarray:
    """Readings at ``(r + a·pitch, u + k·pitch)``, ``a`` in 0..2, ``k`` in -1..reach; zero
    outside the padded frame. Shape ``(len(rows) · len(cols), 3 · (reach + 2))``."""
    width = frame.shape[1]
    out = []
    for a in range(3):
        for k in range(-1, reach + 1):
            shifted = cols + pitch * k
            inside = (shifted >= 0) & (shifted < width)
            block = np.zeros((len(rows), len(cols)))
            block[:, inside] = frame[np.ix_(rows + pitch * a, shifted[inside])]
            out.append(block.reshape(-1))
    return np.stack(out, -1)


def load() -> tuple[int, tuple[list[int], list[int]], dict[int, np.ndarray], np.ndarray]:
    """The lens pitch, the (training, validation) frames used, their padded frames and
    the demixed targets (memory-mapped), read once for every fit."""
    system = SystemConfig.load(f"{DATA}/system.json")
    manifest = json.load(open(f"{DATA}/manifest.json", encoding="utf-8"))
    views = np.load(f"{DATA}/views.npy", mmap_mode="r")
    splits = (manifest["train_frames"][:80], manifest["val_frames"][:24])
    frames = {f: assemble_frame(torch.from_numpy(np.array(views[f])), system).numpy()
              for split in splits for f in split}
    demixed = np.load(f"{DATA}/demixed.npy", mmap_mode="r")
    return lens_pitch(system)[1], splits, frames, demixed


def relative_errors(data: tuple, cols: np.ndarray, reach: int) -> list[float]:
    """Validation relative squared error of the fit, per lens of :data:`LENSES`, on the
    data of :func:`load`."""
    pitch, splits, frames, demixed = data
    size = demixed.shape[-1]
    errors = []
    for lens in LENSES:
        miss = energy = 0.0
        for start in range(0, size, BAND):
            rows = np.arange(start, start + BAND)
            fits = []
            for split in splits:
                x = np.concatenate([readings(frames[f], rows, cols, reach, pitch)
                                    for f in split])
                t = np.concatenate([np.asarray(demixed[f, lens])[np.ix_(rows, cols)].ravel()
                                    for f in split])
                fits.append((np.c_[x, np.ones(len(x))], t))
            (x_train, t_train), (x_val, t_val) = fits
            coef, *_ = np.linalg.lstsq(x_train, t_train, rcond=None)
            miss += float(((x_val @ coef - t_val) ** 2).sum())
            energy += float((t_val**2).sum())
        errors.append(miss / energy)
    return errors


def main() -> None:
    data = load()
    print(f"| columns | reach (pitches) | relative squared error, lenses {LENSES} |")
    print("|---|---|---|")
    for label, cols, reaches in (("0-15 (left strip)", np.arange(16), (1, 2, 3, 4)),
                                 ("64-79", np.arange(64, 80), (2, 3, 4))):
        for reach in reaches:
            errors = relative_errors(data, cols, reach)
            print(f"| {label} | {reach} | {' / '.join(f'{e:.3f}' for e in errors)} |",
                  flush=True)


if __name__ == "__main__":
    main()
