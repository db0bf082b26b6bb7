#!/usr/bin/env bash
# The cm2-mini v2 recipe: realistic-instrument data, lattice masks, resumable over sessions.
# Usage (from the repository root): bash training/cm2-mini-v2/recipe.sh
# Regenerates the data (frame i depends only on the seed and i: the same 480 frames every
# time; about 1 CPU-second per frame), restores the committed resume state into runs/v2 if
# that folder holds none, and continues training from it.
set -euo pipefail
# Threads that wait sleep instead of spinning: on a shared machine spinning cost this run
# up to twice the CPU time per epoch.
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
here="$(cd "$(dirname "$0")" && pwd)"
svcode dataset --preset cm2-mini --frames 480 --out runs/data-v2 --seed 0 \
  --departures "$here/departures.json" --no-progress
if [ ! -f runs/v2/checkpoints/latest.json ] && [ -f "$here/run/checkpoints/latest.json" ]; then
  mkdir -p runs/v2 && cp -r "$here/run/." runs/v2/
fi
resume=()
[ -f runs/v2/checkpoints/latest.json ] && resume=(--resume)
svcode train --preset cm2-mini --data runs/data-v2 --out runs/v2 --model-config mini \
  --epochs 20 --batch-size 8 --same-origin 8 --lr 8e-4 --warmup-steps 200 \
  --patches-per-epoch 3200 --val-patches 128 --seed 0 --no-progress "${resume[@]}"
