#!/usr/bin/env bash
# The learned baselines on the bundled SV-CoDe model's data (the v2 data: 480 cm2-mini
# frames through the realistic instrument departures, 432 for training), with its loss
# ((1 - SSIM) + 100 MSE on the reconstruction) and the exposure brought to one level as at
# reconstruction. 20 epochs of the 432 whole frames, about 9 CPU-minutes an epoch on one
# thread, so about 3 CPU-hours each against the bundled model's 10.3 (stopped earlier if
# the validation curve is flat). Resumable over sessions (../resume.sh); the resume state
# goes to ./ARCH, its learning curve to ./ARCH/log.csv.
#   multiwiener   MultiWienerNet
#   fouriernet    SV-FourierNet
# Usage (from the repository root): bash training/baselines/recipe.sh ARCH [svcode train
# options, e.g. --compile]
# then, to keep the state in the repository: bash training/cm2-mini-v2/snapshot.sh
# runs/baseline-ARCH training/baselines/ARCH running
set -euo pipefail
arch="${1:-}"
shift || true
case "$arch" in
  multiwiener|fouriernet) ;;
  *) echo "recipe: multiwiener or fouriernet" >&2; exit 2 ;;
esac
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../resume.sh" "runs/baseline-$arch" "$here/$arch" --method "$arch" \
  --mse-weight 100 --normalise-exposure --epochs 20 --batch-size 2 --lr 8e-4 \
  --warmup-steps 50 --seed 0 "$@"
