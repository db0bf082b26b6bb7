#!/usr/bin/env bash
# cm2-mini v3 experiments: fine-tune the bundled v2 model on the v2 data (lr 2e-4, cosine,
# 3200 patches per epoch), one arm per question. Resumable over sessions (../resume.sh).
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
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../resume.sh" "runs/v3-$arm" "$here/$arm" --init pretrained "${extra[@]}" \
  --batch-size 8 --same-origin 8 --lr 2e-4 --warmup-steps 50 \
  --patches-per-epoch 3200 --val-patches 128 --seed 1
