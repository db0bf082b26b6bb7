"""Does the Recon-Net lose the edge strips because it cannot tell a missing view from a
dark one?

In the 16-px strips at the field's left and right edges three of the nine lenses' images
fall off the sensor, and their demixing targets there are 0: to the Recon-Net a view that
is missing looks like a view of a dark object. The bundled model, given the *true* demixed
views instead of its own, still reconstructs the strips about 6 dB below the centre. This
probe trains the Recon-Net alone on the true demixed views (the dataset's targets) twice
from the same start: ``plain`` (each view one input channel, as the model has it) and
``coverage`` (each view with a second channel, 1 where its sub-view lies on the sensor,
:func:`svcode_core.physics.geometry.sensor_coverage`), then scores both on whole
validation sub-views: PSNR in the strips, in the centre and over the field.

Other arms: ``interior`` leaves the patch edges inside the sub-view out of the loss;
``reflect`` mirrors the image at every padded convolution's edge instead of padding with 0.
``--edge-share`` draws that share of every batch from the patches that touch the left or
right edge, so that the strips weigh in training what they weigh in the field.

Usage (from the repository root; the mini data of ``training/resume.sh``, or fewer frames
of the same recipe)::

    python training/cm2-mini-v5/fusion_probe.py --data runs/data-v2 --steps 1500 --out runs/fusion
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from svcode_core.evaluation.metrics import edge_columns, psnr_from_mse
from svcode_core.network import ModelConfig
from svcode_core.network.models import ReconNet
from svcode_core.physics.geometry import sensor_coverage
from svcode_core.training.dataset import TrainingData
from svcode_core.training.loss import EDGE_STRIP, stage_loss
from svcode_core.training.sampler import PatchDataset

MARGIN = 16  # px: the ``interior`` arm's loss leaves out this much of inner patch edges


def build(arm: str, seed: int) -> ReconNet:
    """The mini model's Recon-Net; with ``coverage`` its first convolution takes two
    channels per view (the view, its coverage)."""
    torch.manual_seed(seed)
    net = ReconNet(ModelConfig.mini())
    if arm == "coverage":  # (``interior`` differs from ``plain`` only in its loss)
        torch.manual_seed(seed)
        net.intro = nn.Conv2d(2, net.intro.out_channels, 3, padding=1)
    if arm == "reflect":  # every padded convolution mirrors the image instead of adding 0
        for conv in net.modules():
            if isinstance(conv, nn.Conv2d) and any(conv.padding):
                conv.padding_mode = "reflect"
    return net


def inputs(arm: str, demixed: torch.Tensor, cover: torch.Tensor) -> torch.Tensor:
    """``(B, 9, H, W)`` views, with each view's coverage interleaved for ``coverage``."""
    if arm != "coverage":
        return demixed
    both = torch.stack([demixed, cover.expand_as(demixed)], dim=2)  # (B, 9, 2, H, W)
    return both.flatten(1, 2)


def interior(origins: torch.Tensor, patch: int, size: int, margin: int) -> torch.Tensor:
    """``(B, 1, P, P)`` loss mask of the ``interior`` arm: 0 within ``margin`` px of a patch
    edge that lies inside the sub-view (there the truth depends on views the patch does not
    hold), 1 elsewhere and along the sub-view's own border, scaled to mean 1."""
    near = torch.arange(patch) < margin
    mask = torch.ones(len(origins), 1, patch, patch)
    for i, (r, c) in enumerate(origins.tolist()):
        rows = (near & (r > 0)) | (near.flip(0) & (r + patch < size))
        cols = (near & (c > 0)) | (near.flip(0) & (c + patch < size))
        mask[i, 0, rows] = 0
        mask[i, 0, :, cols] = 0
    return mask / mask.mean()


def run(net: ReconNet, views: torch.Tensor, origins: torch.Tensor, size: int) -> torch.Tensor:
    masks = net.masks_for(origins, size, tuple(views.shape[-2:]))
    return net.run(views, masks)


def psnr(a: np.ndarray, b: np.ndarray, span: float) -> float:
    return float(psnr_from_mse(np.mean((a - b) ** 2), span))


def border_scores(out: np.ndarray, truth: np.ndarray) -> tuple[float, float, float, float]:
    """PSNR of one whole sub-view against its truth's range: the column strips, the row
    strips (the same border along the top and bottom), the centre (the middle half), all."""
    size = len(truth)
    centre = slice(size // 4, 3 * size // 4)
    in_strips = edge_columns(size, EDGE_STRIP)
    in_rows = in_strips.T & ~in_strips
    span = float(truth.max() - truth.min()) or 1.0
    return (psnr(out[in_strips], truth[in_strips], span),
            psnr(out[in_rows], truth[in_rows], span),
            psnr(out[centre, centre], truth[centre, centre], span),
            psnr(out, truth, span))  # fmt: skip


def summary(scores: list[tuple[float, float, float, float]]) -> dict[str, float]:
    """The mean of :func:`border_scores` over sub-views, with the centre's lead on the strips."""
    strips, rows, middle, whole = np.mean(scores, axis=0)
    return {"strips": strips, "rows": rows, "centre": middle, "all": whole,
            "gap": middle - strips}


def evaluate(net: ReconNet, arm: str, data: TrainingData, frames: list[int],
             cover: torch.Tensor, gains: PatchDataset) -> dict[str, float]:  # fmt: skip
    """:func:`summary` of the validation ``frames``' whole sub-views."""
    size = data.system.sub_view_size
    scores = []
    net.eval()
    with torch.no_grad():
        for frame in frames:
            gain = gains.gain(frame)
            demixed = data.read(data.demixed[frame])[None] * gain
            truth = data.read(data.objects[frame]).numpy() * gain
            out = run(net, inputs(arm, demixed, cover[None]), torch.tensor([[0, 0]]), size)
            scores.append(border_scores(out[0, 0].clamp_min(0).numpy(), truth))
    net.train()
    return summary(scores)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("runs/data-v2"))
    parser.add_argument("--out", type=Path, default=Path("runs/fusion"))
    parser.add_argument("--steps", type=int, default=1500, help="the learning-rate schedule's")
    parser.add_argument("--until", type=int, help="stop after this step (default: --steps)")
    parser.add_argument("--every", type=int, default=250, help="evaluate every N steps")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--patch", type=int, default=96, help="patch size (px)")
    parser.add_argument("--val-frames", type=int, default=16)
    parser.add_argument("--arms", nargs="+", default=["plain", "coverage"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--edge-share", type=float, default=0.0,
                        help="share of each batch drawn from patches that touch the "
                             "sub-view's left or right edge (0: uniform, as the trainer)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    data = TrainingData(args.data, allow_partial=True)
    size = data.system.sub_view_size
    cover = sensor_coverage(data.system)  # (9, S, S)
    patches = PatchDataset(data, data.train_frames, noise=False, normalise_exposure=True,
                           patch=args.patch)  # fmt: skip
    val = data.val_frames[: args.val_frames]
    args.out.mkdir(parents=True, exist_ok=True)
    log = {arm: [] for arm in args.arms}
    nets = {arm: build(arm, args.seed) for arm in args.arms}
    optims = {arm: torch.optim.Adam(net.parameters(), lr=8e-4) for arm, net in nets.items()}
    scheds = {arm: torch.optim.lr_scheduler.OneCycleLR(opt, 8e-4, total_steps=args.steps,
                                                        pct_start=0.1)
              for arm, opt in optims.items()}  # fmt: skip
    rng = np.random.default_rng(args.seed)
    edge = np.flatnonzero(np.isin(patches.origins[:, 1], (0, size - patches.patch)))
    n_edge = round(args.batch * args.edge_share)
    seconds = dict.fromkeys(args.arms, 0.0)
    last = args.until or args.steps
    for step in range(1, last + 1):
        if n_edge:  # frame, then origin: edge origins for the first n_edge patches
            frames = rng.integers(0, len(patches.frames), args.batch)
            places = np.concatenate([rng.choice(edge, n_edge),
                                     rng.integers(0, len(patches.origins), args.batch - n_edge)])
            picks = frames * len(patches.origins) + places
        else:
            picks = rng.integers(0, len(patches), args.batch)
        batch = [patches[int(i)] for i in picks]
        demixed = torch.stack([b["demixed"] for b in batch])
        target = torch.stack([b["object"] for b in batch])
        origins = torch.stack([b["origin"] for b in batch])
        p = args.patch
        crops = torch.stack([cover[:, r:r + p, c:c + p] for r, c in origins.tolist()])
        for arm, net in nets.items():  # the same patches for both arms
            start = time.process_time()
            with torch.autocast("cpu", dtype=torch.bfloat16):
                out = run(net, inputs(arm, demixed, crops), origins, size)
            if arm == "interior":  # SSIM and squared error only where the truth is held
                keep = interior(origins, p, size, MARGIN)
                loss = stage_loss(out.float() * (keep > 0), target * (keep > 0), 1.0, 100.0,
                                  keep)
            else:
                loss = stage_loss(out.float(), target, 1.0, 100.0)
            optims[arm].zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            optims[arm].step()
            scheds[arm].step()
            seconds[arm] += time.process_time() - start
        if step % args.every == 0 or step == last:
            for arm, net in nets.items():
                scores = evaluate(net, arm, data, val, cover, patches)
                log[arm].append({"step": step, "cpu_s": round(seconds[arm], 1), **scores})
                print(f"step {step} {arm:9s} " + " ".join(f"{k} {v:.2f}" for k, v in
                                                          scores.items()), flush=True)  # fmt: skip
            (args.out / "log.json").write_text(json.dumps(log, indent=1) + "\n")


if __name__ == "__main__":
    main()
