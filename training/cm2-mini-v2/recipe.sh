#!/usr/bin/env bash
# The cm2-mini v2 recipe: realistic-instrument data, lattice masks, resumable over sessions.
# Usage (from the repository root): bash training/cm2-mini-v2/recipe.sh [RUN STATE [options]]
# Regenerates the data if needed, restores the committed resume state (STATE, default this
# folder's run/) into the run folder (RUN, default runs/v2) if that folder holds none, and
# continues training from it (../resume.sh). Further options are added to `svcode train`'s
# (a variant of this recipe, e.g. ../cm2-mini-v3/context-scratch.sh).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
run="${1:-runs/v2}" state="${2:-$here/run}"
shift $(( $# < 2 ? $# : 2 ))
bash "$here/../resume.sh" "$run" "$state" --model-config mini \
  --epochs 20 --batch-size 8 --same-origin 8 --lr 8e-4 --warmup-steps 200 \
  --patches-per-epoch 3200 --val-patches 128 --seed 0 "$@"
