#!/usr/bin/env bash
# The cm2-mini v2 ablations: the recipe of ../recipe.sh (same data, schedule, patches and
# seed) with the coordinate gate or the positional encoding switched off, so each epoch is
# comparable with the full model's at the same epoch. Resumable over sessions like it.
# Usage (from the repository root): bash training/cm2-mini-v2/ablations/recipe.sh no-coordgate|no-pe
# One thread each by default (OMP_NUM_THREADS), so both ablations can share two cores.
set -euo pipefail
ablation="$1"
case "$ablation" in no-coordgate|no-pe) ;; *) echo "ablation: no-coordgate or no-pe" >&2; exit 2;; esac
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../../resume.sh" "runs/v2-$ablation" "$here/$ablation" --model-config mini \
  --ablation "$ablation" \
  --epochs 20 --batch-size 8 --same-origin 8 --lr 8e-4 --warmup-steps 200 \
  --patches-per-epoch 3200 --val-patches 128 --seed 0
