#!/usr/bin/env bash
# The cm2-v2 model's training run: the learning curve's depth4-f4 network (4 and 3 levels on
# a grid four times coarser, 64 channels, lens context; depth4-f4.json) on 384-px patches
# of the cm2-v2 data (data.sh), 4 patches of one origin a step, 100 steps an epoch, 90
# epochs: about 20 CPU-hours on one thread of this 2-core machine. bf16, compiled from epoch
# 19 on (1.16x the eager bf16 step on this network: bench/results/training_speed_cm2-v2.md),
# loss (1 - SSIM) + 100 MSE, one exposure level, validation on 16 fixed patches after every
# epoch.
# Resumable across sessions: the run folder is runs/cm2-v2-long, its kept state ./run (one
# current state; ../cm2-mini-v2/snapshot.sh runs/cm2-v2-long training/cm2-v2/run running).
# Usage (from the repository root): bash training/cm2-v2/recipe.sh [svcode train options]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/resume.sh" runs/cm2-v2-long "$here/run" --model-config "$here/depth4-f4.json" \
  --lens-context --patch-size 384 --precision bf16 --normalise-exposure --mse-weight 100 \
  --epochs 90 --batch-size 4 --same-origin 4 --patches-per-epoch 400 --val-patches 16 \
  --lr 8e-4 --warmup-steps 200 --seed 0 --compile "$@"
