#!/usr/bin/env bash
# The cm2-mini v2 recipe: realistic-instrument data, lattice masks, resumable over sessions.
# Usage (from the repository root): bash training/cm2-mini-v2/recipe.sh
# Regenerates the data if needed, restores the committed resume state into runs/v2 if that
# folder holds none, and continues training from it (../resume.sh).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../resume.sh" runs/v2 "$here/run" --model-config mini \
  --epochs 20 --batch-size 8 --same-origin 8 --lr 8e-4 --warmup-steps 200 \
  --patches-per-epoch 3200 --val-patches 128 --seed 0
