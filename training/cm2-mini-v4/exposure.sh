#!/usr/bin/env bash
# cm2-mini v4: the bundled model (v3 context-ring4) fine-tuned with one exposure level
# (--normalise-exposure: every frame brought to the reference level, as reconstruction
# does) on the v2 data, with the v3 recipe's loss (MSE weight 100, edge and ring weights 4);
# 6 epochs, lr 2e-4 after 100 warm-up steps, seed 12. Resumable over sessions
# (../resume.sh); the resume state goes to ./ARM.
#   exposure      one exposure level only
#   exposure-dim  also dimmer samples (each sample's photon level ×0.25–1, log-uniform)
# Usage (from the repository root): bash training/cm2-mini-v4/exposure.sh ARM
set -euo pipefail
arm="$1"
here="$(cd "$(dirname "$0")" && pwd)"
init="$here/../cm2-mini-v3/context-ring4/best.safetensors"  # bundled at the time
extra=()
case "$arm" in
  exposure) ;;
  exposure-dim) extra=(--photon-range 0.25 1) ;;
  *) echo "unknown arm: $arm (exposure, exposure-dim)" >&2; exit 2 ;;
esac
bash "$here/../resume.sh" "runs/v4-$arm" "$here/$arm" \
  --init "$init" --lens-context --mse-weight 100 --edge-weight 4 --ring-weight 4 \
  --normalise-exposure "${extra[@]}" --epochs 6 --batch-size 8 --same-origin 8 \
  --lr 2e-4 --warmup-steps 100 --patches-per-epoch 3200 --val-patches 128 --seed 12
