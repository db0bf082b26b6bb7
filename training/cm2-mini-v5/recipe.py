"""What the probes that fine-tune `margin16` share: their command line and
`m16-edge32-ring8`'s recipe (from `margin16`, the edge strips weighted 32 and the outer
ring 8, seed 14, on the v2 data with the 16-px margin).

`margin16` was the bundled model while the probes ran; it no longer ships, and
`finetune.sh margin16` (after `finetune.sh edge16`) makes it again, as for finetune.sh's
own arms that start from it."""

from __future__ import annotations

import argparse
from pathlib import Path

from svcode_core.training import TrainConfig

#: `finetune.sh margin16`'s model, where these probes start
MARGIN16 = Path("runs/v5-margin16/best.safetensors")


def probe_parser(doc: str) -> argparse.ArgumentParser:
    """RUN, --data, --epochs and --threads; the description is ``doc``'s first paragraph."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", type=Path, default=Path("runs/data-v2-m16"))
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--init", type=Path, default=MARGIN16,
                        help=f"the model to start from (default {MARGIN16}, margin16)")
    return parser


def start_weights(path: Path) -> Path:
    """``path``, or a clear error naming the recipe that makes ``margin16``."""
    if not path.is_file():
        raise SystemExit(f"no model at {path}: `bash training/cm2-mini-v5/finetune.sh "
                         "margin16` makes margin16 (after the edge16 arm)")
    return path


def border_recipe(epochs: int = 4, patches: int = 3200) -> TrainConfig:
    """`m16-edge32-ring8`'s training settings."""
    return TrainConfig(epochs=epochs, batch_size=8, same_origin=8, lr=2e-4, warmup_steps=100,
                       beta=100.0, edge_weight=32.0, ring_weight=8.0,
                       patches_per_epoch=patches, val_patches=128, seed=14)  # fmt: skip
