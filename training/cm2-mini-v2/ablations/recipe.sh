#!/usr/bin/env bash
# The cm2-mini v2 ablations: the recipe of ../recipe.sh (same data, schedule, patches and
# seed) with the coordinate gate or the positional encoding switched off, so each epoch is
# comparable with the full model's at the same epoch. Resumable over sessions like it.
# Usage (from the repository root): bash training/cm2-mini-v2/ablations/recipe.sh no-coordgate|no-pe
# One thread each by default (OMP_NUM_THREADS), so both ablations can share two cores.
set -euo pipefail
ablation="$1"
case "$ablation" in no-coordgate|no-pe) ;; *) echo "ablation: no-coordgate or no-pe" >&2; exit 2;; esac
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
out="runs/v2-$ablation"
svcode dataset --preset cm2-mini --frames 480 --out runs/data-v2 --seed 0 \
  --departures "$here/../departures.json" --no-progress
if [ ! -f "$out/checkpoints/latest.json" ] && [ -f "$here/$ablation/checkpoints/latest.json" ]; then
  mkdir -p "$out" && cp -r "$here/$ablation/." "$out/"
fi
resume=()
[ -f "$out/checkpoints/latest.json" ] && resume=(--resume)
svcode train --preset cm2-mini --data runs/data-v2 --out "$out" --model-config mini \
  --ablation "$ablation" \
  --epochs 20 --batch-size 8 --same-origin 8 --lr 8e-4 --warmup-steps 200 \
  --patches-per-epoch 3200 --val-patches 128 --seed 0 --no-progress "${resume[@]}"
