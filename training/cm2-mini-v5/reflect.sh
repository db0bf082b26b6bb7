#!/usr/bin/env bash
# Does mirrored padding win the border back for the whole model? Four more epochs of the
# bundled cm2-mini model (the recipe of its last fine-tuning, context-ring4: lr 2e-4,
# MSE weight 100, edge and ring weights 4, seed 12), one arm per padding:
#   reflect   every padded convolution of both stages mirrors (--padding reflect)
#   zeros     the same epochs with zero padding, as the model has it (the control)
# Resumable over sessions (../resume.sh).
# Usage (from the repository root): bash training/cm2-mini-v5/reflect.sh ARM
set -euo pipefail
arm="$1"
here="$(cd "$(dirname "$0")" && pwd)"
case "$arm" in
  reflect|zeros) ;;
  *) echo "reflect.sh: reflect or zeros" >&2; exit 2;;
esac
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
bash "$here/../resume.sh" "runs/v5-$arm" "$here/$arm" \
  --init "$here/../../src/svcode_core/weights/cm2-mini.safetensors" --padding "$arm" \
  --batch-size 8 --same-origin 8 --patches-per-epoch 3200 --val-patches 128 \
  --mse-weight 100 --edge-weight 4 --ring-weight 4 --epochs 4 --lr 2e-4 \
  --warmup-steps 100 --seed 12
