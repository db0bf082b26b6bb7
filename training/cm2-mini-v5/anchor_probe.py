"""Border training with the demixing stage's inside held to a reference model.

The stage swap (README, "Which stage carries the trade") found the border's gain and the
haze regimes' loss both in the demixing stage. This probe fine-tunes with the border
weighted as `m16-edge32-ring8` does, and adds a third pair to the loss: the demixing
stage's output against a frozen reference model's (the start, `margin16`) on the pixels inside
the field that are neither in the outer ring nor in the edge strips (the pixels the
border weights leave at 1), so the inside is asked to stay as it was while the border
moves. The pair is scored like the stages (SSIM and MSE), both sides scaled by
sqrt(--anchor-weight) so that its MSE weighs that many times the demixing stage's own.

A probe, not a product option: `svcode train` with `Trainer._forward` extended here.
Usage (from the repository root; the v2 data with the 16-px margin, `MARGIN=16` in
../resume.sh):
    python training/cm2-mini-v5/anchor_probe.py RUN [--anchor-weight 30] [--threads 2]
"""

from __future__ import annotations

import torch
from recipe import border_recipe, probe_parser, start_weights

from svcode_core.methods.model_file import load_model
from svcode_core.training import Trainer, TrainingData
from svcode_core.training.loss import field_weights, in_field


class AnchoredTrainer(Trainer):
    """A :class:`Trainer` whose batches also hold the demixing stage's inside to
    ``reference``'s."""

    def __init__(self, *args, reference: torch.nn.Module, weight: float, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.reference = reference.to(self.device).eval().requires_grad_(False)
        self.scale = weight**0.5

    def _forward(self, net, batch, autocast=False):
        stages = super()._forward(net, batch, autocast)
        size = self.system.sub_view_size
        with torch.no_grad(), torch.autocast(self.device.type, dtype=torch.bfloat16,
                                             enabled=autocast):  # fmt: skip
            held, _ = self.reference(batch["views"].float(), batch["origin"], size)
        demixed = stages["demix"][0]
        patch = demixed.shape[-1]
        inside = in_field(batch["origin"], patch, size) & (
            field_weights(batch["origin"], patch, size, 2.0, 2.0) == 1.0)
        inside = inside.to(demixed.device, demixed.dtype) * self.scale
        stages["anchor"] = (demixed * inside, held.to(demixed.dtype) * inside)
        return stages


def main() -> None:
    parser = probe_parser(__doc__)
    parser.add_argument("--patches", type=int, default=3200, help="training patches per epoch")
    parser.add_argument("--anchor-weight", type=float, default=30.0)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    weights = start_weights(args.init)
    reference, _ = load_model(weights)
    config = border_recipe(args.epochs, args.patches)
    trainer = AnchoredTrainer(TrainingData(args.data), args.run, reference.model_config, config,
                              progress=False, init_weights=weights, reference=reference,
                              weight=args.anchor_weight)  # fmt: skip
    trainer.fit(resume=(args.run / "checkpoints" / "latest.json").is_file())
    print(f"best epoch {trainer.best.get('epoch')}: {args.run / 'best.safetensors'}")


if __name__ == "__main__":
    main()
