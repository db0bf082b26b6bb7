#!/usr/bin/env bash
# cm2-mini v3 experiments: fine-tune the bundled v2 model on the v2 data (lr 2e-4, cosine,
# 3200 patches per epoch), one arm per question. Resumable over sessions.
#   context      4 epochs, with the lens context (the demixing stage also sees every
#                lens's crop one pitch away), the loss as in v2 (SSIM + MSE, weights 1, 1)
#   mse          2 epochs, MSE weight 100 (SSIM barely sees the edge strips' brightness)
#   context-mse  2 epochs, both
# Usage (from the repository root): bash training/cm2-mini-v3/finetune.sh ARM
set -euo pipefail
arm="$1"
case "$arm" in
  context) extra=(--lens-context --epochs 4);;
  mse) extra=(--mse-weight 100 --epochs 2);;
  context-mse) extra=(--lens-context --mse-weight 100 --epochs 2);;
  *) echo "finetune: context, mse or context-mse" >&2; exit 2;;
esac
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
out="runs/v3-$arm"
svcode dataset --preset cm2-mini --frames 480 --out runs/data-v2 --seed 0 \
  --departures "$here/../cm2-mini-v2/departures.json" --no-progress
if [ ! -f "$out/checkpoints/latest.json" ] && [ -f "$here/$arm/checkpoints/latest.json" ]; then
  mkdir -p "$out" && cp -r "$here/$arm/." "$out/"
fi
resume=()
[ -f "$out/checkpoints/latest.json" ] && resume=(--resume)
svcode train --preset cm2-mini --data runs/data-v2 --out "$out" --init pretrained \
  "${extra[@]}" --batch-size 8 --same-origin 8 --lr 2e-4 --warmup-steps 50 \
  --patches-per-epoch 3200 --val-patches 128 --seed 1 --no-progress "${resume[@]}"
