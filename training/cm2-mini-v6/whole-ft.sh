#!/usr/bin/env bash
# The edge strips, fine-tuned: the cm2-mini model then bundled (v3's context-ring4)
# trained further on whole 384-px sub-views of the v2 data (no patch edge inside the
# field: every padded edge the network meets in training is the sub-view's own border),
# with that model's loss (SSIM + 100 MSE, edge strips and outer ring weighted 4) and exposure normalisation, bf16, one
# sub-view a step (200 an epoch: the pixels of 3200 patches of 96 px).
# Resumable; run folder runs/v6-whole-ft, kept state ./whole-ft.
# Usage (from the repository root): bash training/cm2-mini-v6/whole-ft.sh [svcode train options]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../resume.sh" runs/v6-whole-ft "$here/whole-ft" \
  --init "$here/../cm2-mini-v3/context-ring4/best.safetensors" --lens-context \
  --mse-weight 100 --edge-weight 4 --ring-weight 4 \
  --normalise-exposure --patch-size 384 --batch-size 1 --same-origin 1 \
  --patches-per-epoch 200 --val-patches 32 --epochs 8 --lr 2e-4 --warmup-steps 50 \
  --precision bf16 --seed 12 "$@"
