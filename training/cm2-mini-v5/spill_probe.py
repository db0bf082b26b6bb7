"""Is the sub-view's border lost because each lens view is cut at its window?

A point within the kernel radius ``m`` of the sub-view's edge spreads part of its light
past the window: onto the sensor, but outside the demixed view, which is all the
Recon-Net is given. This probe trains the Recon-Net alone on true, noiseless lens views of
the v2 data's objects (the nominal instrument's lens blur), twice from the same start on
the same patches, every 96-px output patch computed from its input enlarged by ``m`` on
every side (the same context for both arms), its coordinate masks those of the enlarged
patch:

- ``window``: each view cut at its sub-view window (zero beyond), as the model has it;
- ``spill``: each view running on past the window, as far as the sensor holds it.

Scored on whole validation sub-views: PSNR of the 16-px column strips, the 16-px row
strips along the top and bottom, the middle half, and all, against each truth's range.

Usage (from the repository root, the data of ``training/resume.sh``; one thread an arm)::

    python training/cm2-mini-v5/spill_probe.py --arm window --out runs/spill
    python training/cm2-mini-v5/spill_probe.py --arm spill --out runs/spill
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from fusion_probe import border_scores, summary  # this folder's probe: the same scores
from torch import nn

from svcode_core.network import ModelConfig
from svcode_core.network.models import ReconNet
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.training.dataset import TrainingData
from svcode_core.training.loss import stage_loss

PATCH, STRIDE, BATCH = 96, 48, 8


def lens_views(operator: CM2Operator, arm: str):
    """``object (S, S)`` → its nine lens views on the sub-view grid enlarged by the
    operator's margin ``m`` (:meth:`CM2Operator.lens_images` with ``past=m``): zero off the
    sensor, and for ``window`` zero outside the sub-view window too."""
    m, size = operator.margin, operator.system.sub_view_size
    keep = torch.ones(size + 2 * m, size + 2 * m)
    if arm == "window":
        keep = torch.zeros_like(keep)
        keep[m : m + size, m : m + size] = 1

    def views(obj: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return operator.lens_images(obj, past=m) * keep

    return views


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arm", required=True, choices=["window", "spill"])
    parser.add_argument("--data", type=Path, default=Path("runs/data-v2"))
    parser.add_argument("--out", type=Path, default=Path("runs/spill"))
    parser.add_argument("--frames", type=int, default=200, help="training frames used")
    parser.add_argument("--val-frames", type=int, default=12)
    parser.add_argument("--steps", type=int, default=1500, help="the learning-rate schedule's")
    parser.add_argument("--every", type=int, default=250, help="evaluate every N steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = TrainingData(args.data, allow_partial=True)
    operator = CM2Operator.from_system(data.system)
    m, size = operator.margin, data.system.sub_view_size
    views_of = lens_views(operator, args.arm)
    frames = list(data.train_frames[: args.frames])
    val = list(data.val_frames[: args.val_frames])
    objects = {f: data.read(data.objects[f]).float() for f in frames + val}
    views = {f: views_of(objects[f]) for f in frames + val}

    torch.manual_seed(args.seed)
    net = ReconNet(ModelConfig.mini())
    optim = torch.optim.Adam(net.parameters(), lr=8e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(optim, 8e-4, total_steps=args.steps,
                                                pct_start=0.1)  # fmt: skip
    rng = np.random.default_rng(args.seed)
    places = np.arange(0, size - PATCH + 1, STRIDE)

    def run(inputs: torch.Tensor, origins: torch.Tensor) -> torch.Tensor:
        """The Recon-Net on enlarged inputs at enlarged ``origins``, the margin cropped."""
        masks = net.masks_for(origins - m, size, tuple(inputs.shape[-2:]))
        return net.run(inputs, masks)[..., m : inputs.shape[-2] - m, m : inputs.shape[-1] - m]

    def evaluate() -> dict[str, float]:
        net.eval()
        with torch.no_grad():
            outs = [run(views[f][None], torch.tensor([[0, 0]]))[0, 0].clamp_min(0) for f in val]
            scores = [border_scores(out.numpy(), objects[f].numpy())
                      for out, f in zip(outs, val, strict=True)]  # fmt: skip
        net.train()
        return summary(scores)

    args.out.mkdir(parents=True, exist_ok=True)
    log, cpu = [], 0.0
    for step in range(1, args.steps + 1):
        picks = zip(rng.choice(frames, BATCH), rng.choice(places, BATCH),
                    rng.choice(places, BATCH), strict=True)  # fmt: skip
        inputs, target, origins = [], [], []
        for f, r, c in picks:
            inputs.append(views[f][:, r : r + PATCH + 2 * m, c : c + PATCH + 2 * m])
            target.append(objects[f][None, r : r + PATCH, c : c + PATCH])
            origins.append((r, c))
        start = time.process_time()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = run(torch.stack(inputs), torch.tensor(origins))
        loss = stage_loss(out.float(), torch.stack(target), 1.0, 100.0)
        optim.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optim.step()
        sched.step()
        cpu += time.process_time() - start
        if step % args.every == 0 or step == args.steps:
            scores = evaluate()
            log.append({"step": step, "cpu_s": round(cpu, 1), **scores})
            print(f"step {step} {args.arm} " + " ".join(f"{k} {v:.2f}" for k, v in
                                                       scores.items()), flush=True)  # fmt: skip
            (args.out / f"{args.arm}-log.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    main()
