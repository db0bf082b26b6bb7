"""Edge features with a larger step: do the masks use them once they can move?

Fine-tuned from the bundled model with `--edge-width 8` (`finetune.sh m16-edges8-e32-r8`),
the edge features' weights ended at 0.004 on average (the positional encoding's: 0.145)
and the held-out border as without them: from zero, at the recipe's learning rate, Adam
moved them by about 2 % of what a consistent gradient would have. This probe feeds the
edge features multiplied by --scale during training, which multiplies their weights'
effect per Adam step by that factor and leaves every other parameter's step as it was,
then writes the weights times --scale (`best-unscaled.safetensors`): an ordinary model
with edge features that computes what the trained one did.

A probe, not a product option. Usage (from the repository root; the v2 data with the
16-px margin, `MARGIN=16` in ../resume.sh):
    python training/cm2-mini-v5/edge_lr_probe.py RUN [--scale 30] [--threads 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from svcode_core.methods.model_file import load_model, save_model
from svcode_core.network import CoordMLP, base, edge_encoding
from svcode_core.pretrained import bundled_weights
from svcode_core.training import TrainConfig, Trainer, TrainingData


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", type=Path, default=Path("runs/data-v2-m16"))
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--scale", type=float, default=30.0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    base.edge_encoding = lambda *a, **k: args.scale * edge_encoding(*a, **k)
    weights = bundled_weights("cm2-mini")
    config = load_model(weights)[0].model_config.replace(edge_width=8)
    train = TrainConfig(epochs=args.epochs, batch_size=8, same_origin=8, lr=2e-4,
                        warmup_steps=100, beta=100.0, edge_weight=32.0, ring_weight=8.0,
                        patches_per_epoch=3200, val_patches=128, seed=14)
    trainer = Trainer(TrainingData(args.data), args.run, config, train, progress=False,
                      init_weights=weights)
    trainer.fit(resume=(args.run / "checkpoints" / "latest.json").is_file())
    model, system = load_model(args.run / "best.safetensors")
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, CoordMLP):
                for weight in (module.w_row, module.w_col):
                    weight[..., -2:] *= args.scale
    out = save_model(args.run / "best-unscaled.safetensors", model, system)
    print(f"best epoch {trainer.best.get('epoch')}: {out}")


if __name__ == "__main__":
    main()
