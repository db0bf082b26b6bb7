#!/usr/bin/env bash
# The edge strips with the whole field in view: SV-CoDe trained from the start on whole
# 384-px sub-views (every patch holds both edge strips and the outer ring, instead of one
# 96-px patch in nine touching an edge) with the lens context out to two pitches (where the
# strips' one clean reading lies), the network on a grid four times coarser
# (whole-f4.json: pixel_unshuffle 4, 64 channels, the mini model's levels: 238-px reach
# instead of 58, at about the cost per pixel of the bundled model). The bundled model's
# loss, learning rate and pixels per epoch (200 sub-views = 3200 patches of 96 px), one
# exposure level. Resumable; run folder runs/v5-whole, kept state ./whole.
# GRID=2 trains the same on a grid twice coarser instead (whole-f2.json: pixel_unshuffle 2,
# 32 channels at the first level, at most 64: 119-px reach, about the same cost a step);
# run folder runs/v5-whole-f2 (its log and held-out report in ./whole-f2; no state kept).
# Usage (from the repository root): [GRID=2] bash training/cm2-mini-v5/whole.sh [svcode train options]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
grid="${GRID:-4}"
name=whole
[ "$grid" = 4 ] || name="whole-f$grid"
bash "$here/../resume.sh" "runs/v5-$name" "$here/$name" --model-config "$here/whole-f$grid.json" \
  --lens-context 2 --patch-size 384 --batch-size 1 --same-origin 1 \
  --patches-per-epoch 200 --val-patches 32 --epochs 20 --lr 8e-4 --warmup-steps 200 \
  --mse-weight 100 --normalise-exposure --precision bf16 --seed 0 "$@"
